"""``vprscale build --msls ROOT --cities cph,sf --descriptors FILE``: MSLS as a store.

The database images of the chosen cities are the references, their query images the query
set ``msls``, city after city, each side in MSLS's own order (:mod:`.msls`); the descriptors
come from the user's file, keyed by image, in whatever order it holds them (reordered out of
core, :mod:`.shuffle`). Beside the full layout of docs/dataset.md the store keeps what MSLS's
tasks need (docs/bring-your-own.md, "MSLS"): each row's image key, sequence and frame number,
city, panorama flag, subtasks and position. A query row's frame truth is its nearest database
image of the same city within the threshold (25 m), so every frame-radius figure works too.
"""

from __future__ import annotations

import hashlib
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.errors import InputError
from vprscale.dataset.msls import SUBTASKS, Side, key_rows, parse_cities, read_side
from vprscale.dataset.own import NAME, StoreRows, truth_from_positions, write_store
from vprscale.dataset.sources.base import RowSource
from vprscale.dataset.sources.rows import open_rows

NOISE = "msls"  # the store's one query set
KEY_BATCH = 1 << 20  # keys encoded at a time


@dataclass
class MslsRequest:
    """What ``vprscale build --msls`` was asked for."""

    root: str
    cities: str
    descriptors: str
    out: Path
    keys: str | None = None  # a text file of keys, one per row of --descriptors (not a keyed Parquet file)
    name: str = "msls"
    threshold_m: float = 25.0
    force: bool = False
    workers: int = 2
    scheduler: str | None = None
    quiet: bool = False


def open_keyed(path: str, keys: str | None) -> tuple[RowSource, Any]:
    """``(rows, keys)`` of the descriptors: a Parquet file with a ``key`` column and one descriptor
    column (``FILE.parquet``, or ``FILE.parquet:COLUMN``), or rows in any form ``--ref`` takes with
    ``--keys``, a text file of their keys, one per line."""
    import pyarrow as pa
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq

    if keys is not None:
        source = open_rows(path)
        try:
            table = pacsv.read_csv(keys, read_options=pacsv.ReadOptions(column_names=["key"]),
                                   parse_options=pacsv.ParseOptions(delimiter="\t", quote_char=False),
                                   convert_options=pacsv.ConvertOptions(column_types={"key": pa.string()}))
        except (OSError, pa.ArrowInvalid) as exc:
            raise InputError(f"--keys {keys}: cannot be read as one key a line ({str(exc).splitlines()[0]})") from None
        if table.num_rows != source.n_rows:
            raise InputError(f"--keys {keys}: {table.num_rows:,} keys for {source.n_rows:,} descriptor rows")
        return source, table["key"].combine_chunks()
    file, _, column = path.partition(":") if not Path(path).is_file() else (path, "", "")
    if Path(file).suffix != ".parquet":
        raise InputError(f"--descriptors {path}: a Parquet file with a key column, or give --keys (a text file of "
                         "the rows' keys, one a line)")
    try:
        schema = pq.read_schema(file)
    except (OSError, pa.ArrowInvalid) as exc:
        raise InputError(f"--descriptors {file}: cannot be read as Parquet ({str(exc).splitlines()[0]})") from None
    if "key" not in schema.names:
        raise InputError(f"--descriptors {file}: no key column (it has {', '.join(schema.names)})")
    if not column:
        lists = [f.name for f in schema if pa.types.is_list(f.type) or pa.types.is_fixed_size_list(f.type)
                 or pa.types.is_large_list(f.type)]
        if len(lists) != 1:
            raise InputError(f"--descriptors {file}: name the descriptor column, {file}:COLUMN "
                             f"({len(lists)} list columns: {', '.join(lists) or 'none'})")
        column = lists[0]
    source = open_rows(f"{file}:{column}")
    return source, pq.read_table(file, columns=["key"])["key"].combine_chunks()


