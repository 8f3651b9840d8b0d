"""``vprscale bench startup INDEX``: what the one-shot commands cost from start to exit.

Each command runs as a child process, several times; its CPU time is that of the whole process
tree (the SQL sandbox's child and the forkserver that starts it included), sampled every
``SAMPLE_S`` with psutil, since descendants that are not waited for never reach
``RUSAGE_CHILDREN``. CPU time, unlike wall time, does not grow with load on the machine.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import time
from pathlib import Path

from vprscale.jobs.child import vprscale_argv

SAMPLE_S = 0.01


def _commands(index: str) -> dict[str, list[str]]:
    return {"methods": ["methods"], "verify": ["verify", index], "occupancy": ["occupancy", index],
            "results": ["results", index], "sql": ["sql", index, "SELECT count(*) FROM buckets"]}


def tree_cpu(argv: list[str]) -> tuple[float, float, int]:
    """``(cpu_s, wall_s, exit status)`` of a command and every process it starts."""
    import psutil

    seen: dict[int, float] = {}
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    root = psutil.Process(proc.pid)
    while proc.poll() is None:
        try:
            family = [root, *root.children(recursive=True)]
        except psutil.Error:
            family = []
        for p in family:
            try:
                t = p.cpu_times()
                seen[p.pid] = max(seen.get(p.pid, 0.0), t.user + t.system)
            except psutil.Error:
                pass
        time.sleep(SAMPLE_S)
    wall = time.perf_counter() - t0
    usage = os.wait4(proc.pid, 0)[2] if proc.returncode is None else None
    own = seen.pop(proc.pid, 0.0)
    if usage is not None:
        own = max(own, usage.ru_utime + usage.ru_stime)
    return own + sum(seen.values()), wall, proc.returncode or 0


def bench_startup(index: str, repeats: int = 5) -> str:
    """Median and range of each one-shot command's CPU time over ``repeats`` runs."""
    if not (Path(index) / "index.json").is_file():
        from vprscale.core.errors import InputError

        raise InputError(f"{index}: not a vprscale index (no index.json)")
    lines = [f"one-shot commands on {index}: CPU time of the process tree, start to exit, {repeats} runs",
             f"{'command':<10}{'median s':>10}{'min s':>8}{'max s':>8}{'wall s':>8}"]
    for name, argv in _commands(index).items():
        runs = [tree_cpu(vprscale_argv(*argv)) for _ in range(repeats)]
        failed = [r for r in runs if r[2] != 0]
        if failed:
            lines.append(f"{name:<10} failed (exit {failed[0][2]})")
            continue
        cpu = [r[0] for r in runs]
        wall = statistics.median(r[1] for r in runs)
        lines.append(f"{name:<10}{statistics.median(cpu):>10.2f}{min(cpu):>8.2f}{max(cpu):>8.2f}{wall:>8.2f}")
    return "\n".join(lines)
