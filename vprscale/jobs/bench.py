"""``vprscale bench``: benchmark runs that print their figures (never asserted in tests).

Each job runs as a child process so that its wall time and peak memory are its own.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.objects import is_url
from vprscale.core.throughput import throughput
from vprscale.jobs.child import vprscale_argv


def spawn(argv: list[str], env: dict[str, str] | None = None) -> dict[str, Any]:
    """Run the process ``argv`` (``env``: its environment, default this one's) to its end: its
    exit code, wall time, peak RSS and CPU time (user and system, every thread of it)."""
    t0 = time.perf_counter()
    pid = os.spawnve(os.P_NOWAIT, argv[0], argv, os.environ if env is None else env)
    _, status, usage = os.wait4(pid, 0)
    return {"code": os.waitstatus_to_exitcode(status), "wall_s": time.perf_counter() - t0,
            "peak_rss_bytes": usage.ru_maxrss * 1024, "cpu_s": usage.ru_utime + usage.ru_stime}


def run_child(argv: list[str], fresh: Path | None = None, env: dict[str, str] | None = None) -> dict[str, Any]:
    """Run ``vprscale ARGV`` in a child process (:func:`spawn`); its summary, wall time and peak
    RSS. A build is timed fresh: the store ``fresh`` an earlier run left is deleted first,
    because replacing it (``--force`` deletes the old store once the new one is published) is
    not building."""
    if fresh is not None and fresh.exists():
        shutil.rmtree(fresh)
    with tempfile.TemporaryDirectory() as tmp:
        summary = Path(tmp) / "summary.json"
        r = spawn(vprscale_argv(*argv, "--summary", str(summary)), env)
        if r["code"] != 0:
            raise SystemExit(f"bench: vprscale {' '.join(argv)} failed")
        r["summary"] = json.loads(summary.read_text()) if summary.is_file() else {}
    return r


def io_floor(inputs: list[Path], write_bytes: int, where: Path) -> dict[str, float]:
    """Seconds to read the input files and to write as many bytes as the output holds."""
    t0 = time.perf_counter()
    read = 0
    for f in inputs:
        with open(f, "rb", buffering=0) as fh:
            buf = bytearray(1 << 24)
            while n := fh.readinto(buf):
                read += n
    t_read = time.perf_counter() - t0
    block = np.random.default_rng(0).integers(0, 255, 1 << 24, dtype=np.uint8).tobytes()
    target = where / ".io-floor.tmp"
    t0 = time.perf_counter()
    with open(target, "wb") as fh:
        left = write_bytes
        while left > 0:
            fh.write(block[: min(left, len(block))])
            left -= len(block)
    t_write = time.perf_counter() - t0
    target.unlink()
    return {"read_s": t_read, "read_bytes": read, "write_s": t_write, "write_bytes": write_bytes}


def bench_build(scale: str, out: str, deep1b: str | None, fas: str | None, workers: int) -> str:
    """Time a fresh build (:func:`run_child`)."""
    argv = ["build", "--scale", scale, "--out", out, "--workers", str(workers)]
    argv += (["--deep1b", deep1b] if deep1b else []) + (["--fas", fas] if fas else [])
    r = run_child(argv, fresh=Path(out) / f"{scale}.zarr")
    s = r["summary"]
    inputs = []  # the local input files, read again for the I/O floor (a URL's are read where they are)
    for p in (Path(p) for p in (deep1b, fas) if p and not is_url(p)):
        inputs += sorted(f for f in p.iterdir() if f.is_file()) if p.is_dir() else [p]
    floor = io_floor(inputs, s["bytes_on_disk"], Path(out))
    floor_s = floor["read_s"] + floor["write_s"]
    lines = [f"build {scale}: {r['wall_s']:.1f} s wall, peak RSS {r['peak_rss_bytes'] / 2**30:.2f} GiB, "
             f"{s['ref_rows']:,} ref + {s['query_rows']:,} query rows, {s['bytes_on_disk'] / 2**30:.2f} GiB on disk"]
    lines += [f"  stage {name}: {secs:.1f} s" for name, secs in s["stages_s"].items()]
    lines.append("  read " + throughput(s["input_rows"], s["input_bytes"], r["wall_s"], workers)
                 + f"; CPU {r['cpu_s']:,.1f} s, {s['input_rows'] / max(r['cpu_s'], 1e-9):,.0f} rows per CPU-second")
    lines.append(f"  I/O floor: read {floor['read_bytes'] / 2**30:.2f} GiB in {floor['read_s']:.1f} s + write "
                 f"{floor['write_bytes'] / 2**30:.2f} GiB in {floor['write_s']:.1f} s = {floor_s:.1f} s; "
                 f"build / floor = {r['wall_s'] / max(floor_s, 1e-9):.1f}×")
    return "\n".join(lines)


def bench_index(store: str, d: int | None, workers: int) -> str:
    r = run_child(["index", store, "--workers", str(workers)] + (["--d", str(d)] if d else []))
    s = r["summary"]
    per_place = sum(s["parts_published"].values()) / s["n_ref"]
    lines = [f"index {store} (d = {s['d']}): {r['wall_s']:.1f} s wall, peak RSS {r['peak_rss_bytes'] / 2**30:.2f} GiB, "
             f"whole index {per_place:.2f} bytes per place on disk"]
    lines += [f"  stage {k}: {v:.1f} s" for k, v in s["timings_s"].items()]
    lines.append(bench_lookup(s["index"]))
    return "\n".join(lines)


SCANS = {  # whole-table queries of the console, timed by bench lookup
    "count and sum every list entry": "SELECT count(*) AS n, sum(ref_id) AS s FROM lists",
    "list-size histogram": "SELECT size, count(*) AS n FROM buckets GROUP BY size ORDER BY size",
    "largest buckets from the lists": "SELECT hash, count(*) AS n FROM lists GROUP BY hash ORDER BY n DESC LIMIT 5",
}


def bench_lookup(index: str, n: int = 50) -> str:
    """Latency of one-address look-ups and time of whole-table scans through the sandboxed
    DuckDB console (its ``lists`` and ``buckets`` views are the index's Parquet tables)."""
    import pyarrow.parquet as pq

    from vprscale.evaluation.sqlchild import connect, query_table

    addresses = pq.read_table(Path(index) / "buckets.parquet", columns=["hash"])["hash"].to_numpy()
    picks = np.random.default_rng(0).choice(addresses, n)
    t0 = time.perf_counter()
    with connect(index) as con:
        t1 = time.perf_counter()
        query_table(con, f"SELECT ref_id FROM lists WHERE hash = {int(picks[0])}", 10.0)
        cold = time.perf_counter() - t1
        times = []
        for h in picks[1:]:
            t = time.perf_counter()
            query_table(con, f"SELECT ref_id FROM lists WHERE hash = {int(h)}", 10.0)
            times.append(time.perf_counter() - t)
        scans = []
        for what, sql in SCANS.items():
            t = time.perf_counter()
            query_table(con, sql, 3600.0)
            scans.append(f"  {what}: {time.perf_counter() - t:.2f} s")
    return "\n".join([f"  DuckDB look-up of one address: median {1e3 * np.median(times):.2f} ms, "
                      f"p95 {1e3 * np.percentile(times, 95):.2f} ms on an open console; first query "
                      f"{1e3 * cold:.1f} ms, sandboxed connection set-up {1e3 * (t1 - t0):.1f} ms", *scans])


def _frame_part(us: float | None) -> str:
    """`` (per-frame work x µs)`` where a method has per-frame work apart from its kernel."""
    return "" if us is None or us != us else f" (per-frame work {us:.2f})"


def bench_eval(store: str, index: str, args: list[str], workers: int) -> str:
    with tempfile.TemporaryDirectory() as tmp:
        r = run_child(["eval", store, index, "--out", tmp, "--workers", str(workers), *args])
        import pandas as pd

        res = pd.read_parquet(Path(tmp) / "results.parquet")
    res = res[(res.part == "all") & (res.radius == 20)]
    lines = [f"eval {store}: {r['wall_s']:.1f} s wall, peak RSS {r['peak_rss_bytes'] / 2**30:.2f} GiB"]
    for _, row in res.iterrows():
        lines.append(f"  {row.noise} {row.method:<10} {str(row['mode']):<8} L={row.L:<4} d={row.d:<3} "
                     f"{row.us_per_query:10.2f} µs/query{_frame_part(row.us_per_frame)}  N_r {row.nr_mean:7.1f}  "
                     f"within 20 frames {100 * row.recall:5.1f} %  ({row.n_queries} queries)")
    for (noise, L), g in res.groupby(["noise", "L"]):
        m = g[(g.method == "coarsehash") & (g["mode"].isna() | (g["mode"] == "paper"))]
        b = g[g.method == "baseline"]
        if len(m) and len(b):
            lines.append(f"  {noise} L={L}: baseline / method time = "
                         f"{b.us_per_query.iloc[0] / m.us_per_query.iloc[0]:.0f}×, operations = "
                         f"{b.ops_per_query.iloc[0] / m.ops_per_query.iloc[0]:.0f}×")
    return "\n".join(lines)


def bench_online(store: str, index: str, Ls: tuple[int, ...], frames: int = 3000, repeats: int = 5) -> str:
    """Online matching against the batch on the same frames, in one process: each L of ``Ls``,
    paper and aligned (L = 1: one mode).

    Per frame, the CPU time of this thread, each figure the median of its repeats and measured
    alike (one clock reading before and after the whole traverse): ``push`` frame by frame,
    ``push_many`` over the whole traverse, and the batch's ``Index.match`` on one thread, per
    query; hashing and per-frame work included in all three; the ratios are of those medians.
    A frame's latency is read apart, in a repeat of its own, from the monotonic clock around each
    push (median and p99 over every frame): reading the thread's CPU clock is a system call,
    which costs, and disturbs the caches, as much as a push. The matches are checked equal.
    """
    import numba
    import zarr

    from vprscale.method.index import Index
    from vprscale.method.online import OnlineMatcher

    idx = Index.load(index)
    q = zarr.open_group(store, mode="r")["query_qm1"]
    start = max(0, q.shape[0] // 2 - frames // 2)
    x = q[start : start + frames]
    _ = idx.planes
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    lines = [f"online matching, {idx.n_ref:,} places, {len(x):,} frames, CPU time of one thread, {repeats} repeats"]
    try:
        for L, mode in [(n, mode) for n in Ls for mode in (("paper", "aligned") if n > 1 else ("paper",))]:
            warm = OnlineMatcher(idx, L, mode)
            warm.push_many(x[: L + 10])
            for row in x[: L + 10]:
                warm.push(row)
            idx.match(x[: L + 10], L, mode=mode)
            each, pushed, many, batch = [], [], [], []
            latency = OnlineMatcher(idx, L, mode)
            for row in x:
                t0 = time.perf_counter_ns()
                latency.push(row)
                each.append(time.perf_counter_ns() - t0)
            for _ in range(repeats):
                online = OnlineMatcher(idx, L, mode)
                push_one = online.push
                t0 = time.thread_time_ns()
                got = [push_one(row) for row in x]
                pushed.append((time.thread_time_ns() - t0) / len(x))
                blocks = OnlineMatcher(idx, L, mode)
                t0 = time.thread_time_ns()
                block_match, _ = blocks.push_many(x)
                many.append((time.thread_time_ns() - t0) / len(x))
                t0 = time.thread_time_ns()
                found = idx.match(x, L, mode=mode)
                batch.append((time.thread_time_ns() - t0) / len(found.match))
                if not (np.array_equal(np.array(got[L - 1 :], dtype=np.int64), found.match)
                        and np.array_equal(block_match[L - 1 :], found.match)):
                    raise SystemExit("bench online: the online matches differ from the batch")
            median, p99 = float(np.median(each)) / 1e3, float(np.percentile(each, 99)) / 1e3
            push, many_us, batch_us = (float(np.median(v)) / 1e3 for v in (pushed, many, batch))
            lines.append(f"  L = {L:<4} {mode:<8} push {push:.2f} µs a frame (latency median {median:.2f}, "
                         f"p99 {p99:.2f}), "
                         f"push_many {many_us:.2f} µs a frame, batch {batch_us:.2f} µs a query; push / batch "
                         f"{push / batch_us:.2f}, push / push_many {push / many_us:.2f}; N_r mean "
                         f"{found.n_r.mean():.0f}; state {online.state_bytes / 1e3:.0f} kB")
    finally:
        numba.set_num_threads(threads)
    return "\n".join(lines)
