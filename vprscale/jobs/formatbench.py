"""``vprscale bench format``: the index's Parquet tables (format 4) against format 3's succinct
files on disk, and the engine's succinct arrays against plain arrays (format 2's layout) in
memory, on the same index, per query per core, in one process.

On disk: each format's bytes per place against the floor, the time to decode the tables
(in memory, and once into the engine cache) and to load them again from the cache, and the
per-query cost of the index loaded from its tables against the same index opened from format
3's files, interleaved (A, B, B, A) repeat by repeat, with their matches checked equal.

Format 2 held the lists as plain words in memory: ids (uint32), sorted occupied addresses
with a prefix table for the search, offsets and single bests. :class:`PlainLists` rebuilds
exactly that from a format-3 index (decoded once, outside the timing), with format 2's
look-up kernels, so the two are timed side by side on the same frames, interleaved repeat
by repeat, and their matches checked equal. The window scores read the same bit planes in
both (the codes were already d bits a place, built in memory, in format 2).
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from vprscale.core.kernelcache import share_kernels
from vprscale.evaluation.storage import floor_bits, index_parts
from vprscale.method import engine
from vprscale.method.index import Index, QueryFrames
from vprscale.method.indexfile import fill_from_tables, load_index_meta, read_model
from vprscale.method.kernels import address_delta, bit_planes, match_batch
from vprscale.protocol import NO_MASK

share_kernels()

PLAIN_PLACES = 1 << 27  # the largest index whose plain arrays bench format builds beside the succinct ones
PREFIX_BITS = (16, 24)  # format 2's prefix table: about one entry per occupied address, 2^16 to 2^24


@numba.njit(cache=True, nogil=True)
def _nearest_plain(a: np.ndarray, first: np.ndarray, shift: int, h: np.ndarray) -> np.ndarray:
    """Format 2's search: the prefix table's range, then a binary search (ties to the smaller)."""
    out = np.empty(h.shape[0], np.int64)
    for i in range(h.shape[0]):
        x = h[i]
        lo, hi = first[np.int64(x >> np.uint64(shift))], first[np.int64(x >> np.uint64(shift)) + 1]
        while lo < hi:
            mid = (lo + hi) >> 1
            if a[mid] < x:
                lo = mid + 1
            else:
                hi = mid
        if lo < a.shape[0] and a[lo] == x:
            out[i] = lo
        elif lo == 0:
            out[i] = 0
        elif lo == a.shape[0] or x - a[lo - 1] <= a[lo] - x:
            out[i] = lo - 1
        else:
            out[i] = lo
    return out


@numba.njit(cache=True, nogil=True)
def _retrieve_plain(offsets: np.ndarray, ids: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Format 2's list retrieval: each frame's list copied, one after another."""
    start = np.empty(a.shape[0], np.int64)
    stop = np.empty(a.shape[0], np.int64)
    total = 0
    for i in range(a.shape[0]):
        total += offsets[a[i] + 1] - offsets[a[i]]
    out = np.empty(total, np.int64)
    m = 0
    for i in range(a.shape[0]):
        start[i] = m
        for q in range(offsets[a[i]], offsets[a[i] + 1]):
            out[m] = ids[q]
            m += 1
        stop[i] = m
    return start, stop, out


@numba.njit(cache=True, nogil=True)
def _top_plain(slot: np.ndarray, offsets: np.ndarray, ids: np.ndarray, best: np.ndarray, n_best: int) -> np.ndarray:
    """Format 2's L = 1 answer: the single best from its array, then the list by id."""
    out = np.full((slot.shape[0], n_best), -1, np.int64)
    for i in range(slot.shape[0]):
        a = slot[i]
        out[i, 0] = best[a]
        j = 1
        for q in range(offsets[a], offsets[a + 1]):
            if j >= n_best:
                break
            if ids[q] != best[a]:
                out[i, j] = ids[q]
                j += 1
    return out