def key_bytes(keys: Any) -> np.ndarray:
    """Image keys as a ``(n, width)`` uint8 array of their UTF-8 bytes, zero-padded: a plain
    numeric array every Zarr reader opens (:func:`vprscale.dataset.store.read_keys` reads it back)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    keys = keys.cast(pa.string())
    width = max(1, int(pc.max(pc.binary_length(keys)).as_py() or 1))
    out = np.zeros((len(keys), width), np.uint8)
    for a in range(0, len(keys), KEY_BATCH):
        part = keys.slice(a, KEY_BATCH)
        offsets = np.frombuffer(part.buffers()[1], np.int32)[part.offset : part.offset + len(part) + 1]
        data = np.frombuffer(part.buffers()[2], np.uint8)
        lengths = np.diff(offsets)
        row = np.repeat(np.arange(len(part)), lengths)
        col = np.arange(offsets[-1] - offsets[0]) - np.repeat(offsets[:-1] - offsets[0], lengths)
        out[a + row, col] = data[offsets[0] : offsets[-1]]
    return out


def _truth(db: Side, q: Side, radius_m: float) -> np.ndarray:
    """Each query image's nearest database image of its city within ``radius_m`` (−1: none, or a
    test city without positions). Cities are apart: UTM coordinates of two cities may coincide."""
    gt = np.full(len(q), -1, np.int64)
    if db.pos is None or q.pos is None:
        return gt
    for c in np.unique(q.city):
        rows, refs = np.flatnonzero(q.city == c), np.flatnonzero(db.city == c)
        if len(refs):
            near = truth_from_positions(db.pos[refs], q.pos[rows], radius_m)
            gt[rows] = np.where(near >= 0, refs[np.maximum(near, 0)], -1)
    return gt


def _digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def build_msls(req: MslsRequest) -> dict[str, Any]:
    """Write ``<out>/<name>.zarr`` from an MSLS tree and keyed descriptors; returns the summary."""
    root = Path(req.root)
    if not root.is_dir():
        raise InputError(f"--msls {req.root}: no such directory (MSLS's root, holding train_val and test)")
    if not NAME.fullmatch(req.name):
        raise InputError(f"--name {req.name}: lower-case letters, digits and _, starting with a letter")
    if not req.threshold_m > 0:
        raise InputError(f"--gt-radius-m {req.threshold_m}: must be above 0 metres")
    cities = parse_cities(req.cities)
    db, q = read_side(root, cities, "database"), read_side(root, cities, "query")
    if (db.pos is None) != (q.pos is None):
        raise InputError(f"--cities {req.cities}: database and query disagree on positions")
    source, file_keys = open_keyed(req.descriptors, req.keys)
    where = f"--descriptors {req.descriptors}"
    ref_order, query_order = key_rows(db.key, file_keys, where), key_rows(q.key, file_keys, where)
    need = 4 * source.dim * (len(db) + len(q)) * 2  # the store, and its rows once more while they are reordered
    there = next(p for p in (Path(req.out).absolute(), *Path(req.out).absolute().parents) if p.exists())
    if need > shutil.disk_usage(there).free:
        raise InputError(f"--out {req.out}: the build needs {need / 2**30:,.1f} GiB and the disk there has "
                         f"{shutil.disk_usage(there).free / 2**30:,.1f} GiB free")
    gt = _truth(db, q, req.threshold_m)
    labels: dict[str, np.ndarray] = {"gt": gt, "query_part": np.zeros(len(q), np.uint8),
                                     "ref_part": np.zeros(len(db), np.uint8)}
    for side, rows in (("ref", db), ("query", q)):
        labels |= {f"{side}_seq": rows.sequence, f"{side}_frame": rows.frame, f"{side}_key": key_bytes(rows.key),
                   f"{side}_city": rows.city, f"{side}_pano": rows.pano.astype(np.uint8),
                   f"{side}_subtask": rows.subtask}
        if rows.pos is not None:
            labels[f"{side}_pos"] = rows.pos
    identity = {"recipe": {"scale": req.name, "dim": source.dim, "query_stride": 1, "own": True, "msls": True},
                "sources": {"descriptors": source.fingerprint(), "ref_order": _digest(ref_order),
                            "query_order": _digest(query_order),
                            "msls": {"cities": cities, "labels": _digest(*labels.values())},
                            "gt_from_positions_within_m": req.threshold_m},
                "rescale": None, "seed": None}
    layout = {"kind": "full", "n_deep1b": len(q), "n_fas_ref": 0, "n_fas_query": 0, "noises": [NOISE],
              **({"positions": 2} if db.pos is not None else {}),
              "sequences": {"ref": int(len(np.unique(db.sequence))), "query": int(len(np.unique(q.sequence)))},
              "msls": {"cities": cities, "subtasks": list(SUBTASKS), "positions": db.pos is not None}}
    rows = {"ref": StoreRows(source, ref_order), f"query_{NOISE}": StoreRows(source, query_order)}
    return write_store(Path(req.out).absolute() / f"{req.name}.zarr", identity, rows, labels, layout, req)
