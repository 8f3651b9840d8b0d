"""The nearest-neighbour axis (docs/protocol.md, "Nearest-neighbour recall"): ``nn.parquet``.

The compact-code literature files a code by its 1-NN recall at bytes per vector: the share
of query rows whose exact nearest reference is among the code's R best (R@1, R@10, R@100),
with the time a query takes. Here the exact neighbours come from a brute-force scan of every
reference (FAISS's flat search, block by block, out of core), and each method answers with
its own ranking: a FAISS code its top 100, CoarseHash the list of the query's own address
(its single best first, then by id) and then the lists of the occupied addresses nearest it
in Hamming distance, until 100.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from itertools import combinations
from typing import Any

import dask.array as da
import faiss
import numba
import numpy as np

from vprscale.compared.faisscodes import FaissCodes, code_family
from vprscale.core.errors import InputError
from vprscale.core.kernelcache import share_kernels
from vprscale.core.progress import ChunkProgress, StepProgress
from vprscale.evaluation.algorithms.coarsehash import CoarseHash
from vprscale.method.index import Index
from vprscale.method.kernels import bit_gaps

share_kernels()

DEPTHS = (1, 10, 100)  # the R of R@R
TIMED_ROWS = 1000  # query rows each method is timed on, one thread (the answers are of every row)
SCAN_ROWS = 4096  # references one exact scan compares at a time, at fixed offsets (the same ids for any chunking)
LOOKUPS = 1 << 22  # addresses looked up at a time in CoarseHash's Hamming expansion
MAX_MASKS = 1 << 16  # the expansion stops at the Hamming radius with more addresses than this per row

# What the literature reports on Deep1B at 1B (the FAISS wiki, "Indexing 1G vectors", 2017): one CPU
# thread each, so per query per core as this suite times. Bytes per vector: the 20-byte code and,
# for FAISS's inverted multi-index, its 8-byte id; the wiki states ~25 GB of RAM for the billion.
PUBLISHED = (
    {"method": "Babenko & Lempitsky, CVPR'16 (Deep1B, 1B)", "bytes_per_place": 25.0, "recall_at_1": 0.45,
     "us_per_query": 20_000.0, "threads": 1, "source": "FAISS wiki, Indexing 1G vectors"},
    {"method": "FAISS OPQ20_80,IMI2x14,PQ20 (Deep1B, 1B)", "bytes_per_place": 28.0, "recall_at_1": 0.4561,
     "us_per_query": 3_660.0, "threads": 1, "source": "FAISS wiki, Indexing 1G vectors"},
)


def exact_neighbours(ref: da.Array, rows: np.ndarray, workers: int, progress: bool = True) -> np.ndarray:
    """Each row's exact nearest reference by squared L2 (ties: the smaller id), scanning every
    reference once: FAISS's flat search of blocks of ``SCAN_ROWS`` at fixed offsets, each on one
    thread (``workers`` side by side), the nearest kept by (distance, id)."""
    rows = np.ascontiguousarray(rows, np.float32)
    best_d = np.full(len(rows), np.inf, np.float32)
    best_i = np.full(len(rows), -1, np.int64)
    bar = ChunkProgress("exact neighbours (a scan of every reference)", ref.numblocks[0]) if progress else None

    def scan(item: tuple[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        start, x = item
        faiss.omp_set_num_threads(1)
        dist, ids = faiss.knn(rows, np.ascontiguousarray(x, np.float32), 1)
        return dist[:, 0], np.where(ids[:, 0] >= 0, ids[:, 0] + start, -1)

    offset = 0
    with ThreadPoolExecutor(workers) as pool:
        for i in range(ref.numblocks[0]):
            block = np.asarray(ref.blocks[i].compute(), np.float32)
            cuts = np.arange(SCAN_ROWS - offset % SCAN_ROWS, len(block), SCAN_ROWS)
            starts = np.concatenate([[0], cuts]) + offset
            for dist, ids in pool.map(scan, zip(starts, np.split(block, cuts), strict=True)):  # in id order
                better = dist < best_d
                best_d[better], best_i[better] = dist[better], ids[better]
            offset += len(block)
            if bar:
                bar.update(1)
    return best_i


@numba.njit(cache=True, nogil=True)
def _append_lists(out: np.ndarray, filled: np.ndarray, owner: np.ndarray, start: np.ndarray, stop: np.ndarray,
                  flat: np.ndarray) -> None:
    """Append list ``p`` (``flat[start[p]:stop[p]]``) to row ``owner[p]`` of ``out``, in order, until it is full."""
    width = out.shape[1]
    for p in range(owner.shape[0]):
        q = owner[p]
        for j in range(start[p], stop[p]):
            if filled[q] >= width:
                break
            out[q, filled[q]] = flat[j]
            filled[q] += 1


def _masks(d: int, r: int, gaps: np.ndarray) -> np.ndarray:
    """The ``d``-bit masks of ``r`` bits, the cheapest first by CoarseHash's δ (its bits' gaps), then by value."""
    bits = np.array(list(combinations(range(d), r)), np.int64).reshape(math.comb(d, r), r)
    masks = (np.uint64(1) << bits.astype(np.uint64)).sum(axis=1, dtype=np.uint64)
    cost = np.asarray(gaps, np.int64)[bits].sum(axis=1)
    return masks[np.lexsort((masks, cost))]


def coarse_ranking(index: Index, rows: np.ndarray, depth: int) -> np.ndarray:
    """CoarseHash's ``depth`` best references for each row (−1 padded): the lists of the occupied
    addresses at Hamming distance 0, 1, 2, … from its own, within a distance the cheapest by δ
    first, each list its single best (the smallest quantisation error) first, then by id; up to
    the radius whose addresses outnumber ``MAX_MASKS`` (never reached on the ladder's maps)."""
    h, _ = index.hash_frames(rows)
    out = np.full((len(h), depth), -1, np.int64)
    filled = np.zeros(len(h), np.int64)
    gaps = bit_gaps(index.delta_tables()[0])
    for r in range(index.d + 1):
        todo = np.flatnonzero(filled < depth)
        if not len(todo):
            break
        if math.comb(index.d, r) > MAX_MASKS:  # a map this sparse around the row: the rest stays −1
            break
        masks = _masks(index.d, r, gaps)
        per = max(1, LOOKUPS // len(masks))
        for lo in range(0, len(todo), per):
            rows_at = todo[lo : lo + per]
            cand = (h[rows_at, None] ^ masks[None, :]).ravel()
            slots, taken = index.lists.nearest(cand)
            held = taken == cand
            owner = np.repeat(rows_at, len(masks))[held]
            start, stop, flat = index.lists.gather(slots[held])
            _append_lists(out, filled, owner, start, stop, flat)
    return out


def _recalls(ranking: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    found = ranking == truth[:, None]
    return {f"recall_at_{r}": float(found[:, :r].any(axis=1).mean()) if len(truth) else float("nan")
            for r in DEPTHS}


def _timed(fn: Callable[[np.ndarray], Any], rows: np.ndarray) -> float:
    """CPU µs per row of ``fn`` on ``TIMED_ROWS`` evenly spaced rows, on this thread alone."""
    sample = rows[np.unique(np.linspace(0, len(rows) - 1, min(len(rows), TIMED_ROWS)).round().astype(np.int64))]
    t0 = time.thread_time()
    fn(sample)
    return 1e6 * (time.thread_time() - t0) / max(1, len(sample))


def nn_rows(noise: str, rows: np.ndarray, truth: np.ndarray, index: Index, dim: int,
            compared: list[FaissCodes], workers: int, bar: StepProgress) -> list[dict[str, Any]]:
    """``nn.parquet``'s rows of one noise level: CoarseHash's and each FAISS code's recalls at
    1, 10 and 100 against the exact neighbours ``truth`` of ``rows`` (the answers on ``workers``
    threads: FAISS's searches in blocks of fixed size, the same whatever the threads), and CPU µs
    per query on one thread, timed apart on ``TIMED_ROWS`` of them (FAISS single-threaded,
    CoarseHash's numba kernels on one thread)."""
    depth = max(DEPTHS)
    bar.step(f"{noise} coarsehash: nearest-neighbour ranking")
    ranking = coarse_ranking(index, rows, depth)
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        us = _timed(lambda x: coarse_ranking(index, x, depth), rows)
    finally:
        numba.set_num_threads(before)
    found: list[dict[str, Any]] = [
        {"method": "coarsehash", "family": "hashing", "params": f"d={index.d} K={index.k}",
         "bytes_per_place": CoarseHash(index, dim).bytes_per_place, **_recalls(ranking, truth), "us_per_query": us}]
    for codes in compared:
        bar.step(f"{noise} {codes.name}: nearest-neighbour search")
        threads, k, nprobe = codes.threads, codes.k, codes.nprobe
        codes.set_point(depth, nprobe)
        try:
            codes.threads = workers
            _, ids = codes.search(rows)
            codes.threads = 1
            us = _timed(codes.search, rows)
        finally:
            codes.threads = threads
            codes.set_point(k, nprobe)
        found.append({"method": codes.name, "family": code_family(codes.factory),
                      "params": f"k={depth}" + (f" nprobe={nprobe}" if codes.ivf is not None else ""),
                      "bytes_per_place": codes.entry_bytes, **_recalls(ids, truth), "us_per_query": us})
    return [{"noise": noise, **row, "n_queries": len(rows), "timed_queries": min(len(rows), TIMED_ROWS),
             "threads": 1} for row in found]


def check_nn(index: Index, n_deep: int) -> None:
    """Refuse ``--nn`` where CoarseHash's Hamming expansion is not defined (K > 2), or where the
    store has no query rows of the part it is measured on (the first: Deep1B's)."""
    if index.k != 2:
        raise InputError(f"--nn: CoarseHash's ranking expands over Hamming balls of binary addresses; this index "
                         f"has K = {index.k}")
    if n_deep == 0:
        raise InputError("--nn: the store has no query rows in its first part (Deep1B's, or part 0 of your own), "
                         "where the nearest-neighbour axis is measured")
