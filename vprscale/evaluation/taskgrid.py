"""An evaluation of MSLS's tasks (``vprscale eval --task``): every method on one task's
windows, timed as the frame grid times them, scored by recall@k and map@k
(:mod:`vprscale.evaluation.tasks`), and written in MSLS's prediction format on request."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from vprscale.core.progress import StepProgress
from vprscale.evaluation.algorithms import registry
from vprscale.evaluation.runner import Runner, spread
from vprscale.evaluation.tasks import KS, Allowed, TaskSet, keep_allowed, write_predictions
from vprscale.protocol import window_frames, window_positions

log = logging.getLogger(__name__)


def export_path(base: Path, run: str, runs: int) -> Path:
    """Where a run's prediction file goes: ``--export-msls FILE`` itself for one run, else FILE
    with the run's name before its suffix (``pred.csv`` → ``pred.coarsehash-paper.csv``)."""
    if runs == 1:
        return base
    safe = "".join(ch if ch.isalnum() or ch in "-_.+" else "_" for ch in run)
    return base.with_name(f"{base.stem}.{safe}{base.suffix}")


def run_task(req: Any, task: TaskSet, qs: Any, dim: int, indexes: list, base: Any, compared: list, pooled: list,
             plugged: list, method_k: list[int], cities: list[str], export: Path | None
             ) -> tuple[list[dict], list[pa.Table], list[str]]:
    """``(rows, queries, written)``: the task's rows of ``results`` (a row per method, mode, noise
    and city, and ``all``), its ``queries`` (a table per run), and the prediction files written."""
    L, t = task.match_length, task.centres
    frames = window_frames([t], [L])
    runner = Runner(req.workers, req.repeats)
    path, idx = indexes[0]
    algos = registry.create(registry.Context(
        index_path=path, index=idx, dim=dim, n_query=qs.n_query, n_centres=len(t), lengths=[L],
        workers=req.workers, baseline=base, baseline_queries=req.baseline_queries, compared=compared, pooled=pooled,
        compare_queries=req.compare_queries, flat_noise=req.flat_noise, faiss_k=req.faiss_k,
        faiss_nprobe=req.faiss_nprobe, plugged=plugged, method_k=method_k,
        ref_sequences=Allowed(task.allowed)))
    runs = [(noise, a, mode) for noise in req.noises for a in algos if a.runs_on(noise)
            for mode in a.modes(L, req.modes)]
    bar = StepProgress(f"evaluate {task.task}", len(runs), req.quiet)
    rows: list[dict] = []
    queries: list[pa.Table] = []
    written: list[str] = []
    state_of: tuple[Any, Any, Any] | None = None  # one method's frame state at a time
    for noise, alg, mode in runs:
        if state_of is None or state_of[0] != (noise, id(alg)):
            x_q = qs.rows(noise, frames)
            alg.prepare(noise, frames, x_q, {L: t})
            sample = spread(len(t), alg.query_limit)
            held = window_frames([t[sample]], [L])
            state, cost = runner.frames(alg, x_q[np.searchsorted(frames, held)])
            state_of = ((noise, id(alg)), (state, cost), (sample, held))
        state, cost = state_of[1]
        sample, held = state_of[2]
        bar.step(f"{noise} {alg.name}" + (f", {mode} mode" if mode else ""))
        centres = t[sample]
        answer, timing = runner.localise(alg, state, window_positions(held, centres, L), L, mode, cost)
        # what the task may not answer taken out (a frame's own ranking at L = 1 holds panoramas and
        # other subtasks; at L > 1 the matchers never propose them, and this changes nothing)
        ranked = keep_allowed(answer.ranking[0], task.allowed)
        name = alg.name + (f"-{mode}" if mode else "") + (f"-{noise}" if len(req.noises) > 1 else "")
        if export is not None and len(sample) < len(t):  # MSLS's scorer wants every query answered
            log.warning(f"{name}: answered {len(sample):,} of the {len(t):,} queries (a sample: --compare-queries, "
                        "or a scan beyond the budget); its predictions are not written")
        elif export is not None:
            out = export_path(export, name, len(runs))
            write_predictions(out, task, centres, ranked)
            written.append(str(out))
        if not task.scored:
            continue
        per_query = task.metrics(centres, ranked, task.n_positives[sample])
        key = {"task": task.task, "seq_length": task.seq_length, "subtask": task.subtask,
               "threshold_m": task.threshold_m, "noise": noise, "L": L, "method": alg.name, "family": alg.family,
               **alg.columns(), "mode": mode, "bytes_per_place": alg.bytes_per_place}
        city = task.q.city[centres]
        names = cities or ["all"]
        for part, sel in [("all", np.ones(len(centres), bool))] + [
                (names[c], city == c) for c in np.unique(city) if len(names) > 1]:
            rows.append({**key, "part": part, "n_queries": int(sel.sum()),
                         **{m: float(v[sel].mean()) for m, v in per_query.items()},
                         "nr_mean": float(answer.n_r[sel].mean()), **timing.columns(),
                         "ops_per_query": answer.ops_per_query})
        n = len(centres)  # the run's queries as columns (millions of queries: no row objects)
        queries.append(pa.table({**{k: pa.repeat(pa.scalar(v), n) for k, v in key.items()},
                                 "t": centres, "part": np.asarray(names, dtype=object)[city],
                                 "n_positives": task.n_positives[sample],
                                 "top": pa.FixedSizeListArray.from_arrays(np.ascontiguousarray(ranked).ravel(),
                                                                          ranked.shape[1]),
                                 **{m: np.asarray(v, np.float64) for m, v in per_query.items()}}))
    bar.close()
    return rows, queries, written


def task_table(rows: list[dict]) -> str:
    """The printed summary of a task: a line per method, mode and part, recall@k and map@k."""
    from vprscale.core.plaintext import terminal

    head = (f"{'method':<22} {'mode':<8} {'part':<10} {'n':>7}  "
            + " ".join(f"{f'R@{k}':>6}" for k in KS) + "  " + " ".join(f"{f'mAP@{k}':>7}" for k in KS)
            + f" {'B/place':>8} {'µs/q':>10}")
    lines = [head]
    for r in rows:
        lines.append(f"{terminal(r['method']):<22} {r['mode'] or '-':<8} {terminal(r['part']):<10} "
                     f"{r['n_queries']:>7,}  " + " ".join(f"{r[f'recall_at_{k}']:6.3f}" for k in KS) + "  "
                     + " ".join(f"{r[f'map_at_{k}']:7.3f}" for k in KS)
                     + f" {r['bytes_per_place']:8.2f} {r['us_per_query']:10.2f}")
    return "\n".join(lines)
