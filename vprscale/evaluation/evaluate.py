"""``vprscale eval``: the evaluation protocol of docs/protocol.md over a store and its indexes.

For every noise level, index width, sequence length and method it localises the query
centres ``t = 0, z, 2z, …`` (with a truth and the whole window inside the query set),
then writes ``results.parquet`` (recall at radii 0…20 per part, with N_r statistics,
measured µs and counted operations per query) and ``queries.parquet`` (one row per query).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import zarr

from vprscale.compared.encoding import load_encoding, stored_encoding
from vprscale.compared.faisscodes import DEFAULT_NPROBE, FaissCodes
from vprscale.compared.pooled import PooledCodes, fit_pooled, is_pooled, parse_pooled, pooled_encodings
from vprscale.core.cluster import cluster_peak_rss, dask_client
from vprscale.core.errors import InputError
from vprscale.core.localcopy import cache_folder, upload
from vprscale.core.objects import Remote, shown
from vprscale.core.plaintext import terminal
from vprscale.core.progress import StepProgress
from vprscale.core.provenance import parquet_metadata, provenance
from vprscale.core.publish import PartialOutput, check_writable, exclusive, keep_beside, refuse_foreign, shared
from vprscale.dataset.references import reference_rows
from vprscale.dataset.store import ATTR, open_complete_group, read_sequences, store_identity, store_layout
from vprscale.evaluation.algorithms import registry
from vprscale.evaluation.algorithms.base import Answer
from vprscale.evaluation.algorithms.baseline import BaselineMap, baseline_limit, load_baseline_map
from vprscale.evaluation.algorithms.faisscodes import fit_codes
from vprscale.evaluation.algorithms.plugged import load_method
from vprscale.evaluation.metrics import RADII, TOP_N, metrics_at, recall_curve, run_metrics, top_distance
from vprscale.evaluation.nearest import check_nn, exact_neighbours, nn_rows
from vprscale.evaluation.runner import DEFAULT_REPEATS, Runner, Timing, spread
from vprscale.evaluation.taskgrid import run_task, task_table
from vprscale.evaluation.tasks import Allowed, TaskSet
from vprscale.method.index import Index
from vprscale.protocol import (
    PARTS,
    SEQUENCE_MODES,
    Centres,
    Sequences,
    WindowMask,
    part_weights,
    query_centres,
    window_frames,
    window_positions,
)

log = logging.getLogger(__name__)

DEFAULT_NOISES = ("qm1", "qm2")  # the query sets of a recipe-built store (own stores list theirs in the layout)
_HOLDS = ("{out}: already holds an evaluation; --force replaces it and keeps it beside, in {out.name}.previous/ "
          "(or give another --out)")
NN_QUERIES = 10_000  # query rows of the nearest-neighbour axis (Deep1M's and Deep1B's query sets hold 10,000)
MAX_FAISS_K = 1 << 14  # references a FAISS frame may retrieve (the lists of every held frame stay in memory)


@dataclass
class EvalRequest:
    """What ``vprscale eval`` was asked for."""

    store: Path | Remote  # a local store, or one on object storage
    indexes: list[Path] = field(default_factory=list)  # one index, or one per width of a d sweep
    index_urls: list[str | None] = field(default_factory=list)  # where each was read from, if a URL (a cache copy)
    noises: list[str] | None = None  # the store's query sets by name (None: every one the store holds)
    lengths: list[int] = field(default_factory=lambda: [1, 50, 100])
    modes: list[str] = field(default_factory=lambda: ["paper", "aligned"])
    baseline: bool = True
    z: int | None = None
    baseline_queries: int | None = None  # queries per baseline run; None: all below 10^8 query rows, else a sample
    compare: list[str] = field(default_factory=list)  # FAISS index_factory strings
    faiss_k: list[int] | None = None  # top-k per frame, one operating point each (None: CoarseHash's mean list size)
    faiss_nprobe: list[int] = field(default_factory=lambda: [DEFAULT_NPROBE])  # lists an IVF frame visits, likewise
    methods: list[str] = field(default_factory=list)  # your own methods: package.module:Class or installed names
    method_k: list[int] | None = None  # their k per frame, one operating point each (None: as faiss_k's default)
    compare_queries: int | None = None  # centres per compared run (None: all within the scan budget)
    flat_noise: list[str] | None = None  # noise levels flat (exhaustive-scan) FAISS codes run on (None: all)
    deep1b: str | None = None  # a compact store's sources, to recompute its references (synthetic: not needed)
    fas: str | None = None
    radii_m: list[float] | None = None  # radii in metres (a store with positions): results_m.parquet
    nn: bool = False  # the nearest-neighbour axis: nn.parquet
    nn_queries: int = NN_QUERIES  # Deep1B query rows it is measured on (evenly spaced)
    task: str | None = None  # MSLS's task (im2im, seq2im, im2seq, seq2seq) instead of the frame grid
    seq_length: int = 3
    subtask: str = "all"
    threshold_m: float = 25.0  # a task's positives: a database frame within this of a query frame
    export_msls: Path | None = None  # the task's answers as MSLS's prediction file(s)
    repeats: int = DEFAULT_REPEATS  # timing repeats of every timed kernel
    force: bool = False  # replace an evaluation already in the output (kept beside as <out>.previous)
    out: Path | Remote | None = None  # a URL's evaluation is made in the cache, then uploaded
    workers: int = 2
    scheduler: str | None = None
    quiet: bool = False


class QuerySet:
    """The query frames of a store that an evaluation may read, with their truth and part.

    A full store holds every frame; a compact one only the windows its build kept
    (:mod:`vprscale.dataset.compact`). Either way ``gt_at``/``part_at`` answer for any frame
    (−1 / 255 where the store holds nothing), and ``rows`` reads descriptors of held frames.
    """

    def __init__(self, group: zarr.Group, layout: dict[str, Any], noise: str | None = None) -> None:
        self.group = group
        self.compact = layout["kind"] == "compact"
        own = layout.get("query_sets", {}).get(noise)  # a set of its own length, with its own labels
        side = f"query_{noise}" if own else "query"
        self.n_deep = int((own or layout)["n_deep1b"])
        gt = group[f"{side}_gt" if own else "gt"]
        if self.compact:
            self.n_query = int(layout["n_query"])
            self.frames = group["query_frames"][:]
            self.lengths = set(layout["eval_lengths"])
        else:
            self.n_query = int(gt.shape[0])
            self.frames = None
        self.noises = list(layout.get("noises", DEFAULT_NOISES))
        self.sequences = read_sequences(group, side)  # a store of many sequences (None: one traverse)
        self._gt = gt[:]
        self._part = group[f"{side}_part"][:]
        if f"{side}_pos" in group:  # a store of your own: every row's position
            self.positions, self._pos_from = (group["ref_pos"][:], group[f"{side}_pos"][:]), 0
        elif "fas_query_pos" in group:  # a recipe's store: the FAS part's, rows from n_deep1b on
            self.positions, self._pos_from = (group["fas_ref_pos"][:], group["fas_query_pos"][:]), self.n_deep
        else:
            self.positions = None

    def _pos(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, np.int64)
        if not self.compact:
            return t, np.ones(len(t), bool)
        pos = np.minimum(np.searchsorted(self.frames, t), max(0, len(self.frames) - 1))
        return pos, (self.frames[pos] == t) if len(self.frames) else np.zeros(len(t), bool)

    def gt_at(self, t: np.ndarray) -> np.ndarray:
        pos, held = self._pos(t)
        return np.where(held, self._gt[pos], -1)

    def pos_at(self, t: np.ndarray) -> np.ndarray:
        """The query frames' positions in metres (NaN where the store has none: the Deep1B part)."""
        rows = (self._pos(t)[0] if self._pos_from == 0 else np.asarray(t, np.int64)) - self._pos_from
        return _positions(self.positions[1], rows)

    def ref_pos_at(self, ids: np.ndarray) -> np.ndarray:
        """The references' positions in metres (NaN for −1 and where the store has none)."""
        ids = np.asarray(ids, np.int64)
        return _positions(self.positions[0], np.where(ids >= 0, ids - self._pos_from, -1))

    def part_at(self, t: np.ndarray) -> np.ndarray:
        pos, held = self._pos(t)
        return np.where(held, self._part[pos], 255).astype(np.uint8)

    def centres(self, z: int, L: int) -> Centres:
        c = query_centres(self.gt_at, self.n_query, self.n_deep, z, L, self.sequences)
        if self.compact and len(c.t):
            missing = ~np.isin(window_frames([c.t], [L]), self.frames)
            if missing.any() or L not in self.lengths:
                raise InputError(f"--L {L} --z {z}: this compact store holds the query windows of "
                                 f"L = {sorted(self.lengths)} at its recipe's stride only")
        return c

    def rows(self, noise: str, frames: np.ndarray) -> np.ndarray:
        pos, held = self._pos(frames)
        assert held.all(), "frames outside the held windows"
        return self.group[f"query_{noise}"].get_orthogonal_selection((pos, slice(None)))


