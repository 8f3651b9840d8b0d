"""``vprscale eval``: the evaluation protocol of docs/protocol.md over a store and its indexes.

For every noise level, index width, sequence length and method it localises the query
centres ``t = 0, z, 2z, …`` (with a truth and the whole window inside the query set),
then writes ``results.parquet`` (recall at radii 0…20 per part, with N_r statistics,
measured µs and counted operations per query) and ``queries.parquet`` (one row per query).
"""

from __future__ import annotations

import json
import sys
import time
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numba
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import zarr
from tqdm import tqdm

from vprscale.compared.baseline import baseline_batch
from vprscale.dataset.compact import baseline_map
from vprscale.dataset.rawchunks import rows_of
from vprscale.dataset.store import ATTR, PartialOutput, check_writable, exclusive, open_complete_group
from vprscale.errors import InputError
from vprscale.evaluation.accounting import baseline_ops, method_ops
from vprscale.evaluation.protocol import Centres, part_weights, query_centres, window_frames
from vprscale.jobs.cluster import cluster_peak_rss, dask_client
from vprscale.method.engine import Index, QueryFrames
from vprscale.method.index import (
    build_index,
    default_index_dir,
    load_index_meta,
    ref_moments,
    store_identity,
    store_layout,
)
from vprscale.method.kernels import in_list_distance, match_batch
from vprscale.method.pca import ExactPCA, moments_of

NOISES = {"qm1": "query_qm1", "qm2": "query_qm2"}
MODES = ("paper", "aligned")
RADII = np.arange(21)
# Batched kernels run on numba's threads (``--workers`` of them): measured wall time × threads /
# queries is the time per query per core.
PARTS = {"all": None, "deep1b": 0, "fas": 1}
BASELINE_SUBSAMPLE = 64  # baseline queries per run at 10^8 query rows and beyond (each scans every place)


@dataclass
class EvalRequest:
    """What ``vprscale eval`` was asked for."""

    store: Path
    index: Path | None = None
    noises: list[str] = field(default_factory=lambda: ["qm1", "qm2"])
    lengths: list[int] = field(default_factory=lambda: [1, 50, 100])
    modes: list[str] = field(default_factory=lambda: ["paper", "aligned"])
    baseline: bool = True
    z: int | None = None
    baseline_queries: int | None = None  # queries per baseline run; None: all below 10^8 query rows, else a sample
    d_sweep: list[int] | None = None
    out: Path | None = None
    workers: int = 2
    scheduler: str | None = None
    quiet: bool = False


class QuerySet:
    """The query frames of a store that an evaluation may read, with their truth and part.

    A full store holds every frame; a compact one only the windows its build kept
    (:mod:`vprscale.dataset.compact`). Either way ``gt_at``/``part_at`` answer for any frame
    (−1 / 255 where the store holds nothing), and ``rows`` reads descriptors of held frames.
    """

    def __init__(self, group: zarr.Group, layout: dict[str, Any]) -> None:
        self.group = group
        self.compact = layout["kind"] == "compact"
        self.n_deep = int(layout["n_deep1b"])
        if self.compact:
            self.n_query = int(layout["n_query"])
            self.frames = group["query_frames"][:]
            self.lengths = set(layout["eval_lengths"])
        else:
            self.n_query = int(group["gt"].shape[0])
            self.frames = None
        self._gt = group["gt"][:]
        self._part = group["query_part"][:]

    def _pos(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, np.int64)
        if not self.compact:
            return t, np.ones(len(t), bool)
        pos = np.minimum(np.searchsorted(self.frames, t), max(0, len(self.frames) - 1))
        return pos, (self.frames[pos] == t) if len(self.frames) else np.zeros(len(t), bool)

    def gt_at(self, t: np.ndarray) -> np.ndarray:
        pos, held = self._pos(t)
        return np.where(held, self._gt[pos], -1)

    def part_at(self, t: np.ndarray) -> np.ndarray:
        pos, held = self._pos(t)
        return np.where(held, self._part[pos], 255).astype(np.uint8)

    def centres(self, z: int, L: int) -> Centres:
        c = query_centres(self.gt_at, self.n_query, self.n_deep, z, L)
        if self.compact and len(c.t):
            missing = ~np.isin(window_frames([c.t], [L]), self.frames)
            if missing.any() or L not in self.lengths:
                raise InputError(f"--L {L} --z {z}: this compact store holds the query windows of "
                                 f"L = {sorted(self.lengths)} at its recipe's stride only")
        return c

    def rows(self, noise: str, frames: np.ndarray) -> np.ndarray:
        pos, held = self._pos(frames)
        assert held.all(), "frames outside the held windows"
        return self.group[NOISES[noise]].get_orthogonal_selection((pos, slice(None)))


