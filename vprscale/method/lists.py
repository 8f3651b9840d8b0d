"""Inverted lists in bounded memory: the references sorted by address, partition by partition.

A billion (address, id) pairs sorted in memory would take 16 GB and more. The addresses are
first scanned once (counted per 16-bit prefix); the prefixes are cut into partitions of at
most ``PART_ROWS`` references (:func:`prefix_cuts`), a second pass scatters every reference
to its partition's files (:func:`scatter`), and each partition is then sorted on its own
(:func:`inverted_lists`). Partitions are ranges of addresses, so appending them in order
gives the globally sorted lists. Memory is bounded by one partition (about 4 GB at
``PART_ROWS`` = 2^26), whatever the number of references. The files the lists end up in are
:mod:`vprscale.method.indexfile`'s.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from vprscale.core.progress import ChunkProgress

PART_ROWS = 1 << 26
PREFIX_BITS = 16

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


def prefix_cuts(counts: np.ndarray, limit: int) -> list[tuple[int, int]]:
    """Consecutive prefix ranges of at most ``limit`` references (a single prefix may exceed it)."""
    cuts, lo, total = [], 0, 0
    for p, c in enumerate(counts):
        if total and total + c > limit:
            cuts.append((lo, p))
            lo, total = p, 0
        total += int(c)
    cuts.append((lo, len(counts)))
    return cuts


def scatter(work: Path, errors: Reader, bounds: list[tuple[int, int]], ref_hash: np.ndarray,
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