def check_request(req: EvalRequest) -> None:
    """Refuse bad parameters before anything is read or built (the index list is checked by :func:`evaluate`)."""
    for flag, values in (("--noise", req.noises), ("--flat-noise", req.flat_noise), ("--L", req.lengths),
                         ("--modes", req.modes)):
        if values is not None and not values:
            raise InputError(f"{flag}: the list is empty; give at least one value")
    for flag, values in (("--noise", req.noises), ("--flat-noise", req.flat_noise)):
        if values is not None and len(set(values)) != len(values):
            raise InputError(f"{flag}: a query set is given twice")
    bad = [m for m in req.modes if m not in SEQUENCE_MODES]
    if bad:
        raise InputError(f"--modes {','.join(bad)}: unknown mode; choose from {', '.join(SEQUENCE_MODES)}")
    if any(L < 1 for L in req.lengths):
        raise InputError("--L: sequence lengths must be at least 1")
    if req.z is not None and req.z < 1:
        raise InputError(f"--z {req.z}: must be at least 1")
    for flag, values in (("--faiss-k", req.faiss_k), ("--faiss-nprobe", req.faiss_nprobe), ("--method-k", req.method_k),
                         ("--compare-queries", [req.compare_queries])):
        for value in values or []:
            if value is not None and value < 1:
                raise InputError(f"{flag} {value}: must be at least 1")
        if values is not None and len(set(values)) != len(values):
            raise InputError(f"{flag}: a value is given twice")
    if req.radii_m is not None and (not req.radii_m or any(not (r > 0 and np.isfinite(r)) for r in req.radii_m)
                                    or len(set(req.radii_m)) != len(req.radii_m)):
        raise InputError(f"--radius-m {','.join(map(str, req.radii_m))}: give distinct radii in metres above 0")
    if req.faiss_nprobe is not None and not req.faiss_nprobe:
        raise InputError("--faiss-nprobe: the list is empty")
    for flag, given in (("--compare", req.compare), ("--method", req.methods)):
        if len(set(given)) != len(given):
            raise InputError(f"{flag}: {next(f for f in given if given.count(f) > 1)} given twice")