def recall_curve(error: np.ndarray) -> np.ndarray:
    """Share of queries with ``|match − truth| ≤ r`` for r = 0 … 20."""
    if len(error) == 0:
        return np.full(len(RADII), np.nan)
    return (error[:, None] <= RADII[None, :]).mean(axis=0)


def _validate(req: EvalRequest) -> None:
    for flag, values in (("--noise", req.noises), ("--L", req.lengths), ("--modes", req.modes)):
        if not values:
            raise InputError(f"{flag}: the list is empty; give at least one value")
    unknown = [n for n in req.noises if n not in NOISES]
    if unknown:
        raise InputError(f"--noise {','.join(unknown)}: unknown noise; choose from {', '.join(NOISES)}")
    bad = [m for m in req.modes if m not in MODES]
    if bad:
        raise InputError(f"--modes {','.join(bad)}: unknown mode; choose from {', '.join(MODES)}")
    if any(L < 1 for L in req.lengths):
        raise InputError("--L: sequence lengths must be at least 1")
    if req.z is not None and req.z < 1:
        raise InputError(f"--z {req.z}: must be at least 1")


def _indexed_from(path: Path, identity: str) -> bool:
    """Whether ``path`` holds a complete index of the store with this identity."""
    try:
        return load_index_meta(path)["store"]["identity"] == identity
    except InputError:
        return False


def _indexes(req: EvalRequest, identity: str) -> list[Path]:
    if req.d_sweep:
        paths = []
        for d in req.d_sweep:
            path = default_index_dir(req.store, d, 2)
            if not _indexed_from(path, identity):
                build_index(req.store, d=d, k=2, out=path, scheduler=req.scheduler, workers=req.workers,
                            quiet=req.quiet)
            paths.append(path)
        return paths
    if req.index is None:
        raise InputError("eval: give an INDEX, or --d to index the store at several widths")
    return [req.index]


