"""Row files of your own (docs/bring-your-own.md): ``.npy`` arrays beside the fvecs and
``.fbin`` readers of :mod:`.deep1b`, behind one opener."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.errors import InputError
from vprscale.dataset.sources.base import RowSource
from vprscale.dataset.sources.deep1b import open_deep1b
from vprscale.dataset.sources.fingerprint import file_fingerprint


def _open_npy(path: Path) -> np.ndarray:
    """A memory map of an ``.npy`` file, or a one-line error naming what is wrong with it."""
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(f"{path}: not a readable .npy array ({str(exc).splitlines()[0][:160]})") from None


class NpySource(RowSource):
    """A 2-D float ``.npy`` file (any float width; read as float32)."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.name = str(self.path)
        a = _open_npy(self.path)
        if a.ndim != 2 or not np.issubdtype(a.dtype, np.floating) or a.shape[1] == 0:
            raise InputError(f"{self.path}: a 2-D float array of descriptor rows expected, not {a.ndim}-D {a.dtype} "
                             f"{a.shape}")
        self.n_rows, self.dim = int(a.shape[0]), int(a.shape[1])

    def _read(self, start: int, stop: int) -> np.ndarray:
        a = np.load(self.path, mmap_mode="r")  # opened in the task: no array in the graph
        return np.array(a[start:stop], dtype=np.float32)

    def fingerprint(self) -> dict[str, Any]:
        return {"format": "npy", "rows": self.n_rows, "dim": self.dim, "files": [file_fingerprint(self.path)]}


def open_rows(path: str | os.PathLike) -> RowSource:
    """Descriptor rows from an ``.npy``, ``.fbin`` or fvecs file (or a directory of fvecs chunks)."""
    p = Path(path)
    return NpySource(p) if p.suffix == ".npy" else open_deep1b(p)


def read_labels(path: str | os.PathLike, n: int, what: str) -> np.ndarray:
    """A 1-D integer ``.npy`` array of ``n`` labels (one per query row), read whole."""
    p = Path(path)
    if p.suffix != ".npy":
        raise InputError(f"{p}: {what} must be an .npy array of integers, one per query row")
    a = _open_npy(p)
    if a.ndim != 1 or not np.issubdtype(a.dtype, np.integer):
        raise InputError(f"{p}: {what} must be a 1-D integer array, not {a.ndim}-D {a.dtype}")
    if len(a) != n:
        raise InputError(f"{p}: {len(a):,} {what} values for {n:,} query rows")
    if a.dtype.kind == "u" and a.size and a.max() > np.iinfo(np.int64).max:  # would wrap to a negative label
        row = int(np.argmax(a > np.iinfo(np.int64).max))
        raise InputError(f"{p}: row {row:,} holds {int(a[row])}, beyond any row number (an unsigned −1? "
                         "write −1, no truth, as a signed integer)")
    return np.asarray(a, np.int64)


NUMBER = r"-?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?"  # a coordinate in an image's name


def read_positions(path: str | os.PathLike, n: int, what: str) -> np.ndarray:
    """Positions in metres, one row per image, as float64 ``(n, 2)`` or ``(n, 3)``: an ``.npy``
    of UTM easting and northing (or x, y, z), or a text file of image names, one per line, in
    the ``…@UTM_east@UTM_north@…`` form of VPR-methods-evaluation's exports (pitts30k, msls, …)."""
    p = Path(path)
    if p.suffix == ".npy":
        a = _open_npy(p)
        if a.ndim != 2 or a.shape[1] not in (2, 3) or not (np.issubdtype(a.dtype, np.floating)
                                                          or np.issubdtype(a.dtype, np.integer)):
            raise InputError(f"{p}: {what} must be numbers in 2 or 3 columns (UTM east, north; or x, y, z), not "
                             f"{a.ndim}-D {a.dtype} {a.shape}")
        pos = np.asarray(a, np.float64)
    else:
        try:
            lines = p.read_text().splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"{p}: {what}: not a readable text file of image names ({exc})") from None
        pos = np.empty((len(lines), 2))
        for i, line in enumerate(lines):
            fields = Path(line.strip()).name.split("@")  # …@UTM_east@UTM_north@…: the first two fields after an @
            if len(fields) < 4 or not all(re.fullmatch(NUMBER, f) for f in fields[1:3]):
                raise InputError(f"{p}: line {i + 1:,} ({line.strip()[:80]!r}) has no @UTM_east@UTM_north@ in its name "
                                 "(two numbers between its first three @)")
            pos[i] = float(fields[1]), float(fields[2])
    if len(pos) != n:
        raise InputError(f"{p}: {len(pos):,} {what} for {n:,} rows")
    bad = np.flatnonzero(~np.isfinite(pos).all(axis=1))
    if len(bad):
        raise InputError(f"{p}: row {bad[0]:,} of the {what} is not a finite number")
    return pos