def evaluate(req: EvalRequest) -> dict[str, Any]:
    """Run the grid and write ``results.parquet`` and ``queries.parquet``; returns a summary."""
    check_request(req)
    if not req.indexes:
        raise InputError("eval: give an INDEX, or --d to index the store at several widths")
    if (req.compare or req.methods) and len(req.indexes) > 1:
        flag = "--compare" if req.compare else "--method"
        raise InputError(f"{flag}: compares with one index at a time, not with a --d sweep")
    t_start = time.perf_counter()
    group = open_complete_group(req.store)
    meta = group.attrs[ATTR]
    layout = store_layout(group)
    identity = store_identity(group)
    noises = list(layout.get("noises", DEFAULT_NOISES))
    unknown = [n for n in req.noises or [] if n not in noises]
    if unknown:
        raise InputError(f"--noise {','.join(unknown)}: {req.store} holds no such query set; choose from "
                         f"{', '.join(noises)}")
    req.noises = req.noises or noises
    # the query sets' labels: shared by sets row for row, each set's own where their lengths differ
    one = None if "query_sets" in layout else QuerySet(group, layout)
    sets = {noise: one or QuerySet(group, layout, noise) for noise in req.noises}
    qs = sets[req.noises[0]]
    ref_sequences = read_sequences(group, "ref")
    if req.radii_m and any(q.positions is None for q in sets.values()):
        raise InputError(f"--radius-m: {req.store} holds no positions; build it with --ref-pos and --query-pos "
                         "(docs/bring-your-own.md)")
    outside = [n for n in req.flat_noise or [] if n not in req.noises]
    if outside:
        raise InputError(f"--flat-noise {','.join(outside)}: not among the evaluated noise levels "
                         f"({', '.join(req.noises)})")
    task = None
    if req.task is not None:
        if req.radii_m or req.nn or len(req.indexes) > 1:
            flag = "--radius-m" if req.radii_m else "--nn" if req.nn else "--d"
            raise InputError(f"{flag}: not with --task (a task scores its own positives, on one index)")
        if "query_sets" in layout and len(req.noises) > 1:
            raise InputError("--task: this store's query sets have their own lengths; evaluate one at a time, "
                             f"--noise NAME ({', '.join(req.noises)})")
        side = f"query_{req.noises[0]}" if "query_sets" in layout else "query"
        task = TaskSet(group, req.task, req.seq_length, req.subtask, req.threshold_m, side)
        if req.export_msls is None and not task.scored:
            raise InputError(f"--task {req.task}: {req.store} holds no positions (MSLS's test cities): nothing to "
                             "score; --export-msls FILE writes the predictions for MSLS's own server")
        req.lengths = [task.match_length]
    elif req.export_msls is not None:
        raise InputError("--export-msls: writes a task's predictions; give --task too")
    shortest = min(q.n_query for q in sets.values())
    too_long = [L for L in req.lengths if L > shortest]
    if too_long:
        raise InputError(f"--L {too_long[0]}: longer than the {shortest:,} query frames")
    z = req.z or meta["recipe"]["query_stride"]
    dim = int(meta["recipe"]["dim"])
    plugged = [load_method(spec, registry.installed_methods()) for spec in req.methods]
    with dask_client(req.scheduler, req.workers) as client:
        index_paths = req.indexes
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
        remote = req.out if isinstance(req.out, Remote) else None
        if remote is not None:  # made in the cache, uploaded once published (core/localcopy)
            check_writable(remote.parent)
            refuse_foreign(remote)  # before the work: what is there is replaced only if vprscale wrote it
            if (remote / "eval.json").exists() and not req.force:
                raise InputError(_HOLDS.format(out=remote))
        out = cache_folder(remote, fresh=True) if remote else Path(req.out) if req.out else (
            index_paths[0] / "eval" if len(index_paths) == 1 else
            req.store.parent / f"{req.store.name.removesuffix('.zarr')}-dsweep.eval")
        if out.exists() and not out.is_dir():
            raise InputError(f"--out {out}: is a file, not a directory for the evaluation")
        if out.is_dir() and any(out.iterdir()) and not (out / "eval.json").is_file():
            raise InputError(f"--out {out}: exists and holds something other than an evaluation; not replaced")
        partial = PartialOutput(out, {"eval": time.time_ns()})
        if (out / "eval.json").is_file() and not req.force and not partial.sealed.exists():
            raise InputError(_HOLDS.format(out=out))
        check_writable(out.parent)
        compared = _compared(req, indexes, dim)
        # a task's pooled windows: only those it may answer (MSLS's database windows)
        pooled = _pooled(req, indexes, dim, ref_sequences if task is None else Allowed(task.allowed))
        stored = {m.factory: stored_encoding(req.store, m.factory, identity) for m in compared}  # vprscale encode's
        _check_methods(req, plugged, indexes[0][1])
        if req.nn:
            if "query_sets" in layout:
                raise InputError("--nn: measured on the same query rows of every set; this store's sets have "
                                 "their own lengths")
            check_nn(indexes[0][1], qs.n_deep)
        base = load_baseline_map(group, layout) if req.baseline else None
        with ExitStack() as locks:
            for path in index_paths:  # re-indexing is refused during evaluations of the index, not they of each other
                locks.enter_context(shared(path))
            locks.enter_context(exclusive(out))
            if partial.recover():  # a killed run had sealed this evaluation: its publishing is finished, not redone
                log.info(f"{out}: finished publishing the evaluation a killed run had completed")
                return {"out": str(out), "rows": 0, "queries": 0, "z": z, "table": "", "recovered": True}
            if (out / "eval.json").is_file() and not req.force:
                raise InputError(_HOLDS.format(out=out))
            partial.open()
            t_fit = time.perf_counter()
            # encoded by vprscale encode: read, not redone; side by side (at 10M a graph and a fast-scan
            # code's packed lists take tens of seconds each, FAISS and numpy mostly outside the GIL)
            with ThreadPoolExecutor(req.workers) as pool:
                list(pool.map(lambda m: load_encoding(stored[m.factory], m),
                              [m for m in compared if stored[m.factory] is not None]))
            to_fit = [m for m in compared if stored[m.factory] is None]
            needs_ref = to_fit or plugged or pooled or req.nn
            ref = reference_rows(req.store, group, req.deep1b, req.fas) if needs_ref else None
            fit_codes(to_fit, ref, req.quiet) if to_fit else None
            fit_pooled(pooled, ref, not req.quiet) if pooled else None
            fit_s = time.perf_counter() - t_fit
            method_fit_s = _fit_methods(plugged, ref, req.quiet) if plugged else {}
            written: list[str] = []
            if task is not None:
                rows, queries, written = run_task(req, task, qs, dim, indexes, base, compared, pooled, plugged,
                                                  _method_k(req, indexes[0][1]), layout.get("msls", {}).get("cities",
                                                                                                          []),
                                                  req.export_msls)
                rows_m = []
            else:
                rows, queries, rows_m = _grid(req, sets, z, dim, indexes, base, compared, pooled, plugged,
                                              ref_sequences)
            columns = {"scale": meta["recipe"]["scale"], "store": shown(req.store),
                       "store_identity": identity}
            record = provenance(inputs={"store_identity": identity, "indexes": [
                {"path": where, "store_identity": i.meta["store"]["identity"], "d": i.d, "k": i.k}
                for where, (_, i) in zip(_index_sources(req), indexes, strict=True)]},
                workers=req.workers, repeats=req.repeats)
            _write_parquet(partial.path / "results.parquet", rows, columns, record)
            _write_parquet(partial.path / "queries.parquet", queries, columns, record)
            if rows_m:
                _write_parquet(partial.path / "results_m.parquet", rows_m, columns, record)
            if req.nn:
                _write_parquet(partial.path / "nn.parquet", _nn(req, qs, indexes[0][1], dim, compared, ref),
                               columns, record)
            summary = {"wall_s": time.perf_counter() - t_start, "peak_rss_bytes": cluster_peak_rss(client), "z": z,
                       "noises": req.noises, "flat_noise": req.flat_noise,
                       "radii_m": req.radii_m, "nn_queries": req.nn_queries if req.nn else None,
                       "lengths": req.lengths, "modes": req.modes,
                       **({"task": {"task": task.task, "seq_length": task.seq_length, "subtask": task.subtask,
                                    "threshold_m": task.threshold_m, "queries": len(task.centres),
                                    "predictions": written}} if task is not None else {}),
                       **({"windows": window_counts(list(sets.values()), ref_sequences, req.lengths, z)}
                          if qs.sequences is not None or ref_sequences is not None else {}),
                       "baseline": req.baseline,
                       "baseline_queries": baseline_limit(req.baseline_queries, max(q.n_query for q in sets.values())),
                       "layout": layout["kind"],
                       "indexes": _index_sources(req),
                       "compare": {c.name: {"k": req.faiss_k or [c.k], "nprobe": req.faiss_nprobe if c.ivf else None,
                                            "bytes_per_place": c.bytes_per_place,
                                            "encoding": str(stored[c.factory]) if stored[c.factory] else None}
                                   for c in compared},
                       "pooled": {s.name: {"pooling": s.pooling, "factory": s.factory, "rerank": s.rerank,
                                           "lengths": sorted(p.codes), "bytes_per_place": p.bytes_per_place}
                                  for p in pooled for s in p.specs},
                       "compare_fit_s": fit_s if compared or pooled else None,
                       "methods": {label: {"k": _method_k(req, indexes[0][1]), "fit_s": method_fit_s[label]}
                                   for label, _ in plugged}, **columns,
                       "provenance": record}
            (partial.path / "eval.json").write_text(json.dumps(summary, indent=1))
            if req.force and (out / "eval.json").is_file():  # the previous evaluation is kept, not replaced
                keep_beside(out)
            partial.publish()  # the three files appear together, by one rename
        if remote is not None:
            upload(out, remote, keep=True)  # with --force: the previous evaluation is kept beside
    n_queries = sum(t.num_rows for t in queries) if task is not None else len(queries)
    return {"out": str(remote or out), "rows": len(rows), "queries": n_queries, "z": z,
            "table": task_table(rows) if task is not None else _summary_table(rows),
            "windows": None if task is not None else summary.get("windows"), "predictions": written}