def evaluate(req: EvalRequest) -> dict[str, Any]:
    """Run the grid and write ``results.parquet`` and ``queries.parquet``; returns a summary."""
    _validate(req)
    t_start = time.perf_counter()
    group = open_complete_group(req.store)
    meta = group.attrs[ATTR]
    layout = store_layout(group)
    identity = store_identity(req.store)
    qs = QuerySet(group, layout)
    too_long = [L for L in req.lengths if L > qs.n_query]
    if too_long:
        raise InputError(f"--L {too_long[0]}: longer than the {qs.n_query:,} query frames")
    z = req.z or meta["recipe"]["query_stride"]
    dim = int(meta["recipe"]["dim"])
    threads = numba.get_num_threads()
    numba.set_num_threads(max(1, min(req.workers, numba.config.NUMBA_NUM_THREADS)))
    with dask_client(req.scheduler, req.workers) as client, _restore_threads(threads):
        index_paths = _indexes(req, identity)
        indexes = []
        for path in index_paths:
            idx = Index.load(path).warm()  # the directory read in order, not timed as random reads
            if idx.meta["store"]["identity"] != identity:
                raise InputError(f"{path}: this index was built from another store "
                                 f"({idx.meta['store']['path']}), not {req.store}")
            if idx.components.shape[1] != dim:
                raise InputError(f"{path}: index expects {idx.components.shape[1]}-d descriptors, "
                                 f"the store holds {dim}-d")
            indexes.append((path, idx))
        out = Path(req.out) if req.out else (index_paths[0] / "eval" if len(index_paths) == 1 else
                                             req.store.parent / f"{req.store.name.removesuffix('.zarr')}-dsweep.eval")
        if out.exists() and not out.is_dir():
            raise InputError(f"--out {out}: is a file, not a directory for the evaluation")
        if out.is_dir() and any(out.iterdir()) and not (out / "eval.json").is_file():
            raise InputError(f"--out {out}: exists and holds something other than an evaluation; not replaced")
        check_writable(out.parent)
        base = _baseline_map(group, layout) if req.baseline else None
        with ExitStack() as locks:
            for path in index_paths:  # re-indexing waits for (is refused during) an evaluation of the index
                locks.enter_context(exclusive(path))
            locks.enter_context(exclusive(out))
            partial = PartialOutput(out, {"eval": time.time_ns()})
            partial.recover()
            partial.open()
            rows, queries = _grid(req, qs, z, dim, indexes, base)
            provenance = {"scale": meta["recipe"]["scale"], "store": str(Path(req.store).resolve()),
                          "store_identity": identity}
            _write_parquet(partial.path / "results.parquet", rows, provenance)
            _write_parquet(partial.path / "queries.parquet", queries, provenance)
            summary = {"wall_s": time.perf_counter() - t_start, "peak_rss_bytes": cluster_peak_rss(client), "z": z,
                       "noises": req.noises, "lengths": req.lengths, "modes": req.modes, "baseline": req.baseline,
                       "baseline_queries": _baseline_limit(req, qs), "layout": layout["kind"],
                       "indexes": [str(Path(p).resolve()) for p in index_paths], **provenance}
            (partial.path / "eval.json").write_text(json.dumps(summary, indent=1))
            partial.publish()  # the three files appear together, by one rename
    return {"out": str(out), "rows": len(rows), "queries": len(queries), "z": z,
            "table": _summary_table(rows)}


@contextmanager
def _restore_threads(n: int):
    try:
        yield
    finally:
        numba.set_num_threads(n)


@dataclass
class BaselineMap:
    """The d = 1 baseline's map (every reference's first principal component) and its projection."""

    x: np.ndarray  # float32, one per reference
    mean: np.ndarray
    component: np.ndarray  # (1, D)

    def project(self, rows: np.ndarray) -> np.ndarray:
        return baseline_map(rows, self.mean, self.component).astype(np.float64)


def _baseline_map(group: zarr.Group, layout: dict[str, Any]) -> BaselineMap:
    """The baseline's map: kept by a compact build, else projected chunk by chunk from ``ref``.

    Its PCA (d = 1) is the first component of the references' PCA, fitted on the moments
    the build derived, so both layouts give the baseline the same map.
    """
    if layout["kind"] == "compact":
        model = group["transforms/coarsehash"]
        return BaselineMap(group["base_x1"][:], model["mean"][:], model["components"][:1])
    ref = rows_of(group["ref"])
    moments = ref_moments(group)
    pca = ExactPCA(1).fit_moments(moments if moments is not None else moments_of(ref))
    x = ref.map_blocks(baseline_map, pca.mean_, pca.components_, drop_axis=1, dtype=np.float32).compute()
    return BaselineMap(x, pca.mean_, pca.components_)


def _baseline_limit(req: EvalRequest, qs: QuerySet) -> int | None:
    """Queries the baseline localises per run (None: all); a full scan of 10^8 places costs ~0.1 s a query."""
    if req.baseline_queries is not None:
        return req.baseline_queries
    return BASELINE_SUBSAMPLE if qs.n_query >= 10**8 else None


def _subsample(n: int, limit: int | None) -> np.ndarray:
    """``limit`` evenly spaced positions of ``n`` (all when there are no more)."""
    if limit is None or n <= limit:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, limit).round().astype(np.int64))


