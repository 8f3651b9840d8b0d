"""``vprscale bench codes``: the cost of one window-score term on FAISS codes, ours against FAISS's.

A window score adds one distance term per (candidate, window frame): a query frame against
a reference's code. :mod:`vprscale.compared.codescore` computes each term from per-frame
tables; FAISS computes the same distance from the same codes in two ways of its own. This
benchmark prints, per FAISS method and in one process, on the same codes, CPU ns per term:

- **ours, window**: the window scores (:meth:`FaissCodes.score`) of windows of ``L`` frames
  centred at random query frames, each over random candidate centres (a candidate's codes
  read as a window reads them: ``L`` consecutive references);
- **ours, random ids**: the same kernel with one-frame windows, each term a random reference;
- **FAISS, distance computer**: FAISS's own exact distance of a query to the code of a given
  id (the index's ``get_distance_computer``), on random ids: ``IndexRefine`` over
  ``IndexRandom`` calls it for every id the random index proposes, and the random index's
  own search, timed right after it, is subtracted (what remains includes the refinement's
  choice of the best of each row's ids, a comparison per id); a median difference within the
  timing noise prints as such, with no ratio. The bar: ours at most 2× this.
  FAISS's computer for IVF-PQ, fast-scan and binary codes decodes each code (a vector, then
  its distance), so there ours is two orders of magnitude faster;
- **FAISS, scan**: FAISS's search over every code in order (the flat index's scan; IVF-PQ's
  list scan with precomputed tables over every list, ``nprobe = nlist``; the SIMD block scan
  of 4-bit fast-scan codes), FAISS's fastest loop, which no random access matches;
- for residual IVF-PQ codes, ours / ours on the first flat PQ of the same code size;
- for enumerable flat codes, a frame's top-k (``FRAME_K``): FAISS's search, which scans every
  code and is what an evaluation times, against the exact enumeration of code values that
  gives the evaluation the same answers (:mod:`vprscale.compared.codesearch`), µs per frame,
  and on how many of the frames the two agree exactly.

Times are CPU seconds of the calling thread (numba and FAISS on one thread), medians of
``repeats`` with min and max; nothing here is asserted in a test.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import faiss
import numba
import numpy as np
import zarr

from vprscale.compared.faisscodes import FaissCodes, FrameTerms, training_rows
from vprscale.compared.subtables import ProductTables
from vprscale.core.errors import InputError
from vprscale.core.progress import StepProgress
from vprscale.dataset.store import open_complete_group, store_layout

DEFAULT_FACTORIES = ("PQ3", "OPQ3,PQ3", "IVF1024,PQ3")
WINDOWS = 256  # windows whose candidates are scored per repeat
CANDIDATES = 256  # random candidate centres per window
PROPOSED = 4096  # random ids FAISS's distance computer scores per query row
PAIR_S = 0.02  # CPU seconds of each half of a timed pair (FAISS's distance computer)
FRAME_K = 16  # places a frame retrieves in the frame-search comparison (an evaluation's default k is smaller)
SEARCHED_FRAMES = 256  # query frames of the frame-search comparison


def _timed(fn: Callable[[], object], calls: int = 1) -> float:
    """CPU seconds of the calling thread over ``calls`` calls of ``fn``."""
    t0 = time.thread_time()
    for _ in range(calls):
        fn()
    return time.thread_time() - t0


def _cpu_ns(fn: Callable[[], object], n: int, repeats: int) -> tuple[float, float, float]:
    """(median, min, max) CPU ns of the calling thread per item over ``repeats`` calls."""
    fn()  # compile and warm outside the timing
    took = [_timed(fn) / n * 1e9 for _ in range(repeats)]
    return float(np.median(took)), min(took), max(took)


def _fmt(t: tuple[float, float, float]) -> str:
    return f"{t[0]:6.2f} ({t[1]:.2f}–{t[2]:.2f})"


def _ours(codes: FaissCodes, terms: FrameTerms, L: int, rng: np.random.Generator, repeats: int,
          windows: int = WINDOWS, candidates: int = CANDIDATES) -> tuple[float, float, float]:
    """Our window score per term, on random windows of the query frames of ``terms`` and random
    candidates (L = 1: random ids)."""
    half = L // 2
    n_frames = len(terms.tables) or len(terms.vectors)
    centres = rng.integers(half, n_frames - L + half + 1, windows)
    cand = rng.integers(0, codes.n_ref, windows * candidates)
    first = np.arange(windows, dtype=np.int64) * candidates
    n_r = np.full(windows, candidates, np.int64)
    return _cpu_ns(lambda: codes.score(centres, L, cand, first, n_r, terms), windows * candidates * L, repeats)


def _faiss_distance_computer(codes: FaissCodes, query: np.ndarray, repeats: int) -> tuple[float, float, float]:
    """FAISS's distance computer of the searched index on random ids, per id (one thread):
    ``IndexRefine(IndexRandom)``'s search less the random index's own, timed in pairs, one right
    after the other and each long enough (``PAIR_S``) to time well; the median of the pairs'
    differences. The random index's own search costs as much as the distances of the cheapest
    codes, so the difference of two medians taken apart can be lost in their noise."""
    if codes.ivf is not None:  # an IVF finds an id's code through it (a fast-scan code: in its searched copy)
        faiss.extract_index_ivf(codes.searched).make_direct_map()
    proposed = min(PROPOSED, codes.n_ref)  # FAISS's random index proposes at most every place
    y = np.ascontiguousarray(query[:WINDOWS * CANDIDATES // proposed], np.float32)
    proposer = faiss.IndexRandom(codes.dim, codes.n_ref)
    refined = faiss.IndexRefine(proposer, codes.searched)
    refined.k_factor = proposed
    faiss.omp_set_num_threads(1)
    refine, alone = (lambda: refined.search(y, 1)), (lambda: proposer.search(y, proposed))
    calls = max(1, math.ceil(PAIR_S / max(_timed(refine), 1e-6)))  # the first call also warms
    per_id = len(y) * proposed * calls
    diffs = [(_timed(refine, calls) - _timed(alone, calls)) / per_id * 1e9 for _ in range(repeats)]
    return float(np.median(diffs)), min(diffs), max(diffs)


def _faiss_scan(codes: FaissCodes, query: np.ndarray, repeats: int) -> tuple[float, float, float]:
    """FAISS's own search over the same codes, per code visited (one thread)."""
    y = np.ascontiguousarray(codes._transform(query[:16]), np.float32)
    inner = codes.searched_inner
    if codes.ivf is not None:
        codes.ivf.nprobe = codes.ivf.nlist
        visited = codes.n_ref
    else:
        visited = inner.ntotal
    faiss.omp_set_num_threads(1)
    try:
        return _cpu_ns(lambda: inner.search(y, 1), len(y) * visited, repeats)
    finally:
        if codes.ivf is not None:
            codes.ivf.nprobe = codes.nprobe