def window_counts(sets: list[QuerySet], ref_sequences: Sequences | None, lengths: list[int], z: int
                  ) -> dict[str, Any]:
    """What a store of many sequences leaves out, per ``L``: the query centres (on the stride,
    with a truth, in every query set evaluated) whose window would cross a sequence's end or a
    gap, and the places on which no reference window can be centred. Neither is ever a query, a
    candidate or an answer."""
    counts: dict[str, Any] = {}
    for L in lengths:
        crossing = 0
        for qs in (q for q in sets if q.sequences is not None):
            t = np.arange(0, qs.n_query, z, dtype=np.int64)
            t = t[qs.gt_at(t) >= 0]
            crossing += int((~qs.sequences.window_ok(t, L)).sum())
        counts[str(L)] = {"query_centres_without_window": crossing,
                          "places_without_window": ref_sequences.missing(L) if ref_sequences is not None and L > 1
                          else 0}
    return counts


def _index_sources(req: EvalRequest) -> list[str]:
    """Where the evaluated indexes were read from, as the evaluation records them: a URL for one
    on object storage (read from its copy in the cache), else the absolute path."""
    urls = req.index_urls if len(req.index_urls) == len(req.indexes) else [None] * len(req.indexes)
    return [url or str(Path(p).resolve()) for p, url in zip(req.indexes, urls, strict=True)]