def _grid(req: EvalRequest, qs: QuerySet, z: int, dim: int, indexes: list, base: BaselineMap | None
          ) -> tuple[list[dict], list[dict]]:
    rows: list[dict] = []
    queries: list[dict] = []
    centres = {L: qs.centres(z, L) for L in req.lengths}
    frames = window_frames([centres[L].t for L in req.lengths], req.lengths)
    weights = part_weights(qs.n_query, qs.n_deep)
    limit = _baseline_limit(req, qs)
    combos = len(req.noises) * len(indexes) * len(req.lengths)
    bar = tqdm(total=combos, desc="evaluate", unit="combo", file=sys.stderr, disable=None, leave=False)
    for noise in req.noises:
        x_q = qs.rows(noise, frames)
        y_base = base.project(x_q) if base is not None else None
        for path, idx in indexes:
            idx.query_frames(idx.hash_queries(x_q[:1]))  # load the compiled kernels outside the timing
            t0 = time.perf_counter()  # the per-frame work: hash, nearest occupied, list retrieval, planes
            h = idx.hash_queries(x_q)
            qf = idx.query_frames(h, frames)
            hash_us = (time.perf_counter() - t0) / max(1, len(frames)) * 1e6
            occupied = idx.addresses[qf.addr] == h  # by position among the frames
            args = idx.kernel_args()
            for L in req.lengths:
                c = centres[L]
                t, pos = c.t, qf.positions(c.t, L)
                truth, parts = qs.gt_at(t), qs.part_at(t)
                key = {"noise": noise, "d": idx.d, "K": idx.k, "L": L, "index": str(Path(path).resolve()),
                       "fas_stride": c.fas_stride}
                w = weights if c.fas_stride is not None else None
                fallback = float(1 - occupied[pos].mean()) if len(t) else 0.0
                results = _method_runs(req, idx, pos, L, qf, truth, args)
                paper_nr = None
                for mode, (match, n_r, secs, in_list) in results.items():
                    if mode == "paper" and L > 1:
                        paper_nr = n_r
                    if L > 1 and mode not in req.modes:
                        continue
                    ops = method_ops(dim, idx.d, idx.k, L, float(n_r.mean()) if len(n_r) else 0.0,
                                     len(idx.addresses), fallback)
                    us = secs * numba.get_num_threads() / max(1, len(t)) * 1e6 + hash_us
                    _emit(rows, queries, {**key, "method": "coarsehash", "mode": None if L == 1 else mode},
                          t, truth, parts, match, n_r, (us, hash_us), ops["total"], in_list, w)
                if base is not None:
                    nr = 1 if L == 1 else max(1, int(round(float(paper_nr.mean())))) if len(t) else 1
                    sub = _subsample(len(t), limit)
                    x_range = float(np.ptp(base.x))
                    baseline_batch(pos[:1], L, nr, base.x, y_base, x_range)  # compile outside the timing
                    t0 = time.perf_counter()
                    match, n_r = baseline_batch(pos[sub], L, nr, base.x, y_base, x_range)
                    secs = time.perf_counter() - t0
                    ops = baseline_ops(dim, len(base.x), L, nr)
                    us = secs * numba.get_num_threads() / max(1, len(sub)) * 1e6
                    _emit(rows, queries, {**key, "d": 1, "K": None, "method": "baseline", "mode": None},
                          t[sub], truth[sub], parts[sub], match, n_r, (us, None), ops["total"], None, w)
                bar.update()
    bar.close()
    return rows, queries


def _method_runs(req: EvalRequest, idx: Index, pos: np.ndarray, L: int, qf: QueryFrames, truth: np.ndarray,
                 args: tuple) -> dict:
    """``{mode: (match, n_r, seconds, in-list distance or None)}`` for one index and L.

    ``pos`` are the query centres' positions in ``qf``, ``truth`` their true matches.
    """
    if L == 1:
        t0 = time.perf_counter()
        a = qf.addr[pos]
        match = idx.best[a]
        secs = time.perf_counter() - t0
        n_r = idx.offsets[a + 1] - idx.offsets[a]
        return {"single": (match, n_r, secs, in_list_distance(a, truth, idx.offsets, idx.ids))}
    modes = set(req.modes) | ({"paper"} if req.baseline else set())
    out = {}
    for mode in MODES:
        if mode not in modes:
            continue
        match_batch(pos[:1], L, mode == "aligned", *qf.kernel_args(), *args)  # compile outside the timing
        t0 = time.perf_counter()
        match, n_r = match_batch(pos, L, mode == "aligned", *qf.kernel_args(), *args)
        out[mode] = (match, n_r, time.perf_counter() - t0, None)
    return out


