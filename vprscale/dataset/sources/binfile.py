"""big-ann-benchmarks' ``bin`` files: a uint32 ``n``, a uint32 ``d``, then ``n·d`` values row-major,
typed by the suffix (``.fbin`` float32 — Deep1B, Text2Image, MS Turing —, ``.f16bin`` float16,
``.u8bin`` uint8 — BIGANN —, ``.i8bin`` int8 — MS SPACEV —, ``.ibin`` int32, their ground truth's
ids), memory-mapped inside each read. Byte offsets are Python ints throughout (an int32 offset
overflows past ~5.6 M rows × 96)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.errors import InputError
from vprscale.dataset.sources.base import RowSource
from vprscale.dataset.sources.fingerprint import file_fingerprint

BIN_TYPES = {".fbin": np.dtype("<f4"), ".f16bin": np.dtype("<f2"), ".u8bin": np.dtype("u1"),
             ".i8bin": np.dtype("i1"), ".ibin": np.dtype("<i4")}
HEADER = 8


def bin_type(name: str) -> np.dtype | None:
    """The value type a ``bin`` file's name says (its query string left out), else None."""
    base = name.split("?", 1)[0]
    return next((t for s, t in BIN_TYPES.items() if base.endswith(s)), None)


def check_header(name: str, n: int, d: int, values: np.dtype, size: int) -> None:
    """Refuse a header that does not describe a file of ``size`` bytes, in one line naming it."""
    expected = HEADER + values.itemsize * n * d  # Python ints: no overflow
    if d == 0 or size != expected:
        raise InputError(f"{name}: header says n = {n}, d = {d} (a file of {expected:,} bytes) but the file has "
                         f"{size:,} bytes")


class BinSource(RowSource):
    """A local ``bin`` file of any of the types (read as float32)."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path).absolute()  # tasks may run in another directory (a cluster's workers)
        self.name = str(self.path)
        self.values = bin_type(self.path.name)
        if self.values is None:
            raise InputError(f"{self.path}: not a bin file (.fbin, .f16bin, .u8bin, .i8bin or .ibin)")
        if not self.path.is_file():
            raise InputError(f"{self.path}: no such file")
        size = self.path.stat().st_size
        if size < HEADER:
            raise InputError(f"{self.path}: {size} bytes is too short for the 8-byte bin header")
        with open(self.path, "rb") as fh:
            n, d = (int(v) for v in np.frombuffer(fh.read(HEADER), dtype="<u4"))
        check_header(self.name, n, d, self.values, size)
        self.n_rows, self.dim = n, d

    def _read(self, start: int, stop: int) -> np.ndarray:
        if stop == start:
            return np.empty((0, self.dim), np.float32)
        mm = np.memmap(self.path, dtype=self.values, mode="r", offset=HEADER + self.values.itemsize * start * self.dim,
                       shape=(stop - start, self.dim))
        out = np.array(mm, dtype=np.float32)
        del mm
        return out

    def fingerprint(self) -> dict[str, Any]:
        return {"format": self.path.suffix[1:], "rows": self.n_rows, "dim": self.dim,
                "files": [file_fingerprint(self.path)]}