def _default_k(idx: Index) -> int:
    """References a compared method's frame retrieves by default: CoarseHash's mean list size."""
    return max(1, int(round(idx.n_ref / max(1, idx.occupied))))


def _method_k(req: EvalRequest, idx: Index) -> list[int]:
    return req.method_k or [_default_k(idx)]


def _check_methods(req: EvalRequest, plugged: list[tuple[str, Any]], idx: Index) -> None:
    labels = [label for label, _ in plugged]
    if len(set(labels)) != len(labels):
        raise InputError(f"--method: two methods are named {next(x for x in labels if labels.count(x) > 1)}; "
                         "give each class its own name attribute")
    for k in req.method_k or []:
        if k > min(idx.n_ref, MAX_FAISS_K):
            raise InputError(f"--method-k {k:,}: at most {min(idx.n_ref, MAX_FAISS_K):,} (the references, and "
                             f"{MAX_FAISS_K:,} per frame: each frame's list is held for every window)")


def _fit_methods(plugged: list[tuple[str, Any]], ref: Any, quiet: bool) -> dict[str, float]:
    """Fit every ``--method`` on the reference rows (a Dask array); seconds each took."""
    took = {}
    for label, method in plugged:
        if not quiet:
            log.info(f"… fit {label} on {ref.shape[0]:,} references")
        t0 = time.perf_counter()
        method.fit(ref)
        took[label] = time.perf_counter() - t0
    return took


