"""The index directory format: the one module that writes and reads it.

An index directory holds:

- ``index.json``: kind, format, parameters (``d``, ``k``, ``bins``, ``n_ref``, ``dim``,
  ``occupied``) and whatever the writer adds (the store it came from, storage, timings);
- ``model/{mean,components,centres,explained_variance}.npy``: the fitted CoarseHasher;
- ``components.parquet``: per component and cluster: centre, reference count and share;
- the inverted lists as ``.npy`` files the query side memory-maps: ``ref_hash.npy`` (every
  place's address, P1), ``ids.npy`` (ids grouped by address, ascending inside),
  ``addresses.npy`` (sorted occupied addresses), ``offsets.npy`` (CSR, one more than the
  addresses) and ``best.npy`` (single best per address); ids, offsets and bests are uint32
  below 2^32 places, addresses as narrow as ``K^d`` allows;
- ``lists.parquet`` (``hash``, ``ref_id``) and ``buckets.parquet`` (``hash``, ``size``,
  ``best_id``, ``offset``): the lists as tables for the SQL console.

Two writers produce the same files: :func:`write_lists` streams a job's references through
the partitioned sort of :mod:`vprscale.method.lists` (bounded memory at any scale), and
:func:`write_arrays` writes lists held in memory (``Index.save``). Both finish with
:func:`write_model` and :func:`write_meta`; :func:`read_arrays` opens either. Publishing
(hidden work copy, lock, atomic rename) is the caller's.
"""

from __future__ import annotations

import io
import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from vprscale.core.errors import InputError
from vprscale.core.manifest import check_manifest
from vprscale.core.progress import ChunkProgress
from vprscale.method.coarsehash import CoarseHasher
from vprscale.method.lists import (
    PART_ROWS,
    PREFIX_BITS,
    Reader,
    address_dtype,
    inverted_lists,
    prefix_cuts,
    scatter,
)

KIND = "coarsehash-index"
INDEX_FORMAT = 2  # 2: lists as .npy files beside the Parquet copies
MODEL = ("mean", "components", "centres", "explained_variance")
MODEL_FILES = {"P2": ["centres.npy"], "P3": ["components.npy", "explained_variance.npy"], "P4": ["mean.npy"]}
LIST_FILES = ("ids", "addresses", "offsets", "best")
ROW_GROUP = 1 << 16  # look-ups prune to one row group; fewer groups keep DuckDB's planning cheap

def id_dtype(n_ref: int) -> np.dtype:
    """Ids (and offsets, single bests) are uint32 below 2^32 places."""
    return np.dtype(np.uint32) if n_ref < 2**32 else np.dtype(np.uint64)


class _Views:
    """``lists.parquet`` and ``buckets.parquet``, the SQL views of the lists, written a run at a time."""

    def __init__(self, out: Path, id_t: np.dtype) -> None:
        self.lists = pq.ParquetWriter(out / "lists.parquet",
                                      pa.schema([("hash", pa.uint64()), ("ref_id", pa.from_numpy_dtype(id_t))]),
                                      compression="zstd", use_dictionary=False,
                                      column_encoding={"hash": "DELTA_BINARY_PACKED",
                                                       "ref_id": "DELTA_BINARY_PACKED"})
        self.buckets = pq.ParquetWriter(out / "buckets.parquet",
                                        pa.schema([("hash", pa.uint64()), ("size", pa.uint32()),
                                                   ("best_id", pa.from_numpy_dtype(id_t)), ("offset", pa.uint64())]),
                                        compression="zstd", use_dictionary=False,
                                        column_encoding={"hash": "DELTA_BINARY_PACKED", "size": "PLAIN",
                                                         "best_id": "PLAIN", "offset": "DELTA_BINARY_PACKED"})
        self.id_t = id_t

    def write(self, addresses: np.ndarray, sizes: np.ndarray, offsets: np.ndarray, ids: np.ndarray,
              best: np.ndarray) -> None:
        """One run of occupied addresses with their list sizes and (global) offsets, ids and single bests."""
        hashes = np.repeat(np.asarray(addresses, np.uint64), sizes)
        for r in range(0, len(ids), 1 << 24):  # bounded Arrow buffers
            self.lists.write_table(pa.table({"hash": pa.array(hashes[r : r + (1 << 24)], pa.uint64()),
                                             "ref_id": pa.array(np.asarray(ids[r : r + (1 << 24)], self.id_t))}),
                                   row_group_size=ROW_GROUP)
        self.buckets.write_table(pa.table({"hash": pa.array(np.asarray(addresses, np.uint64), pa.uint64()),
                                           "size": pa.array(np.asarray(sizes, np.uint32)),
                                           "best_id": pa.array(np.asarray(best, self.id_t)),
                                           "offset": pa.array(np.asarray(offsets, np.uint64))}),
                                 row_group_size=ROW_GROUP)

    def close(self) -> None:
        self.lists.close()
        self.buckets.close()


