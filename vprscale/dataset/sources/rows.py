"""Row files of your own (docs/bring-your-own.md), in any of the forms the field's data lives in,
behind one opener (:func:`open_rows`): ``.npy`` (a file, or a directory of shards), the ``bin``
forms (``.fbin``, ``.f16bin``, ``.u8bin``, ``.i8bin``), fvecs and bvecs (a file or a directory of
chunks), an HDF5 dataset (``file.hdf5:train``) and a Parquet list column (``file.parquet:emb``,
or a directory of Parquet files), local or by URL (http(s), or object storage, where a prefix of
objects is a directory); and labels,
ground truth and positions beside them."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.errors import InputError
from vprscale.core.objects import is_url
from vprscale.dataset.sources.base import RowSource
from vprscale.dataset.sources.deep1b import FvecsSource, open_deep1b
from vprscale.dataset.sources.fingerprint import file_fingerprint
from vprscale.dataset.sources.hdf5 import SUFFIXES as HDF5_SUFFIXES
from vprscale.dataset.sources.hdf5 import Hdf5Source, read_ids
from vprscale.dataset.sources.parquetrows import ParquetRowsSource
from vprscale.dataset.sources.remote import RemoteNpySource, prefix_suffixes
from vprscale.dataset.sources.shards import NpyShardsSource, check_rows, open_npy


class NpySource(RowSource):
    """A 2-D ``.npy`` file of floats or integers (any width; read as float32)."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path).absolute()  # tasks may run in another directory (a cluster's workers)
        self.name = str(self.path)
        a = open_npy(self.path)
        check_rows(self.path, a)
        self.n_rows, self.dim = int(a.shape[0]), int(a.shape[1])

    def _read(self, start: int, stop: int) -> np.ndarray:
        a = np.load(self.path, mmap_mode="r")  # opened in the task: no array in the graph
        return np.array(a[start:stop], dtype=np.float32)

    def fingerprint(self) -> dict[str, Any]:
        return {"format": "npy", "rows": self.n_rows, "dim": self.dim, "files": [file_fingerprint(self.path)]}


def open_rows(spec: str | os.PathLike) -> RowSource:
    """Descriptor rows from any of the forms of the module's docstring, chosen by name: a
    ``PATH:NAME`` whose path is an HDF5 file names its dataset, one whose path is a Parquet
    file (or a directory of them) its list column; a directory of ``.npy`` files is shards,
    any other directory vecs chunks."""
    text = str(spec)
    head, _, key = text.rpartition(":")
    if is_url(text):  # the same forms by URL; a prefix of objects is a folder
        return _open_url(text)
    if head and Path(head).suffix in HDF5_SUFFIXES:
        return Hdf5Source(head, key)
    if Path(text).suffix in HDF5_SUFFIXES:
        return Hdf5Source(text, None)  # its one 2-D dataset, as a Parquet file's one list column
    for path, column in ((Path(head), key), (Path(text), None)) if head else ((Path(text), None),):
        if path.suffix == ".parquet" or path.is_dir() and any(path.glob("*.parquet")):
            return ParquetRowsSource(path, column or None)
    p = Path(text)
    if p.suffix == ".npy":
        return NpySource(p)
    if p.is_dir() and any(p.glob("*.npy")):
        return NpyShardsSource(p)
    return open_deep1b(p)


def _open_url(text: str) -> RowSource:
    """:func:`open_rows` of a URL: a key after the last colon names an HDF5 dataset or a Parquet
    column (of a file, or of a prefix of Parquet objects); a prefix of ``.npy`` objects is shards."""
    head, _, key = text.rpartition(":")
    if Path(head.split("?", 1)[0]).suffix in HDF5_SUFFIXES:
        return Hdf5Source(head, key)
    if Path(text.split("?", 1)[0]).suffix in HDF5_SUFFIXES:
        return Hdf5Source(text, None)
    keyed = "/" not in key and not key.isdigit()  # not a port, nor a path
    listed: dict[str, set[str]] = {}  # what a prefix holds, asked of the storage once

    def holds(base: str, suffix: str) -> bool:
        if Path(base.split("?", 1)[0]).suffix == suffix:
            return True
        if base not in listed:
            listed[base] = prefix_suffixes(base)
        return suffix in listed[base]

    for base, column in ((head, key), (text, None)) if keyed else ((text, None),):
        if holds(base, ".parquet"):
            return ParquetRowsSource(base, column)
    return RemoteNpySource(text) if holds(text, ".npy") else open_deep1b(text)


def neighbour_ids(path: Path) -> np.ndarray:
    """The neighbour ids of a ground-truth file of the field, ``(n, k)`` int32: big-ann-benchmarks'
    ``.ibin`` (a uint32 ``n`` and ``k``, the ids, then optionally as many float32 distances) or
    TEXMEX's ``.ivecs`` (records of an int32 ``k`` then ``k`` ids)."""
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    size = path.stat().st_size
    if path.suffix == ".ibin":
        with open(path, "rb") as fh:
            head = fh.read(8)
        n, k = (int(v) for v in np.frombuffer(head.ljust(8, b"\0"), "<u4"))
        if len(head) < 8 or k == 0 or size not in (8 + 4 * n * k, 8 + 8 * n * k):
            raise InputError(f"{path}: header says n = {n}, k = {k}: a file of {8 + 4 * n * k:,} bytes (ids) or "
                             f"{8 + 8 * n * k:,} (ids and distances), but it has {size:,}")
        return np.memmap(path, "<i4", mode="r", offset=8, shape=(n, k))
    source = FvecsSource(path)  # the size checked against the first record's k, as any vecs file's
    rec = np.memmap(path, "<i4", mode="r", shape=(source.n_rows, source.dim + 1))
    bad = np.flatnonzero(rec[:, 0] != source.dim)  # every record's k: records of another k shift all after them
    if bad.size:
        at, k = int(bad[0]) * 4 * (source.dim + 1), int(rec[bad[0], 0])
        raise InputError(f"{path}: offset {at:,}: a record of k = {k}, the first holds {source.dim}; every record of "
                         "an .ivecs ground truth must hold as many ids")
    return rec[:, 1:]