def _compared(req: EvalRequest, indexes: list[tuple[Path, Index]], dim: int) -> list[FaissCodes]:
    """The FAISS methods asked for (factory strings checked now, before anything is read).

    Each frame retrieves ``k`` references: by default CoarseHash's mean list size on the
    index, so that both methods propose as many candidates per frame.
    """
    if not req.compare:
        return []
    idx = indexes[0][1]
    for k in req.faiss_k or []:
        if k > min(idx.n_ref, MAX_FAISS_K):
            raise InputError(f"--faiss-k {k:,}: at most {min(idx.n_ref, MAX_FAISS_K):,} (the references, and "
                             f"{MAX_FAISS_K:,} per frame: each frame's list is held for every window)")
    k = (req.faiss_k or [_default_k(idx)])[0]
    methods = [FaissCodes(factory, dim, k, req.faiss_nprobe[0], req.workers)
               for factory in req.compare if not is_pooled(factory)]
    for m in methods:
        if m.ivf is not None and m.ivf.nlist > idx.n_ref:
            raise InputError(f"--compare {m.factory}: {m.ivf.nlist:,} inverted lists for {idx.n_ref:,} references; "
                             "FAISS needs at least one reference per list to train")
    return methods


def _nn(req: EvalRequest, qs: QuerySet, idx: Index, dim: int, compared: list[FaissCodes], ref: Any
        ) -> list[dict]:
    """``nn.parquet``'s rows: on ``nn_queries`` evenly spaced query rows of the Deep1B part of each
    noise level, their exact neighbours found in one scan of the references for every level."""
    held = np.arange(qs.n_deep) if qs.frames is None else qs.frames[qs.frames < qs.n_deep]
    frames = held[spread(len(held), req.nn_queries)]
    rows = {noise: qs.rows(noise, frames) for noise in req.noises}
    truth = exact_neighbours(ref, np.concatenate(list(rows.values())), req.workers, not req.quiet)
    bar = StepProgress("nearest neighbours", len(rows) * (1 + len(compared)), req.quiet)
    found = []
    for i, (noise, x) in enumerate(rows.items()):
        found += nn_rows(noise, x, truth[i * len(frames) : (i + 1) * len(frames)], idx, dim, compared, req.workers,
                         bar)
    bar.close()
    return found


def _pooled(req: EvalRequest, indexes: list[tuple[Path, Index]], dim: int,
            ref_sequences: WindowMask | None) -> list[PooledCodes]:
    """The pooled sequence descriptors asked for (``--compare seq:…``): an encoding per pooling and
    code, with a code per evaluated L > 1."""
    specs = [parse_pooled(s) for s in req.compare if is_pooled(s)]
    if specs and not any(1 < L <= indexes[0][1].n_ref for L in req.lengths):
        raise InputError(f"--compare {specs[0].name}: a pooled descriptor matches sequences; evaluate an --L above 1 "
                         f"(--L {','.join(map(str, req.lengths))} has none)")
    return pooled_encodings(specs, dim, req.lengths, indexes[0][1].n_ref, req.faiss_nprobe[0], req.workers,
                            ref_sequences)


