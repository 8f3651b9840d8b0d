"""Inverted lists in bounded memory: the references sorted by address, partition by partition.

A billion (address, id) pairs sorted in memory would take 16 GB and more. The addresses are
first scanned once (written to ``ref_hash.npy``, counted per 16-bit prefix and per code
level); the prefixes are cut into partitions of at most ``PART_ROWS`` references, a second
pass scatters every reference to its partition's files, and each partition is then sorted
on its own and appended to the outputs. Partitions are ranges of addresses, so appending
them in order gives the globally sorted lists. Memory is bounded by one partition (about
4 GB at ``PART_ROWS`` = 2^26), whatever the number of references.

Outputs, all in the index directory:

- ``ref_hash.npy``: every reference's address (P1, the map of the sequence matcher);
- ``ids.npy``: reference ids grouped by address, ascending inside an address;
- ``addresses.npy``, ``offsets.npy`` (CSR, one more than the addresses; as wide as the ids),
  ``best.npy``;
- ``lists.parquet`` (``hash``, ``ref_id``) and ``buckets.parquet`` (``hash``, ``size``,
  ``best_id``, ``offset``) for SQL.

Ids are uint32 below 2^32 references, addresses as narrow as ``K^d`` allows; the engine
memory-maps the ``.npy`` files, so a query touches only the lists and windows it reads.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from vprscale.jobs.progress import ChunkProgress

PART_ROWS = 1 << 26
PREFIX_BITS = 16
ROW_GROUP = 1 << 16  # look-ups prune to one row group; fewer groups keep DuckDB's planning cheap

Reader = Callable[[int, int], np.ndarray]  # rows [a, b) of one per-reference array


def address_dtype(d: int, k: int) -> np.dtype:
    """The narrowest unsigned integer that holds ``K^d`` addresses (2 bytes up to d = 16 at K = 2)."""
    for t in (np.uint16, np.uint32):
        if k**d <= np.iinfo(t).max + 1:
            return np.dtype(t)
    return np.dtype(np.uint64)


def inverted_lists(h: np.ndarray, err: np.ndarray) -> dict[str, np.ndarray]:
    """Sorted lists, occupied addresses, sizes, offsets and single best per address of rows ``0 … n − 1``.

    Sorted by (address, id), so ids stay ascending inside an address. When an address and
    an id fit in 64 bits together (10M refs at d = 24: 48 bits; a partition of 2^27 at
    d = 32: 59), the pair is sorted as one integer, which numpy sorts with SIMD five
    times faster than a stable argsort of the addresses.
    """
    h = np.asarray(h, np.uint64)
    id_bits = max(1, (len(h) - 1).bit_length())
    top = int(h.max()) if len(h) else 0
    if top.bit_length() + id_bits <= 64:
        key = (h << np.uint64(id_bits)) | np.arange(len(h), dtype=np.uint64)
        key.sort()
        order = (key & np.uint64((1 << id_bits) - 1)).astype(np.int64)
        hs = key >> np.uint64(id_bits)
        del key
    else:
        order = np.argsort(h, kind="stable")
        hs = h[order]
    starts = np.flatnonzero(np.r_[True, hs[1:] != hs[:-1]]) if len(hs) else np.empty(0, np.int64)
    sizes = np.diff(np.r_[starts, len(hs)])
    es = err[order]
    min_err = np.minimum.reduceat(es, starts) if len(starts) else es[:0]
    hits = np.flatnonzero(es == np.repeat(min_err, sizes))
    best = order[hits[np.searchsorted(hits, starts)]]  # first (smallest id) at the minimum
    return {"order": order, "hash": hs, "addresses": hs[starts], "sizes": sizes, "offsets": starts, "best": best}


class _Views:
    """``lists.parquet`` (``hash``, ``ref_id``) and ``buckets.parquet`` (``hash``, ``size``,
    ``best_id``, ``offset``), the SQL views of the lists, written a partition at a time."""

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


def write_views(out: Path, addresses: np.ndarray, offsets: np.ndarray, ids: np.ndarray, best: np.ndarray) -> None:
    """The SQL views of lists held in memory (CSR ``offsets``, one more than the addresses)."""
    views = _Views(out, np.asarray(ids).dtype)
    offsets = np.asarray(offsets, np.int64)
    views.write(addresses, np.diff(offsets), offsets[:-1], ids, best)
    views.close()


class _Appender:
    """A ``.npy`` file written by appending: the header is rewritten with the final length."""

    HEADER = 128

    def __init__(self, path: Path, dtype: np.dtype) -> None:
        self.path, self.dtype, self.n = path, np.dtype(dtype), 0
        self.f = path.open("wb")
        self.f.write(b"\0" * self.HEADER)

    def append(self, x: np.ndarray) -> None:
        np.ascontiguousarray(x, self.dtype).tofile(self.f)
        self.n += len(x)

    def close(self) -> None:
        head = f"{{'descr': '{self.dtype.str}', 'fortran_order': False, 'shape': ({self.n},), }}"
        raw = b"\x93NUMPY\x01\x00" + np.uint16(self.HEADER - 10).tobytes()
        self.f.seek(0)
        self.f.write(raw + head.ljust(self.HEADER - 11).encode() + b"\n")
        self.f.close()


def _prefix_cuts(counts: np.ndarray, limit: int) -> list[tuple[int, int]]:
    """Consecutive prefix ranges of at most ``limit`` references (a single prefix may exceed it)."""
    cuts, lo, total = [], 0, 0
    for p, c in enumerate(counts):
        if total and total + c > limit:
            cuts.append((lo, p))
            lo, total = p, 0
        total += int(c)
    cuts.append((lo, len(counts)))
    return cuts


def _scatter(work: Path, errors: Reader, bounds: list[tuple[int, int]], ref_hash: np.ndarray,
             cuts: list[tuple[int, int]], shift: np.uint64, id_t: np.dtype, quiet: bool) -> list:
    """Loaders of each partition's ``(addresses, errors, ids)``, ids ascending.

    With one partition everything is read straight into memory. With more, one pass over
    the chunks appends every reference to its partition's files (12 bytes a reference), so
    that no partition has to scan the whole set again; each loader reads its files back
    and deletes them.
    """
    if len(cuts) == 1:
        def whole() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            err = np.concatenate([np.asarray(errors(a, b), np.float32) for a, b in bounds])
            return np.asarray(ref_hash), err, np.arange(len(ref_hash), dtype=id_t)
        return [whole]
    work.mkdir(exist_ok=True)
    names = [(work / f"{i}.hash", work / f"{i}.err", work / f"{i}.ids") for i in range(len(cuts))]
    handles = [[n.open("wb") for n in trio] for trio in names]
    edges = np.array([hi for _, hi in cuts[:-1]], np.int64)
    progress = None if quiet else ChunkProgress("scatter partitions", len(bounds))
    for a, b in bounds:
        h = np.asarray(ref_hash[a:b])
        err = np.asarray(errors(a, b), np.float32)
        which = np.searchsorted(edges, (h >> h.dtype.type(shift)).astype(np.int64), side="right")
        order = np.argsort(which, kind="stable")  # ids stay ascending inside each partition
        starts = np.searchsorted(which[order], np.arange(len(cuts) + 1))
        ids = np.arange(a, b, dtype=id_t)
        for i in range(len(cuts)):
            sel = order[starts[i] : starts[i + 1]]
            for f, x in zip(handles[i], (h[sel], err[sel], ids[sel]), strict=True):
                x.tofile(f)
        if progress:
            progress.update(1)
    for trio in handles:
        for f in trio:
            f.close()

    def loader(i: int):
        def load() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            out = tuple(np.fromfile(n, dtype=t) for n, t in zip(names[i], (ref_hash.dtype, np.float32, id_t),
                                                                 strict=True))
            for n in names[i]:
                n.unlink()
            return out
        return load

    return [loader(i) for i in range(len(cuts))]


def write_lists(out: Path, addresses: Reader, errors: Reader, bounds: list[tuple[int, int]], n_ref: int, d: int,
                k: int, quiet: bool = False, part_rows: int = PART_ROWS) -> dict:
    """Sort references into inverted lists in ``out``; returns counts and sizes.

    ``addresses(a, b)`` and ``errors(a, b)`` give the addresses and quantisation errors of
    references ``[a, b)`` (``bounds`` are their chunks); each is read once. Returns
    ``level_counts`` (d × K references per code level), ``occupied`` and ``partitions``.
    """
    bits = max(1, math.ceil(d * math.log2(k)))
    addr_t = address_dtype(d, k)
    id_t = np.dtype(np.uint32) if n_ref < 2**32 else np.dtype(np.uint64)
    shift = np.uint64(max(0, bits - PREFIX_BITS))
    ref_hash = np.lib.format.open_memmap(out / "ref_hash.npy", mode="w+", dtype=addr_t, shape=(n_ref,))
    prefix_counts = np.zeros(1 << min(bits, PREFIX_BITS), np.int64)
    level_counts = np.zeros((d, k), np.int64)
    progress = None if quiet else ChunkProgress("scan addresses", len(bounds))
    for a, b in bounds:
        h = np.asarray(addresses(a, b), np.uint64)
        ref_hash[a:b] = h
        prefix_counts += np.bincount((h >> shift).astype(np.int64), minlength=len(prefix_counts))
        rest = h.copy()
        for j in range(d - 1, -1, -1):  # the code of component j is digit d − 1 − j (first = most significant)
            level_counts[j] += np.bincount((rest % np.uint64(k)).astype(np.int64), minlength=k)
            rest //= np.uint64(k)
        if progress:
            progress.update(1)
    ref_hash.flush()
    cuts = _prefix_cuts(prefix_counts, part_rows)
    files = {name: _Appender(out / f"{name}.npy", t) for name, t in
             (("ids", id_t), ("addresses", addr_t), ("offsets", id_t), ("best", id_t))}
    views = _Views(out, id_t)
    parts = _scatter(out / ".partitions", errors, bounds, ref_hash, cuts, shift, id_t, quiet)
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
    return {"level_counts": level_counts, "occupied": files["addresses"].n, "partitions": len(cuts)}