class _Appender:
    """A 1-D ``.npy`` file written by appending; its header (numpy's own) gets the final length at close.

    The header is given a fixed 128 bytes up front, which numpy's 1.0 header of any 1-D
    shape below 10^40 elements fills exactly.
    """

    HEADER = 128

    def __init__(self, path: Path, dtype: np.dtype) -> None:
        self.path, self.dtype, self.n = path, np.dtype(dtype), 0
        self.f = path.open("wb")
        self.f.write(b"\0" * self.HEADER)

    def append(self, x: np.ndarray) -> None:
        np.ascontiguousarray(x, self.dtype).tofile(self.f)
        self.n += len(x)

    def close(self) -> None:
        head = io.BytesIO()
        np.lib.format.write_array_header_1_0(head, {"descr": np.lib.format.dtype_to_descr(self.dtype),
                                                    "fortran_order": False, "shape": (self.n,)})
        assert len(head.getvalue()) == self.HEADER, "numpy's .npy header changed length"
        self.f.seek(0)
        self.f.write(head.getvalue())
        self.f.close()


def level_counts(addresses: np.ndarray, d: int, k: int) -> np.ndarray:
    """References per code level, (d × K), of addresses (the first component is the top digit)."""
    rest = np.asarray(addresses, np.uint64).copy()
    counts = np.zeros((d, k), np.int64)
    for j in range(d - 1, -1, -1):
        counts[j] += np.bincount((rest % np.uint64(k)).astype(np.int64), minlength=k)
        rest //= np.uint64(k)
    return counts


def write_lists(out: Path, addresses: Reader, errors: Reader, bounds: list[tuple[int, int]], n_ref: int, d: int,
                k: int, quiet: bool = False, part_rows: int = PART_ROWS) -> dict:
    """Sort references into inverted lists in ``out`` in bounded memory; returns counts and sizes.

    ``addresses(a, b)`` and ``errors(a, b)`` give the addresses and quantisation errors of
    references ``[a, b)`` (``bounds`` are their chunks); each is read once. Returns
    ``level_counts`` (d × K references per code level), ``occupied`` and ``partitions``.
    """
    bits = max(1, math.ceil(d * math.log2(k)))
    addr_t, id_t = address_dtype(d, k), id_dtype(n_ref)
    shift = np.uint64(max(0, bits - PREFIX_BITS))
    ref_hash = np.lib.format.open_memmap(out / "ref_hash.npy", mode="w+", dtype=addr_t, shape=(n_ref,))
    prefix_counts = np.zeros(1 << min(bits, PREFIX_BITS), np.int64)
    counts = np.zeros((d, k), np.int64)
    progress = None if quiet else ChunkProgress("scan addresses", len(bounds))
    for a, b in bounds:
        h = np.asarray(addresses(a, b), np.uint64)
        ref_hash[a:b] = h
        prefix_counts += np.bincount((h >> shift).astype(np.int64), minlength=len(prefix_counts))
        counts += level_counts(h, d, k)
        if progress:
            progress.update(1)
    ref_hash.flush()
    cuts = prefix_cuts(prefix_counts, part_rows)
    files = {name: _Appender(out / f"{name}.npy", t) for name, t in
             (("ids", id_t), ("addresses", addr_t), ("offsets", id_t), ("best", id_t))}
    views = _Views(out, id_t)
    parts = scatter(out / ".partitions", errors, bounds, ref_hash, cuts, shift, id_t, quiet)
    progress = None if quiet or len(cuts) == 1 else ChunkProgress("sort partitions", len(cuts))
    offset = 0
    for part in parts:
        h, err, ids = part()
        lists = inverted_lists(h, err)
        del h, err
        order = ids[lists["order"]]
        best = ids[lists["best"]]
        del ids
        files["ids"].append(order)
        files["addresses"].append(lists["addresses"])
        files["offsets"].append(lists["offsets"] + offset)
        files["best"].append(best)
        views.write(lists["addresses"], lists["sizes"], lists["offsets"] + offset, order, best)
        offset += len(order)
        del lists, order, best
        if progress:
            progress.update(1)
    shutil.rmtree(out / ".partitions", ignore_errors=True)
    files["offsets"].append(np.array([offset]))
    for f in files.values():
        f.close()
    views.close()
    return {"level_counts": counts, "occupied": files["addresses"].n, "partitions": len(cuts)}