def read_labels(path: str | os.PathLike, n: int, what: str) -> np.ndarray:
    """``n`` labels (one per query row), read whole: a 1-D integer ``.npy`` array, or the nearest
    neighbour (first column) of a ground-truth ``.ibin`` or ``.ivecs`` file or of an HDF5 dataset
    (``FILE.hdf5:neighbors``, ann-benchmarks' own)."""
    p = Path(path)
    head, _, key = str(path).rpartition(":")
    if head and Path(head).suffix in HDF5_SUFFIXES:
        a = read_ids(head, key)
        a = a[:, 0] if a.ndim == 2 else a
    elif p.suffix in (".ibin", ".ivecs"):
        a = np.asarray(neighbour_ids(p)[:, 0])
    elif p.suffix != ".npy":
        raise InputError(f"{p}: {what} must be an .npy array of integers (or an .ibin, .ivecs or HDF5 "
                         "FILE.hdf5:DATASET ground truth), one per query row")
    else:
        a = open_npy(p)
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
        a = open_npy(p)
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


SEQUENCE_COLUMNS = ("sequence_key", "sequence", "seq")  # a table's sequence column, first found (MSLS's first)
FRAME_COLUMNS = ("frame_number", "frame")


def read_sequences(path: str | os.PathLike, n: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    """``(sequence, frame)`` of ``n`` rows, int64: which sequence each row belongs to (ids numbered
    by first appearance when the file names them by key) and its frame number. An ``.npy`` of two
    integer columns, or a CSV or Parquet table with a ``sequence_key`` (or ``sequence``) and a
    ``frame_number`` (or ``frame``) column, one row per descriptor row: MSLS's ``seq_info.csv``
    as it is."""
    p = Path(path)
    if p.suffix == ".npy":
        a = open_npy(p)
        if a.ndim != 2 or a.shape[1] != 2 or not np.issubdtype(a.dtype, np.integer):
            raise InputError(f"{p}: {what} must be integers in 2 columns (sequence, frame number), not "
                             f"{a.ndim}-D {a.dtype} {a.shape}")
        sequence, frame = np.asarray(a[:, 0], np.int64), np.asarray(a[:, 1], np.int64)
    elif p.suffix in (".csv", ".parquet"):
        table = _read_table(p)
        seq_col = next((c for c in SEQUENCE_COLUMNS if c in table.column_names), None)
        frame_col = next((c for c in FRAME_COLUMNS if c in table.column_names), None)
        if seq_col is None or frame_col is None:
            raise InputError(f"{p}: {what} needs a {' or '.join(SEQUENCE_COLUMNS[:2])} column and a "
                             f"{' or '.join(FRAME_COLUMNS)} column; it has {', '.join(table.column_names) or 'none'}")
        sequence = _column_ids(p, table[seq_col], seq_col)
        frame = _column_ints(p, table[frame_col], frame_col)
    else:
        raise InputError(f"{p}: {what} must be an .npy of (sequence, frame number) rows, or a .csv or .parquet "
                         "table with sequence_key and frame_number columns")
    if len(sequence) != n:
        raise InputError(f"{p}: {len(sequence):,} {what} rows for {n:,} descriptor rows")
    return sequence, frame


def _read_table(p: Path) -> Any:
    import pyarrow as pa
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq

    try:
        return pq.read_table(p) if p.suffix == ".parquet" else pacsv.read_csv(p)
    except (OSError, pa.ArrowInvalid) as exc:
        raise InputError(f"{p}: cannot be read as {p.suffix[1:].upper()} ({str(exc).splitlines()[0]})") from None


def _nulls(p: Path, column: Any, name: str) -> None:
    if column.null_count:
        row = int(np.flatnonzero(np.asarray(column.is_null()))[0])
        raise InputError(f"{p}: row {row:,} has no {name}")


def _column_ids(p: Path, column: Any, name: str) -> np.ndarray:
    """A sequence column as int64 ids: integers as they are, keys numbered by first appearance."""
    _nulls(p, column, name)
    values = column.to_numpy(zero_copy_only=False)
    if np.issubdtype(values.dtype, np.integer):
        return values.astype(np.int64)
    _, first, inverse = np.unique(values.astype(str), return_index=True, return_inverse=True)
    rank = np.empty(len(first), np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    return rank[inverse.ravel()]


def _column_ints(p: Path, column: Any, name: str) -> np.ndarray:
    _nulls(p, column, name)
    values = column.to_numpy(zero_copy_only=False)
    if not np.issubdtype(values.dtype, np.integer):
        raise InputError(f"{p}: {name} must be integers, not {values.dtype}")
    return values.astype(np.int64)