@dataclass
class PlainLists:
    """Format 2's lists, in memory: what the plain side of the benchmark reads."""

    addresses: np.ndarray
    offsets: np.ndarray
    ids: np.ndarray
    best: np.ndarray
    first: np.ndarray
    shift: int

    @classmethod
    def of(cls, idx: Index) -> PlainLists:
        bits = int(np.ceil(idx.d * np.log2(idx.k)))
        addr_t = np.uint16 if bits <= 16 else np.uint32 if bits <= 32 else np.uint64
        addresses = idx.lists.occupied.decode().astype(addr_t)
        offsets = idx.lists.starts.decode().astype(np.uint32 if idx.n_ref < 2**32 else np.uint64)
        order = idx.lists.ids_range(0, idx.n_ref)
        best = order[offsets[:-1].astype(np.int64)]
        for a in range(len(addresses)):  # format 2 kept ids ascending inside a list, the best apart
            order[offsets[a] : offsets[a + 1]].sort()
        wanted = int(np.ceil(np.log2(max(2, len(addresses)))))
        shift = max(0, bits - min(PREFIX_BITS[1], max(PREFIX_BITS[0], wanted)))
        counts = np.zeros((1 << (bits - shift)) + 1, np.int64)
        counts[1:] = np.bincount((addresses.astype(np.uint64) >> np.uint64(shift)).astype(np.int64),
                                 minlength=len(counts) - 1)
        id_t = offsets.dtype
        return cls(addresses, offsets, order.astype(id_t), best.astype(id_t), np.cumsum(counts), shift)

    def query_frames(self, idx: Index, h: np.ndarray) -> QueryFrames:
        a = _nearest_plain(self.addresses, self.first, self.shift, h)
        start, stop, ids = _retrieve_plain(self.offsets, self.ids, a)
        return QueryFrames(np.arange(len(h)), h, a, self.addresses[a].astype(np.uint64), start, stop, ids,
                           bit_planes(h, idx.d))


def _cpu(fn: Callable[[], object]) -> float:
    t0 = time.thread_time()
    fn()
    return time.thread_time() - t0