def _frame_search(codes: FaissCodes, query: np.ndarray, repeats: int) -> str:
    """One line: FAISS's search and the exact enumeration of an enumerable flat code, µs per frame."""
    y = np.ascontiguousarray(query[:SEARCHED_FRAMES], np.float32)
    codes.k, codes.threads = FRAME_K, 1
    faiss.omp_set_num_threads(1)
    theirs = _cpu_ns(lambda: codes.search(y), len(y), repeats)
    ours = _cpu_ns(lambda: codes.exact_search(y), len(y), repeats)
    same = int((codes.search(y)[1] == codes.exact_search(y)[1]).all(axis=1).sum())
    return (f"{codes.factory:<18} {_fmt(tuple(t / 1e3 for t in theirs)):>24} {_fmt(tuple(t / 1e3 for t in ours)):>24} "
            f"{theirs[0] / ours[0]:9.0f}× {same:>5}/{len(y)}")


def bench_codes(store: str, factories: list[str], places: int | None, L: int, repeats: int = 5) -> str:
    """Print the per-term cost of our window scores and FAISS's scans (module docstring)."""
    path = Path(store)
    group = open_complete_group(path)
    if store_layout(group)["kind"] == "compact":
        raise InputError(f"bench codes: {store} is a compact store; give a full one (it encodes its reference rows)")
    ref_array = group["ref"]
    assert isinstance(ref_array, zarr.Array)
    n = min(places or ref_array.shape[0], ref_array.shape[0])
    ref = np.asarray(ref_array[:n], np.float32)
    query = np.asarray(group["query_qm1"][: max(4 * L, 1024)], np.float32)
    rng = np.random.default_rng(0)
    numba.set_num_threads(1)
    lines = [f"window-score term cost, CPU ns per term, one thread, median (min–max) of {repeats}; "
             f"{n:,} references of {path.name}, L = {L}, {WINDOWS} windows × {CANDIDATES} random candidates; "
             f"FAISS's distance computer on {PROPOSED:,} random ids per query row (the bar: ours at most 2× it)",
             f"{'method':<18} {'form':<9} {'B/code':>6} {'ours: window':>22} {'ours: random ids':>22} "
             f"{'FAISS: distance comp.':>22} {'FAISS: scan':>22} {'ours/dist.':>10} {'ours/scan':>9} {'ours/PQ':>8}"]
    flat_pq: dict[int, float] = {}
    searches: list[str] = []
    steps = StepProgress("bench codes", len(factories))  # a few minutes a code at 1M places (--quiet: silent)
    for factory in factories:
        steps.step(f"{factory}: train, encode {n:,} references, time")
        codes = FaissCodes(factory, ref.shape[1], k=1)
        codes.train(ref[training_rows(n)])
        codes.start(n)
        for i in range(0, n, 1 << 16):
            codes.encode(ref[i : i + (1 << 16)])
        codes.finish()
        terms = codes.frame_terms(query)
        ours = _ours(codes, terms, L, rng, repeats)
        # one-frame windows of as many random ids as FAISS's distance computer gets per query row
        ours_random = _ours(codes, terms, 1, rng, repeats, WINDOWS * CANDIDATES // PROPOSED, PROPOSED)
        computer = _faiss_distance_computer(codes, query, repeats)
        theirs = _faiss_scan(codes, query, repeats)
        width = codes.code_width
        if codes.form == "tables" and isinstance(codes.subs, ProductTables):
            flat_pq.setdefault(width, ours[0])
        vs_pq = f"{ours[0] / flat_pq[width]:8.2f}" if codes.form == "residual" and width in flat_pq else f"{'-':>8}"
        # a difference within the timing noise is no time: said, and no ratio made of it
        resolved = computer[0] > 0
        vs_computer = f"{ours_random[0] / computer[0]:10.2f}" if resolved else f"{'-':>10}"
        lines.append(f"{factory:<18} {codes.form:<9} {width:>6} {_fmt(ours):>22} {_fmt(ours_random):>22} "
                     f"{_fmt(computer) if resolved else 'within noise':>22} {_fmt(theirs):>22} {vs_computer} "
                     f"{ours[0] / theirs[0]:9.2f} {vs_pq}")
        if codes.enumerable:
            searches.append(_frame_search(codes, query, repeats))
    steps.close()
    if searches:
        lines += ["", f"a frame's top-{FRAME_K}, CPU µs per frame, one thread, median (min–max) of {repeats}, "
                      f"{SEARCHED_FRAMES} query frames: FAISS's search (every code; what an evaluation times) "
                      "against the exact enumeration of code values (what it answers from); frames with the same ids",
                  f"{'method':<18} {'FAISS: search':>24} {'ours: enumeration':>24} {'faster':>10} {'same':>9}",
                  *searches]
    return "\n".join(lines)
