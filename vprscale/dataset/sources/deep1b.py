"""Readers of the two real Deep1B layouts (docs/dataset.md), memory-mapped inside each read.

fvecs: records of a little-endian int32 ``d`` then ``d`` float32 (bvecs: uint8, ivecs: int32,
the other TEXMEX forms, read the same way); a directory of chunk files (``base_00``,
``base_01`` …) is one array in name order. fbin (and the other ``bin`` forms):
:mod:`~vprscale.dataset.sources.binfile`. Byte offsets are Python ints throughout (an int32
offset overflows past ~5.6 M rows × 96).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.errors import InputError
from vprscale.core.objects import is_url
from vprscale.dataset.sources.base import RowSource
from vprscale.dataset.sources.binfile import BinSource, bin_type
from vprscale.dataset.sources.chunks import local_chunks
from vprscale.dataset.sources.fetched import check_fetched
from vprscale.dataset.sources.fingerprint import file_fingerprint
from vprscale.dataset.sources.fvecs import read_vecs, record_bytes, vecs_type


class FvecsSource(RowSource):
    """One fvecs (or bvecs, ivecs) file, or a directory of such chunk files read as one array in name order."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path).absolute()  # tasks may run in another directory (a cluster's workers)
        self.name = str(self.path)
        if self.path.is_dir():
            files = local_chunks(self.path, what="fvecs files")
        elif self.path.is_file():
            files = [self.path]
        else:
            raise InputError(f"{self.path}: no such file or directory")
        self.files = files
        self.form, self.values = vecs_type(files[0].name)
        self.dim = self._first_dim(files[0])
        record = record_bytes(self.dim, self.values)
        counts = []
        for f in files:
            size = f.stat().st_size
            if size % record:
                raise InputError(
                    f"{f}: size {size} is not a multiple of the record size {record} "
                    f"(d = {self.dim}); the record at offset {size - size % record} is truncated"
                )
            if size and self._first_dim(f) != self.dim:
                raise InputError(f"{f}: offset 0: record dimension {self._first_dim(f)}, expected {self.dim}")
            counts.append(size // record)
        self.starts = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)])
        self.n_rows = int(self.starts[-1])

    @staticmethod
    def _first_dim(f: Path) -> int:
        with open(f, "rb") as fh:
            head = fh.read(4)
        if len(head) < 4:
            raise InputError(f"{f}: file too short for an fvecs record header")
        d = int(np.frombuffer(head, dtype="<i4")[0])
        if not 0 < d <= 1 << 16:
            raise InputError(f"{f}: offset 0: implausible record dimension {d}")
        return d

    def _read(self, start: int, stop: int) -> np.ndarray:
        record = record_bytes(self.dim, self.values)

        def records(i: int, lo: int, hi: int) -> np.ndarray:
            rows = int(self.starts[i + 1] - self.starts[i])
            return np.memmap(self.files[i], dtype="u1", mode="r", shape=(rows, record))[lo:hi]

        return read_vecs(self.starts, self.dim, self.values, start, stop, records, lambda i: str(self.files[i]))

    def fingerprint(self) -> dict[str, Any]:
        return {"format": self.form, "rows": self.n_rows, "dim": self.dim,
                "files": [file_fingerprint(f) for f in self.files]}

def open_deep1b(path: str | os.PathLike) -> RowSource:
    """A vecs file (fvecs, bvecs, ivecs), a directory of such chunks, or a ``bin`` file (``.fbin``,
    ``.f16bin``, ``.u8bin``, ``.i8bin``), local or by URL (http(s), or object storage, where a
    prefix of chunk objects is a directory): read by byte ranges where it lives."""
    from vprscale.dataset.sources.remote import RemoteBinSource, RemoteFvecsSource

    if is_url(path):
        return RemoteBinSource(str(path)) if bin_type(str(path)) is not None else RemoteFvecsSource(str(path))
    p = Path(path)
    if p.is_file():
        check_fetched(p)  # before its header is believed
    return BinSource(p) if bin_type(p.name) is not None else FvecsSource(p)