def _positions(table: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``table[rows]``, NaN for rows outside it."""
    held = (rows >= 0) & (rows < len(table))
    out = np.full((*rows.shape, table.shape[1]), np.nan)
    out[held] = table[rows[held]]
    return out


def _grid(req: EvalRequest, sets: dict[str, QuerySet], z: int, dim: int, indexes: list, base: BaselineMap | None,
          compared: list[FaissCodes], pooled: list[PooledCodes], plugged: list[tuple[str, Any]],
          ref_sequences: Sequences | None = None) -> tuple[list[dict], list[dict]]:
    """Every method of every index on every noise, L and mode; the methods come from the registry.
    Each noise is a query set (``sets``), whose centres are its own when its labels are."""
    rows: list[dict] = []
    queries: list[dict] = []
    rows_m: list[dict] = []
    windows = {id(qs): _windows(qs, z, req.lengths) for qs in sets.values()}
    runner = Runner(req.workers, req.repeats)
    methods = [(path, registry.create(registry.Context(
        index_path=path, index=idx, dim=dim, n_query=max(q.n_query for q in sets.values()),
        n_centres=max(len(c.t) for centres, _ in windows.values() for c in centres.values()),
        lengths=req.lengths, workers=req.workers, baseline=base, baseline_queries=req.baseline_queries,
        compared=compared, pooled=pooled, compare_queries=req.compare_queries, flat_noise=req.flat_noise,
        faiss_k=req.faiss_k, faiss_nprobe=req.faiss_nprobe, plugged=plugged, method_k=_method_k(req, idx),
        ref_sequences=ref_sequences)))
        for path, idx in indexes]
    steps = sum(1 + sum(len(a.modes(L, req.modes)) for L in req.lengths)
                for noise in req.noises for _, algos in methods for a in algos if a.runs_on(noise))
    bar = StepProgress("evaluate", steps, req.quiet)
    # one method's frame state at a time (at 10M a method's is up to 1.5 GB a noise level: all of
    # them at once held 6 GB), its runs' rows put back in the order noise, index, L, method, mode
    runs: dict[tuple[int, int, int, int], tuple[list, list, list]] = {}
    for n_i, noise in enumerate(req.noises):
        qs = sets[noise]
        centres, frames = windows[id(qs)]
        weights = part_weights(qs.n_query, qs.n_deep)
        x_q = qs.rows(noise, frames)
        for p_i, (path, algos) in enumerate(methods):
            for a_i, alg in enumerate(algos):
                if not alg.runs_on(noise):
                    continue
                bar.step(f"{noise} {alg.name}: per-frame work")  # on the frames it localises
                alg.prepare(noise, frames, x_q, {L: centres[L].t for L in req.lengths})
                sample = {L: spread(len(centres[L].t), alg.query_limit) for L in req.lengths}
                held = window_frames([centres[L].t[sample[L]] for L in req.lengths], req.lengths)
                state, frame_cost = runner.frames(alg, x_q[np.searchsorted(frames, held)])
                for l_i, L in enumerate(req.lengths):
                    c = centres[L]
                    t = c.t[sample[L]]
                    truth, parts = qs.gt_at(t), qs.part_at(t)
                    pos = window_positions(held, t, L)
                    key = {"noise": noise, "L": L, "index": str(Path(path).resolve()), "fas_stride": c.fas_stride,
                           "method": alg.name, "family": alg.family, **alg.columns(),
                           "bytes_per_place": alg.bytes_per_place}
                    run = runs.setdefault((n_i, p_i, l_i, a_i), ([], [], []))
                    for mode in alg.modes(L, req.modes):
                        bar.step(f"{noise} {alg.name} L = {L}" + (f", {mode} mode" if mode else ""))
                        answer, timing = runner.localise(alg, state, pos, L, mode, frame_cost)
                        in_list = alg.in_list(state, pos, truth) if L == 1 else None
                        metres = (run[2], req.radii_m, qs.ref_pos_at, qs.pos_at(t)) if req.radii_m else None
                        _emit(run[0], run[1], {**key, "mode": mode}, t, truth, parts, answer, timing, in_list,
                              weights if c.fas_stride is not None else None, metres)
                del state  # before the next method's is made
    for run in (runs[k] for k in sorted(runs)):
        rows += run[0]
        queries += run[1]
        rows_m += run[2]
    bar.close()
    return rows, queries, rows_m


def _windows(qs: QuerySet, z: int, lengths: list[int]) -> tuple[dict[int, Centres], np.ndarray]:
    """A query set's centres for each L, and every frame of their windows."""
    centres = {L: qs.centres(z, L) for L in lengths}
    return centres, window_frames([centres[L].t for L in lengths], lengths)


def _emit(rows: list, queries: list, key: dict, t: np.ndarray, truth: np.ndarray, parts: np.ndarray,
          answer: Answer, timing: Timing, in_list: np.ndarray | None, weights: dict[str, float] | None,
          metres: tuple[list, list[float], Callable, np.ndarray] | None = None) -> None:
    """Rows of ``results`` and ``queries`` for one run of one method, and with ``metres``
    (``(rows_m, radii, ref_pos_at, query_pos)``) the rows of ``results_m``: the same figures with
    a match correct when the matched reference lies within a radius in metres of the query's
    position (VPR-methods-evaluation's positives), each query's distance in ``queries.error_m``;
    for the parts whose every query has a position (a recipe's store: the FAS part).

    With ``weights`` (a stratified sample) the overall figures weight each part by its
    share of the query rows (each query by its part's share over its part's queries);
    without, every query localised counts once.
    """
    match, n_r = answer.match, answer.n_r
    ranked, weighed = answer.ranking
    error = np.abs(np.asarray(match, np.int64) - truth)
    if metres is not None:
        rows_m, radii, ref_pos_at, query_pos = metres
        error_m = top_distance(np.asarray(match, np.int64)[:, None], query_pos, ref_pos_at, 1)
        near_m = {n: top_distance(ranked, query_pos, ref_pos_at, n) for n in TOP_N[1:]}
        placed = np.isfinite(query_pos).all(axis=1)
    select = {name: np.ones(len(t), bool) if code is None else parts == code for name, code in PARTS.items()}
    held = [p for p in ("deep1b", "fas") if select[p].any()]
    if len(held) < 2:  # one part (a store of your own without --part): its rows are the "all" rows
        select = {"all": select["all"]}
    per_query = None
    if weights is not None and held:
        per_query = np.zeros(len(t))
        for p in held:
            per_query[select[p]] = weights[p] / select[p].sum()
    for name, sel in select.items():
        w = per_query[sel] if name == "all" and per_query is not None else None
        figures = run_metrics(error[sel], ranked[sel], truth[sel], answer.score[sel], w)
        in_curve = recall_curve(in_list[sel], w) if in_list is not None else None
        n = int(sel.sum())
        nr = n_r[sel]
        stats = {"n_queries": n,
                 "nr_mean": float(nr.mean()) if len(nr) else np.nan,
                 "ranked_mean": float(weighed[sel].mean()) if n else np.nan,
                 "nr_median": float(np.median(nr)) if len(nr) else np.nan,
                 "nr_p95": float(np.percentile(nr, 95)) if len(nr) else np.nan,
                 **timing.columns(), "ops_per_query": answer.ops_per_query}
        for r in RADII:
            rows.append({**key, "part": name, "radius": int(r), **{f: float(v[r]) for f, v in figures.items()},
                         "recall_in_list": float(in_curve[r]) if in_curve is not None else None, **stats})
        if metres is not None and placed[sel].all() and sel.any():
            at = metrics_at(error_m[sel], {n: e[sel] for n, e in near_m.items()}, answer.score[sel], w,
                            np.asarray(radii, np.float64))
            for i, r in enumerate(radii):
                rows_m.append({**key, "part": name, "radius_m": float(r), **{f: float(v[i]) for f, v in at.items()},
                               **stats})
    for i in range(len(t)):
        queries.append({**key, "t": int(t[i]), "gt": int(truth[i]), "match": int(match[i]), "error": int(error[i]),
                        **({"error_m": float(error_m[i]) if placed[i] else None} if metres is not None else {}),
                        "score": float(answer.score[i]), "top": ranked[i].tolist(),
                        "n_r": int(n_r[i]), "in_list": int(in_list[i]) if in_list is not None else None,
                        "part": "deep1b" if parts[i] == 0 else "fas"})


def _write_parquet(path: Path, rows: list[dict] | list[pa.Table], columns: dict, record: dict) -> None:
    """Rows (dicts, or tables of them) with the store's columns; the provenance record in the
    file's key-value metadata."""
    if rows and isinstance(rows[0], pa.Table):
        table = pa.concat_tables(rows, promote_options="permissive")
        for i, f in enumerate(table.schema):  # a column no run filled (params, mode): text, as in the frame grid
            if pa.types.is_null(f.type):
                table = table.set_column(i, f.name, table.column(i).cast(pa.string()))
        for name, value in columns.items():
            table = table.append_column(name, pa.repeat(pa.scalar(value), table.num_rows))
    else:
        table = pa.Table.from_pylist([{**r, **columns} for r in rows])
    table = table.replace_schema_metadata({**(table.schema.metadata or {}), **parquet_metadata(record)})
    pq.write_table(table, path, compression="zstd")


def _summary_table(rows: list[dict]) -> str:
    """The printed summary: one line per method, parameters, mode, L and part (recall at 0, 5 and
    20 frames); ``vprscale results`` shows every column."""
    keys = [(terminal(r["noise"]), terminal(r["method"]), terminal(r.get("params") or "-"), r["mode"] or "-",
             "-" if r["d"] is None else r["d"], r["L"], r["part"]) for r in rows]  # names as text on a terminal
    width = max([len("params"), *(len(k[2]) for k in keys)])
    lines = [f"{'noise':<5} {'method':<20} {'params':<{width}} {'mode':<8} {'d':>3} {'L':>4} {'part':<7} {'n':>6} "
             f"{'≤0 fr':>6} {'≤5 fr':>6} {'≤20 fr':>6} {'N_r':>7} {'B/place':>8} {'µs/q':>10} {'ops/q':>11}"]
    by_key: dict[tuple, dict[int, dict]] = {}
    for key, r in zip(keys, rows, strict=True):
        by_key.setdefault(key, {})[r["radius"]] = r
    for (noise, method, params, mode, d, L, part), radii in by_key.items():
        r0 = radii[0]
        lines.append(f"{noise:<5} {method:<20} {params:<{width}} {mode:<8} {d:>3} {L:>4} {part:<7} "
                     f"{r0['n_queries']:>6} {radii[0]['recall']:>6.3f} {radii[5]['recall']:>6.3f} "
                     f"{radii[20]['recall']:>6.3f} {r0['nr_mean']:>7.1f} {r0['bytes_per_place']:>8.2f} "
                     f"{r0['us_per_query']:>10.2f} {r0['ops_per_query']:>11.0f}")
    lines.append("≤r fr: share of queries whose match lies within r frames of the truth (not Recall@N)")
    return "\n".join(lines)