def bench_format(store: str, index: str, Ls: tuple[int, ...] = (1, 100), frames: int = 4096,
                 repeats: int = 5) -> str:
    """Per-frame work and per-query cost of both layouts (µs, one thread, medians of ``repeats``
    with their range), the ratio succinct / plain, and the bytes per place of each. As in the
    evaluation's runner, a query's cost includes one frame's work (hashing it too). Above
    ``PLAIN_PLACES`` places format 2's arrays are not built (tens of GB, and a sort per list):
    one line says so."""
    import zarr

    n_ref = int(load_index_meta(Path(index))["n_ref"])
    if n_ref > PLAIN_PLACES:
        return (f"plain arrays (format 2's layout): not built for {n_ref:,} places, above {PLAIN_PLACES:,} "
                f"(about {16 * n_ref / 2**30:,.0f} GiB in memory and a sort per list)")
    idx = Index.load(index).warm()
    q = zarr.open_group(store, mode="r")["query_qm1"]
    start = max(0, q.shape[0] // 2 - frames // 2)
    rows = q[start : start + frames]
    h, _ = idx.hash_frames(rows)
    plain = PlainLists.of(idx)
    plain_bytes = sum(a.nbytes for a in (plain.addresses, plain.offsets, plain.ids, plain.best)) + idx.codes.nbytes
    new_bytes = idx.codes.nbytes + sum(idx.lists.nbytes().values())
    sides: dict[str, Callable[[np.ndarray], QueryFrames]] = {
        "succinct": lambda x: idx.query_frames(x), "plain": lambda x: plain.query_frames(idx, x)}
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        lines = [f"index format, {idx.n_ref:,} places, {frames:,} query frames, one thread, median of {repeats} "
                 f"(range); bytes per place (codes + lists in memory): succinct {new_bytes / idx.n_ref:.2f}, "
                 f"plain {plain_bytes / idx.n_ref:.2f}"]
        qf = {name: make(h) for name, make in sides.items()}
        per_frame: dict[str, list[float]] = {name: [] for name in sides}
        for _ in range(repeats):  # as the runner times it: hashing included (the same code in both)
            for name, make in sides.items():
                per_frame[name].append(_cpu(lambda make=make: make(idx.hash_frames(rows)[0])) / frames * 1e6)
        lines.append(_line("per-frame work (hash, look-up, list, planes)", per_frame))
        for L in Ls:
            pos = np.arange(L // 2, frames - L + L // 2 + 1, max(1, (frames - L) // 1024))
            for mode in ("paper",) if L == 1 else ("paper", "aligned"):
                run = {"succinct": lambda L=L, mode=mode, pos=pos: idx.answer(qf["succinct"], pos, L, mode, 1),
                       "plain": lambda L=L, mode=mode, pos=pos: _answer_plain(idx, plain, qf["plain"], pos, L, mode)}
                a, b = (np.asarray(run[s]()[0]) for s in ("succinct", "plain"))
                if not np.array_equal(a[:, 0], b[:, 0]):
                    raise SystemExit(f"bench format: L = {L} {mode}: the two layouts' matches differ")
                per_query: dict[str, list[float]] = {name: [] for name in sides}
                for r in range(repeats):
                    for name in sides:
                        per_query[name].append(_cpu(run[name]) / len(pos) * 1e6 + per_frame[name][r])
                lines.append(_line(f"L = {L} {mode}: per query, per-frame work included", per_query))
    finally:
        numba.set_num_threads(before)
    return "\n".join(lines)


def _answer_plain(idx: Index, plain: PlainLists, qf: QueryFrames, pos: np.ndarray, L: int,
                  mode: str) -> tuple[np.ndarray, ...]:
    if L == 1:  # format 2's answer: the address taken read back from the directory, the best from its array
        w, tables, _ = idx.delta_tables()
        taken = plain.addresses[qf.slot[pos]].astype(np.uint64)
        return (_top_plain(qf.slot[pos], plain.offsets, plain.ids, plain.best, 1),
                address_delta(qf.hashes[pos], taken, w, tables, idx.d, idx.k))
    return match_batch(pos, L, mode == "aligned", *qf.kernel_args(), *idx.kernel_args(), NO_MASK, 1, 1)


def _line(what: str, times: dict[str, list[float]]) -> str:
    med = {k: float(np.median(v)) for k, v in times.items()}
    spans = ", ".join(f"{k} {med[k]:.2f} ({min(v):.2f}–{max(v):.2f}) µs" for k, v in times.items())
    return f"  {what}: {spans}; succinct / plain = {med['succinct'] / med['plain']:.2f}×"


def bench_tables(store: str, index: str, L: int = 100, frames: int = 4096, repeats: int = 9) -> str:
    """Format 4's tables against format 3's files of the same index: bytes per place, decode and
    load times, and the per-query cost (µs, one thread, L = 1 and ``L`` in paper mode) of the
    index loaded from each, A-B-B-A."""
    import zarr

    path = Path(index)
    meta = load_index_meta(path)
    n, d, k = int(meta["n_ref"]), int(meta["d"]), int(meta["k"])
    floor = floor_bits(n, d, k) / 8
    parts = index_parts(path)
    shared = sum(parts[p] for p in ("buckets", "components", "model (P2-P4)", "metadata"))  # in format 3 too
    with tempfile.TemporaryDirectory(prefix="vprscale-format3-", dir=path.parent) as tmp:
        old = Path(tmp)
        seconds = []
        for _ in range(2):  # as a command loads it: in memory each time, or into a fresh cache, then from it
            t0 = time.perf_counter()
            loaded = engine.engine_arrays(path, n, d, k, fill_from_tables(path), root=old / "cache")
            seconds.append(time.perf_counter() - t0)
        tables = Index(read_model(path, meta), *loaded, n, meta)
        layout = _format_3(tables, old)
        old_bytes = sum(f.stat().st_size for f in old.iterdir() if f.is_file()) + shared
        codes, lists = engine.open_engine(old, layout, n, d, k)
        files = Index(tables.hasher, codes, lists, n, tables.meta).warm()
        tables.warm()
        new_bytes = sum(parts.values())
        lines = [f"index on disk, {n:,} places, d = {d}, K = {k}: floor d + ⌈log2 N⌉ = {floor:.3f} B/place",
                 f"  format 4 (Parquet tables) {new_bytes / n:.3f} B/place ({new_bytes / n / floor:.3f}× the floor); "
                 f"format 3 (succinct .npy files) {old_bytes / n:.3f} ({old_bytes / n / floor:.3f}×); "
                 f"tables / files = {new_bytes / old_bytes:.3f}×",
                 "  " + ", ".join(f"{name} {b / n:.3f}" for name, b in parts.items()) + " B/place",
                 "  load: " + (f"decoded in memory, {seconds[1]:.2f} s (every load of an index this size)"
                               if n <= engine.IN_MEMORY_PLACES else
                               f"decode into the engine cache {seconds[0]:.2f} s (the first load), from the cache "
                               f"{seconds[1]:.3f} s (every later one)")]
        q = zarr.open_group(store, mode="r")["query_qm1"]
        start = max(0, q.shape[0] // 2 - frames // 2)
        h, _ = tables.hash_frames(q[start : start + frames])
        qf = {"tables": tables.query_frames(h), "files": files.query_frames(h)}
        sides = {"tables": tables, "files": files}
        threads = numba.get_num_threads()
        numba.set_num_threads(1)
        try:
            per_frame: dict[str, list[float]] = {name: [] for name in sides}
            for r in range(repeats):  # the look-ups: each frame's slot, its list and its planes
                for name in ("tables", "files") if r % 2 == 0 else ("files", "tables"):
                    per_frame[name].append(_cpu(lambda idx=sides[name]: idx.query_frames(h)) / frames * 1e6)
            lines.append(_ab_line("per-frame work (look-up, list, planes)", per_frame))
            for length in (1, L):
                pos = np.arange(length // 2, frames - length + length // 2 + 1, max(1, (frames - length) // 1024))
                run = {name: (lambda idx=idx, name=name, length=length, pos=pos:
                              idx.answer(qf[name], pos, length, "paper", 1)) for name, idx in sides.items()}
                if not all(np.array_equal(a, b) for a, b in zip(run["tables"](), run["files"](), strict=True)):
                    raise SystemExit(f"bench format: L = {length}: the two formats' answers differ")
                per_query: dict[str, list[float]] = {name: [] for name in sides}
                for r in range(repeats):
                    for name in ("tables", "files") if r % 2 == 0 else ("files", "tables"):
                        per_query[name].append(_cpu(run[name]) / len(pos) * 1e6 + per_frame[name][r])
                lines.append(_ab_line(f"L = {length} paper, per query, per-frame work included", per_query))
        finally:
            numba.set_num_threads(threads)
        del files, codes, lists, tables, loaded
    return "\n".join(lines)


def _format_3(idx: Index, folder: Path, rows: int = 1 << 24) -> dict:
    """Format 3's succinct files of ``idx`` written into ``folder`` a run at a time (bounded memory at
    any scale); returns their layout."""
    writer = engine.EngineWriter(folder, idx.n_ref, idx.d, idx.k)
    for a in range(0, idx.n_ref, rows):
        writer.codes(a, idx.ref_addresses(a, a + rows))
    for a in range(0, idx.lists.n_lists, rows):
        b = min(idx.lists.n_lists, a + rows)
        starts = idx.lists.starts.decode(a, b + 1)
        ids = idx.lists.ids_range(int(starts[0]), int(starts[-1]))
        writer.lists(idx.lists.occupied.decode(a, b), np.diff(starts), ids)
    return writer.close()


def _ab_line(what: str, times: dict[str, list[float]]) -> str:
    med = {k: float(np.median(v)) for k, v in times.items()}
    spans = ", ".join(f"{k} {med[k]:.2f} ({min(v):.2f}–{max(v):.2f}) µs" for k, v in times.items())
    return f"  {what}: {spans}; tables / files = {med['tables'] / med['files']:.3f}×"

