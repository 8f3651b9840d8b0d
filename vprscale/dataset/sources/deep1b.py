"""Readers of the two real Deep1B layouts (docs/dataset.md), memory-mapped inside each read.

fvecs: records of a little-endian int32 ``d`` then ``d`` float32; a directory of chunk
files (``base_00``, ``base_01`` …) is one array in name order.
fbin: uint32 ``n``, uint32 ``d``, then ``n·d`` float32 row-major.
Byte offsets are Python ints throughout (an int32 offset overflows past ~5.6 M rows × 96).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.errors import InputError
from vprscale.core.objects import is_url
from vprscale.dataset.sources.base import RowSource
from vprscale.dataset.sources.fingerprint import file_fingerprint
from vprscale.dataset.sources.fvecs import read_fvecs


class FvecsSource(RowSource):
    """One fvecs file, or a directory of fvecs chunk files read as one array in name order."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.name = str(self.path)
        if self.path.is_dir():
            files = sorted(p for p in self.path.iterdir() if p.is_file() and not p.name.startswith("."))
            if not files:
                raise InputError(f"{self.path}: directory holds no fvecs files")
        elif self.path.is_file():
            files = [self.path]
        else:
            raise InputError(f"{self.path}: no such file or directory")
        self.files = files
        self.dim = self._first_dim(files[0])
        record = 4 * (self.dim + 1)
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
        def records(i: int, lo: int, hi: int) -> np.ndarray:
            rows = int(self.starts[i + 1] - self.starts[i])
            return np.memmap(self.files[i], dtype="<i4", mode="r", shape=(rows, self.dim + 1))[lo:hi]

        return read_fvecs(self.starts, self.dim, start, stop, records, lambda i: str(self.files[i]))

    def fingerprint(self) -> dict[str, Any]:
        return {"format": "fvecs", "rows": self.n_rows, "dim": self.dim,
                "files": [file_fingerprint(f) for f in self.files]}


class FbinSource(RowSource):
    """A big-ann-benchmarks ``.fbin`` file."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.name = str(self.path)
        if not self.path.is_file():
            raise InputError(f"{self.path}: no such file")
        size = self.path.stat().st_size
        if size < 8:
            raise InputError(f"{self.path}: {size} bytes is too short for the 8-byte fbin header")
        with open(self.path, "rb") as fh:
            n, d = (int(v) for v in np.frombuffer(fh.read(8), dtype="<u4"))
        expected = 8 + 4 * n * d  # Python ints: no overflow
        if d == 0 or size != expected:
            raise InputError(
                f"{self.path}: header says n = {n}, d = {d} (file of {expected} bytes) "
                f"but the file has {size} bytes"
            )
        self.n_rows, self.dim = n, d

    def _read(self, start: int, stop: int) -> np.ndarray:
        mm = np.memmap(self.path, dtype="<f4", mode="r", offset=8 + 4 * start * self.dim,
                       shape=(stop - start, self.dim))
        out = np.array(mm, dtype=np.float32)
        del mm
        return out

    def fingerprint(self) -> dict[str, Any]:
        return {"format": "fbin", "rows": self.n_rows, "dim": self.dim,
                "files": [file_fingerprint(self.path)]}


def open_deep1b(path: str | os.PathLike) -> RowSource:
    """An fvecs file, a directory of fvecs chunks, or an ``.fbin`` file, local or by URL (http(s),
    or object storage, where a prefix of fvecs chunk objects is a directory): read by byte ranges
    where it lives."""
    from vprscale.dataset.sources.remote import RemoteFbinSource, RemoteFvecsSource

    if is_url(path):
        if str(path).split("?", 1)[0].endswith(".fbin"):
            return RemoteFbinSource(str(path))
        return RemoteFvecsSource(str(path))
    p = Path(path)
    if p.is_file() and p.suffix in {".fbin", ".u8bin"} or p.name.endswith(".fbin"):
        return FbinSource(p)
    return FvecsSource(p)