def _emit(rows: list, queries: list, key: dict, t, truth, parts, match, n_r, us: tuple[float, float | None],
          ops: float, in_list, weights: dict[str, float] | None) -> None:
    """Rows of ``results`` and ``queries`` for one run; ``us`` is (µs per query, of which per-frame work).

    With ``weights`` (a stratified sample) the overall recall weights each part's recall by
    its share of the query rows; without, it is the share of all queries localised.
    """
    error = np.abs(np.asarray(match, np.int64) - truth)
    select = {name: np.ones(len(t), bool) if code is None else parts == code for name, code in PARTS.items()}
    curves = {name: (recall_curve(error[sel]), recall_curve(in_list[sel]) if in_list is not None else None)
              for name, sel in select.items()}
    held = [p for p in ("deep1b", "fas") if select[p].any()]
    if weights is not None and held:  # the overall curve from the parts' curves, each weighted by its row share
        total = sum(weights[p] for p in held)
        curves["all"] = tuple(None if curves[held[0]][i] is None else
                              sum(weights[p] * curves[p][i] for p in held) / total for i in (0, 1))
    for name, sel in select.items():
        curve, in_curve = curves[name]
        nr = n_r[sel]
        stats = {"n_queries": int(sel.sum()),
                 "nr_mean": float(nr.mean()) if len(nr) else np.nan,
                 "nr_median": float(np.median(nr)) if len(nr) else np.nan,
                 "nr_p95": float(np.percentile(nr, 95)) if len(nr) else np.nan,
                 "us_per_query": us[0], "us_per_frame": us[1], "ops_per_query": ops}
        for r in RADII:
            rows.append({**key, "part": name, "radius": int(r), "recall": float(curve[r]),
                         "recall_in_list": float(in_curve[r]) if in_curve is not None else None, **stats})
    for i in range(len(t)):
        queries.append({**key, "t": int(t[i]), "gt": int(truth[i]), "match": int(match[i]), "error": int(error[i]),
                        "n_r": int(n_r[i]), "in_list": int(in_list[i]) if in_list is not None else None,
                        "part": "deep1b" if parts[i] == 0 else "fas"})


def _write_parquet(path: Path, rows: list[dict], provenance: dict) -> None:
    pq.write_table(pa.Table.from_pylist([{**r, **provenance} for r in rows]), path, compression="zstd")


def _summary_table(rows: list[dict]) -> str:
    lines = [f"{'noise':<5} {'method':<10} {'mode':<8} {'d':>3} {'L':>4} {'part':<7} {'n':>6} "
             f"{'R@0':>6} {'R@5':>6} {'R@20':>6} {'N_r':>7} {'µs/q':>9} {'ops/q':>11}"]
    by_key: dict[tuple, dict[int, dict]] = {}
    for r in rows:
        by_key.setdefault((r["noise"], r["method"], r["mode"] or "-", r["d"], r["L"], r["part"]), {})[r["radius"]] = r
    for (noise, method, mode, d, L, part), radii in by_key.items():
        r0 = radii[0]
        lines.append(f"{noise:<5} {method:<10} {mode:<8} {d:>3} {L:>4} {part:<7} {r0['n_queries']:>6} "
                     f"{radii[0]['recall']:>6.3f} {radii[5]['recall']:>6.3f} {radii[20]['recall']:>6.3f} "
                     f"{r0['nr_mean']:>7.1f} {r0['us_per_query']:>9.2f} {r0['ops_per_query']:>11.0f}")
    return "\n".join(lines)