def write_model(path: Path, hasher: CoarseHasher, counts: np.ndarray, n_ref: int) -> None:
    """``model/*.npy`` and ``components.parquet`` of a fitted hasher and its references' code levels."""
    (path / "model").mkdir(exist_ok=True)
    for name in MODEL:
        np.save(path / "model" / f"{name}.npy", getattr(hasher, f"{name}_"))
    d, k = counts.shape
    comp = pa.table({"component": np.repeat(np.arange(1, d + 1), k).astype(np.int32),
                     "cluster": np.tile(np.arange(k), d).astype(np.int32),
                     "centre": hasher.centres_.ravel(),
                     "refs": counts.ravel().astype(np.int64),
                     "share": (counts / max(1, n_ref)).ravel(),
                     "variance": np.repeat(hasher.explained_variance_, k)})
    pq.write_table(comp, path / "components.parquet")


def write_meta(path: Path, hasher: CoarseHasher, n_ref: int, occupied: int, extra: dict[str, Any]) -> dict[str, Any]:
    """``index.json``: the format's own keys, then what the writer adds (``extra`` cannot override them)."""
    own = {"kind": KIND, "complete": True, "format": INDEX_FORMAT, "d": int(hasher.d_), "k": int(hasher.k),
           "n_ref": int(n_ref), "dim": int(hasher.n_features_in_), "occupied": int(occupied), "bins": int(hasher.bins)}
    meta = {**own, **{key: value for key, value in extra.items() if key not in own}}
    (path / "index.json").write_text(json.dumps(meta, indent=1, default=str))
    return meta


def write_arrays(path: Path, hasher: CoarseHasher, ref_hash: np.ndarray, addresses: np.ndarray,
                 offsets: np.ndarray, ids: np.ndarray, best: np.ndarray, extra: dict[str, Any]) -> dict[str, Any]:
    """Write lists held in memory into the directory ``path`` (which must exist and be empty).

    The arrays are written in the dtypes :func:`write_lists` gives them, so the directory is
    the one a job writes for the same lists.
    """
    d, k, n_ref = hasher.d_, hasher.k, len(ref_hash)
    addr_t, id_t = address_dtype(d, k), id_dtype(n_ref)
    arrays = {"ref_hash": (ref_hash, addr_t), "ids": (ids, id_t), "addresses": (addresses, addr_t),
              "offsets": (offsets, id_t), "best": (best, id_t)}
    for name, (arr, dtype) in arrays.items():
        np.save(path / f"{name}.npy", np.asarray(arr, dtype))
    views = _Views(path, id_t)
    offsets = np.asarray(offsets, np.int64)
    views.write(addresses, np.diff(offsets), offsets[:-1], ids, best)
    views.close()
    write_model(path, hasher, level_counts(ref_hash, d, k), n_ref)
    return write_meta(path, hasher, n_ref, len(addresses), extra)


def load_index_meta(index: str | Path) -> dict[str, Any]:
    """``index.json`` of a complete index, or an error naming the directory."""
    p = Path(index)
    meta_file = p / "index.json"
    if not meta_file.is_file():
        raise InputError(f"{p}: not a vprscale index (no index.json)")
    try:
        meta = json.loads(meta_file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{meta_file}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict) or not meta.get("complete") or meta.get("kind") != KIND:
        raise InputError(f"{p}: the index is incomplete or of another kind")
    if meta.get("format", 1) < INDEX_FORMAT:
        raise InputError(f"{p}: an index of an older vprscale (no memory-mapped lists); re-run vprscale index")
    check_manifest(p)
    return meta


def read_arrays(path: str | Path) -> tuple[CoarseHasher, dict[str, np.ndarray], dict[str, Any]]:
    """``(hasher, arrays, meta)`` of an index directory: the model read, the lists and the map
    memory-mapped (a query touches only the pages it reads)."""
    path = Path(path)
    meta = load_index_meta(path)
    try:
        model = {name: np.load(path / "model" / f"{name}.npy") for name in MODEL}
        arrays = {name: np.load(path / f"{name}.npy", mmap_mode="r") for name in (*LIST_FILES, "ref_hash")}
    except (OSError, ValueError, EOFError) as exc:  # a missing or truncated file of an index without a manifest
        raise InputError(f"{path}: an index file is missing or damaged ({str(exc).splitlines()[0][:200]}); "
                         "re-run vprscale index") from None
    hasher = CoarseHasher.from_fitted(int(meta["k"]), int(meta.get("bins", 1 << 14)), int(meta["n_ref"]), **model)
    return hasher, arrays, meta
