"""Kill -9 at every step of publishing (each unlink and rename after the seal), then run again:
the command succeeds and its output has the bytes of an undisturbed run."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from vprscale.cli import main

from .conftest import write_recipe

STRACE = shutil.which("strace")
pytestmark = pytest.mark.skipif(STRACE is None, reason="needs strace (installed by .ci/run)")
CALLS = "unlinkat,unlink,rename,renameat,renameat2,rmdir"
KILL_POINTS = 8  # publish steps killed at, per test (a sample when there are more)
HOLD_SECONDS = 600  # how long strace holds the call to be killed at (the kill comes within milliseconds)


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "vprscale.cli", *args]


def _again(cmd: list[str]) -> int:
    """Re-run a command in this process (the killed run's lock died with it)."""
    return main(cmd[3:])


def _watch(output: Path) -> list[str]:
    """strace path filters: the calls on these paths are the steps of publishing ``output``."""
    partial = output.with_name(f".{output.name}.partial")
    paths = [output, partial, partial / ".work", partial / ".done", partial / ".job.json",
             output.with_name(f".{output.name}.old"), output.with_name(f".{output.name}.sealed"),
             output.with_name(f".{output.name}.sealed.tmp")]
    return [arg for p in paths for arg in ("-P", str(p))]


def _publish_points(cmd: list[str], output: Path, log: Path) -> list[tuple[str, int]]:
    """``(syscall, n)``: the n-th call of that syscall on the publish paths is a step of the publish."""
    # traced by seccomp-bpf: only the watched calls stop the process (a kill's injection needs ptrace's own stops)
    subprocess.run([STRACE, "-f", "-qq", "--seccomp-bpf", *_watch(output), "-e", f"trace={CALLS}", "-o", str(log),
                    *cmd], check=True, capture_output=True)
    seen: dict[str, int] = {}
    points, previous = [], None
    for line in log.read_text().splitlines():
        m = re.match(r"\d+\s+(\w+)\(", line)
        if not m or "resumed>" in line:
            continue
        name = m.group(1)
        seen[name] = seen.get(name, 0) + 1
        # Every rename, rmdir and unlink is a step; a run of unlinkat calls is one step (emptying a
        # folder): killing at its 3rd file leaves what killing at its 1st does, a folder half emptied.
        if name != "unlinkat" or previous != "unlinkat":
            points.append((name, seen[name]))
        previous = name
    assert len(points) >= 4, f"too few publish steps found: {points}"
    # A sample keeps the suite's time in check: the first and last steps and evenly spaced ones
    # between (the seal, the moves and the removals each fall in it at these counts).
    keep = sorted({round(i * (len(points) - 1) / (KILL_POINTS - 1)) for i in range(KILL_POINTS)})
    return [points[i] for i in keep] if len(points) > KILL_POINTS else points


def _killed(cmd: list[str], output: Path, name: str, n: int, log: Path) -> bool:
    """Run ``cmd`` and kill -9 it at the entry of the n-th ``name`` call on the publish paths, before
    the call is made; whether it got there. strace holds that call at its entry (an injected delay),
    having written its line, and this kills strace and the command together there: a signal injected
    by strace itself is delivered only when ptrace stops the command at every system call, which
    makes a run three times slower, while seccomp-bpf stops it at the watched calls alone."""
    log.unlink(missing_ok=True)  # a line of the last run is no entry of this one
    traced = subprocess.Popen([STRACE, "-f", "-qq", "--seccomp-bpf", *_watch(output), "-e", f"trace={name}",
                               "-e", f"inject={name}:delay_enter={HOLD_SECONDS * 1_000_000}:when={n}",
                               "-o", str(log), *cmd], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True)
    entry = re.compile(rf"^\d+\s+{name}\(", re.M)
    held = False
    while not held and traced.poll() is None:
        held = log.exists() and len(entry.findall(log.read_text())) >= n
        if held:
            os.killpg(traced.pid, signal.SIGKILL)
        else:
            time.sleep(0.01)
    traced.wait()
    while _alive(traced.pid):  # the command's locks go with its last thread
        time.sleep(0.01)
    return held


def _alive(group: int) -> bool:
    """Whether a thread of this process group still runs: a process holds its files until its last
    thread has exited (its first may be a zombie before that)."""
    for stat in Path("/proc").glob("[0-9]*/task/[0-9]*/stat"):
        try:
            state, _, pgrp = stat.read_text().rsplit(")", 1)[1].split()[:3]
        except OSError:  # gone while read
            continue
        if int(pgrp) == group and state != "Z":
            return True
    return False


def _tree(path: Path) -> dict[str, bytes]:
    """Every file's bytes, but for the run's timings and provenance (and their manifest entries)."""
    import json

    skip = ("build.json", "eval.json", "index.json")  # run timings: they differ from run to run
    tree = {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*"))
            if p.is_file() and p.name not in skip}
    if "manifest.json" in tree:
        files = json.loads(tree["manifest.json"])["files"]
        tree["manifest.json"] = json.dumps({k: v for k, v in files.items() if Path(k).name not in skip},
                                           sort_keys=True).encode()
    return tree


def _kill_at_each_step(cmd: list[str], output: Path, reset, tmp_path: Path) -> None:
    reset()
    subprocess.run(cmd, check=True, capture_output=True)
    want = _tree(output)
    reset()
    points = _publish_points(cmd, output, tmp_path / "trace.log")
    reset()
    for name, n in points:
        reset()
        assert _killed(cmd, output, name, n, tmp_path / "kill.log"), f"not killed at {name} #{n}"
        assert _again(cmd) == 0, f"after a kill at {name} #{n}"
        assert _tree(output) == want, f"after a kill at {name} #{n}"
        leftovers = [p.name for p in output.parent.iterdir() if p.name.startswith(f".{output.name}.")
                     and not p.name.endswith(".lock")]
        assert not leftovers, f"after a kill at {name} #{n}: {leftovers}"


@pytest.fixture(scope="module")
def small(sources, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("faults")
    recipe = write_recipe(root / "tiny.toml", deep1b_rows_read=40_000, deep1b_rows_kept=32_768,
                          fas_ref_rows=2000, fas_query_rows=1000, query_stride=50)
    return {"recipe": recipe, "root": root}


@pytest.mark.slow
def test_forced_rebuild_survives_a_kill_at_every_publish_step(small, sources, tmp_path):
    """--force replaces a complete store (every step of a first publish, and moving the old store aside)."""
    out = tmp_path / "out"
    base = _cli("build", "--scale", str(small["recipe"]), "--deep1b", str(sources["fbin"]), "--fas",
                str(sources["fas"]), "--out", str(out), "--workers", "1")
    subprocess.run(base, check=True, capture_output=True)
    saved = tmp_path / "saved"
    shutil.copytree(out, saved)

    def reset() -> None:
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(saved, out)

    _kill_at_each_step([*base, "--force"], out / "tiny.zarr", reset, tmp_path)


@pytest.mark.slow
def test_index_and_eval_survive_a_kill_at_every_publish_step(small, sources, tmp_path):
    out = tmp_path / "out"
    subprocess.run(_cli("build", "--scale", str(small["recipe"]), "--deep1b", str(sources["fbin"]), "--fas",
                        str(sources["fas"]), "--out", str(out)), check=True, capture_output=True)
    store, index = out / "tiny.zarr", tmp_path / "i" / "tiny.index"
    index.parent.mkdir()
    _kill_at_each_step(_cli("index", str(store), "--d", "12", "--out", str(index)), index,
                       lambda: shutil.rmtree(index, ignore_errors=True), tmp_path)
    ev = tmp_path / "e" / "eval"
    ev.parent.mkdir()
    cmd = _cli("eval", str(store), str(index), "--L", "1,5", "--noise", "qm1", "--repeats", "1", "--no-baseline",
               "--out", str(ev))  # what is checked is the publishing: one timing repeat, no baseline
    # An evaluation's timings differ from run to run; its matches must not.
    subprocess.run(cmd, check=True, capture_output=True)
    import pyarrow.parquet as pq

    want = pq.read_table(ev / "queries.parquet").drop_columns(["store"]).to_pandas()
    shutil.rmtree(ev)
    points = _publish_points(cmd, ev, tmp_path / "trace.log")
    for name, n in points:
        shutil.rmtree(ev, ignore_errors=True)
        assert _killed(cmd, ev, name, n, tmp_path / "kill.log"), f"not killed at {name} #{n}"
        # Killed mid-publish: the three files are either all at the public path or none is.
        present = [f for f in ("results.parquet", "queries.parquet", "eval.json") if (ev / f).exists()]
        assert len(present) in (0, 3), present
        assert _again(cmd) == 0
        got = pq.read_table(ev / "queries.parquet").drop_columns(["store"]).to_pandas()
        assert got.equals(want)
