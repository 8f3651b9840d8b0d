"""A directory of ``.npy`` shards read as one array in name order: what LAION-style embedding
pipelines (clip-retrieval, embedding-reader, autofaiss) write, ``img_emb_0.npy``,
``img_emb_1.npy`` …, each memory-mapped inside the read that needs it."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.errors import InputError
from vprscale.dataset.sources.base import RowSource, part_spans
from vprscale.dataset.sources.chunks import local_chunks
from vprscale.dataset.sources.fingerprint import file_fingerprint


def open_npy(path: Path) -> np.ndarray:
    """A memory map of an ``.npy`` file, or a one-line error naming what is wrong with it."""
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(f"{path}: not a readable .npy array ({str(exc).splitlines()[0][:160]})") from None


def check_rows(path: Path, a: np.ndarray) -> None:
    """Refuse anything but a 2-D array of float or integer descriptor values."""
    if a.ndim != 2 or a.dtype.kind not in "fiu" or a.shape[1] == 0:
        raise InputError(f"{path}: a 2-D array of descriptor rows expected, not {a.ndim}-D {a.dtype} {a.shape}")


class NpyShardsSource(RowSource):
    """Every ``.npy`` file of a directory, in name order (numbers as numbers), as one array."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path).absolute()  # tasks may run in another directory (a cluster's workers)
        self.name = str(self.path)
        self.files = local_chunks(self.path, ".npy", ".npy shards")
        counts = []
        for f in self.files:
            a = open_npy(f)
            check_rows(f, a)
            if counts and a.shape[1] != self.dim:
                raise InputError(f"{f}: rows of {a.shape[1]} values, the shards before it {self.dim}")
            self.dim = int(a.shape[1])
            counts.append(int(a.shape[0]))
        self.starts = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)])
        self.n_rows = int(self.starts[-1])

    def _read(self, start: int, stop: int) -> np.ndarray:
        out = np.empty((stop - start, self.dim), np.float32)
        for i, a, b in part_spans(self.starts, start, stop):
            at = int(self.starts[i]) + a - start
            out[at : at + b - a] = np.load(self.files[i], mmap_mode="r")[a:b]
        return out

    def fingerprint(self) -> dict[str, Any]:
        return {"format": "npy shards", "rows": self.n_rows, "dim": self.dim,
                "files": [file_fingerprint(f) for f in self.files]}
