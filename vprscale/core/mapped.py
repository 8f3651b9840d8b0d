"""``.npy`` files written through a memory map, with their disk blocks allocated first.

A page of a memory-mapped file that the filesystem cannot back (a full disk) is not an error
the writer can catch: the kernel kills the process with SIGBUS, and a job dies without a word.
Allocating the whole file before it is mapped turns a full disk into an ``OSError`` (ENOSPC)
at the start, which the commands report in one line like any other full disk.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def allocated_memmap(path: Path, dtype: np.dtype | type, shape: tuple[int, ...]) -> np.memmap:
    """A new ``.npy`` file at ``path`` of ``shape`` and ``dtype``, its blocks allocated, mapped for writing."""
    dtype = np.dtype(dtype)
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": np.lib.format.dtype_to_descr(dtype),
                                                 "fortran_order": False, "shape": tuple(shape)})
        size = f.tell() + dtype.itemsize * int(np.prod(shape, dtype=np.int64))
        f.flush()
        if size > f.tell():
            os.posix_fallocate(f.fileno(), 0, size)
    return np.lib.format.open_memmap(path, mode="r+")
