"""A pipeline under a wall-clock budget, part of a pipeline, overrides and the stage graph."""

from __future__ import annotations

import hashlib
import json
import threading
import time
import types
from pathlib import Path

import numpy as np
import pytest

import vprscale.core.deadline as deadline_mod
import vprscale.core.passes as passes
import vprscale.jobs.pipeline as pl
from vprscale.cli import main
from vprscale.core.deadline import EXIT_MORE, BudgetSpent
from vprscale.core.errors import InputError
from vprscale.jobs.budget import Pending, check, may_start, parse_duration, plan_calls
from vprscale.jobs.pipeline import load_pipeline, override, run_pipeline, select, stage_graph

STAGES = """name = "t"
out = "{out}"

[[stages]]
name = "build"
kind = "build"
scale = "20K"

[[stages]]
name = "index"
kind = "index"
store = "build"

[[stages]]
name = "eval"
kind = "eval"
store = "build"
index = "index"
noise = ["qm1"]
L = [1, 50]
baseline = false

[[stages]]
name = "build-b"
kind = "build"
scale = "20K"
rescale = false

[[stages]]
name = "report"
kind = "report"
results = ["eval"]
out = "{out}/report"
"""


def _pipeline(tmp_path: Path) -> Path:
    path = tmp_path / "p.toml"
    path.write_text(STAGES.format(out=tmp_path / "data"))
    return path


class _Clock:
    """A clock the test moves: each chunk of a pass takes 10 s of it."""

    def __init__(self) -> None:
        self.now = 1000.0
        self.lock = threading.Lock()

    def tick(self, seconds: float) -> None:
        with self.lock:
            self.now += seconds

    def time(self) -> float:
        return self.now


def _pass(work: Path, calls: list[int], clock: _Clock | None = None) -> np.ndarray:
    def task(a: int, b: int) -> np.ndarray:
        calls.append(a)
        if clock is not None:
            clock.tick(10.0)
        return np.arange(a, b, dtype=np.float64) ** 1.5

    bounds = [(i * 10, i * 10 + 10) for i in range(12)]
    return passes.reduce_pass(work, "test pass", bounds, task, lambda s, r: s + [float(r.sum())], [], group=2,
                              quiet=True)


@pytest.mark.parametrize(("budget", "chunks_done"), [(25.0, 2), (45.0, 4), (-1.0, 0)])
def test_a_pass_stops_at_the_last_checkpoint_that_fits_and_resumes_to_the_same_state(
        tmp_path, monkeypatch, budget, chunks_done):
    """Under a deadline a pass starts a group only if the last group's time still fits before it;
    the next run (no deadline) continues from the checkpoint, computing no chunk twice, and
    reduces to what an uninterrupted pass does."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    clock = _Clock()
    fake = types.SimpleNamespace(time=clock.time, perf_counter=clock.time)
    monkeypatch.setattr(passes, "time", fake)
    monkeypatch.setattr(deadline_mod, "time", fake)
    monkeypatch.setenv(deadline_mod.ENV, repr(clock.now + budget))
    calls: list[int] = []
    with pytest.raises(BudgetSpent, match=f"test pass: {chunks_done} of 12 chunks done"):
        _pass(tmp_path / "a", calls, clock)
    assert sorted(calls) == [i * 10 for i in range(chunks_done)]
    monkeypatch.delenv(deadline_mod.ENV)
    resumed = _pass(tmp_path / "a", calls)
    assert sorted(calls) == [i * 10 for i in range(12)]  # every chunk once
    whole = _pass(tmp_path / "b", [])
    assert resumed == whole


def test_a_budget_is_a_duration():
    assert parse_duration("2h") == 7200 and parse_duration("1h30m") == 5400 and parse_duration("90") == 90
    assert parse_duration("1.5d") == 129600 and parse_duration("45s") == 45
    for bad in ("", "2 hours", "h", "0", "-1h", "1x"):
        with pytest.raises(InputError, match="--budget"):
            parse_duration(bad)
    assert main(["run", "quickstart", "--budget", "soon"]) == 2


def test_a_stage_that_cannot_stop_midway_starts_only_where_its_estimate_fits():
    build, index = Pending("b", "build", 3000.0), Pending("i", "index", 1000.0)
    assert may_start(build, 10.0, False) is None  # it stops at a checkpoint when it must
    assert "more than the 10 s left" in may_start(index, 10.0, False)
    assert may_start(index, 1000.0, False) is None
    assert may_start(index, 10.0, True) is None  # first in a call: the only way it ever runs
    assert may_start(Pending("e", "eval", None), 1.0, False) is None  # nothing to judge it by: it starts
    assert may_start(build, 0.0, True) is None  # first in a call, nothing left: it still starts (and progresses)
    check([build, index], 1000)  # a build longer than the budget stops at checkpoints
    with pytest.raises(InputError, match="stage 'i' cannot stop midway and is estimated at 17 min, longer than the "
                                         "whole budget"):
        check([build, index], 600)
    # the plan: the build spans two calls, the index waits for the third, the evaluation fits beside it
    plan = plan_calls([Pending("b", "build", 5000.0), Pending("i", "index", 3000.0), Pending("e", "eval", 500.0)],
                      3600)
    assert [c for c, _ in plan] == [2, 3, 3]
    assert plan[0][1] == "calls 1-2: stops at a checkpoint and continues"
    assert plan[1][1] == "call 3; cannot stop midway"
    plan = plan_calls([Pending("i", "index", None), Pending("e", "eval", 3000.0), Pending("r", "report", None)], 3600)
    unmeasured = (1, "call 1 at the earliest; never measured, may run past the budget")
    assert plan == [unmeasured, (1, "call 1; cannot stop midway"), unmeasured]


def test_part_of_a_pipeline_takes_what_it_reads_and_downstream_what_reads_it(tmp_path):
    pipe = load_pipeline(_pipeline(tmp_path))

    def names(stages, downstream=False):
        covered, asked = select(pipe, stages, downstream)
        return [s.name for s in covered], asked

    assert names(["index"]) == (["build", "index"], {"index"})
    assert names(["index"], True) == (["build", "index", "eval", "report"], {"index", "eval", "report"})
    assert names(["build-b"], True) == (["build-b"], {"build-b"})
    assert names([]) == (["build", "index", "eval", "build-b", "report"],
                         {"build", "index", "eval", "build-b", "report"})
    with pytest.raises(InputError, match="no stage 'indx'"):
        select(pipe, ["indx"], False)


def test_an_override_is_checked_as_the_file_is_and_changes_the_fingerprint(tmp_path, capsys):
    path = _pipeline(tmp_path)
    pipe = load_pipeline(path)
    override(pipe, ["eval.L=[1, 100]", "build-b.rescale=true", "eval.noise=[\"qm2\"]"])
    params = {s.name: s.params for s in pipe.stages}
    assert params["eval"]["L"] == [1, 100] and params["build-b"]["rescale"] is True
    assert params["eval"]["noise"] == ["qm2"]
    for bad, message in [("eval.L=fifty", "key 'L' must be a list of integers, got 'fifty'"),
                         ("eval.colour=red", "unknown key 'colour' for a eval stage"),
                         ("eval.index=build-b", "key 'index' must name an earlier index stage, got 'build-b'"),
                         ("nothing.L=[1]", "has no stage 'nothing'"), ("eval.L", "give STAGE.KEY=VALUE")]:
        with pytest.raises(InputError, match=message):
            override(load_pipeline(path), [bad])
        assert main(["run", str(path), "--set", bad, "--dry-run"]) == 2
        assert message in capsys.readouterr().err
    plain = {s["name"]: s["fingerprint"] for s in run_pipeline(path, dry_run=True)["stages"]}
    changed = {s["name"]: s["fingerprint"] for s in run_pipeline(path, dry_run=True, settings=["eval.L=[1]"])["stages"]}
    assert {n for n in plain if plain[n] != changed[n]} == {"eval", "report"}  # the stage and what reads it


def test_the_stage_graph_shows_each_stage_and_what_it_reads_with_its_state(tmp_path, monkeypatch):
    path = _pipeline(tmp_path)
    mermaid = stage_graph(path, "mermaid")
    assert mermaid.startswith("flowchart TD\n")
    assert 's0["build (build)<br/>pending: no complete run recorded"]:::pending' in mermaid
    for edge in ("s0 --> s1", "s0 --> s2", "s1 --> s2", "s2 --> s4"):
        assert f"  {edge}\n" in mermaid
    assert "s3 -->" not in mermaid and mermaid.count("-->") == 4
    dot = stage_graph(path, "dot", stages=["index"])
    assert dot.startswith("digraph pipeline {") and "s0 -> s1;" in dot and "eval" not in dot
    # a reason names paths, which may hold anything: a label stays text in both forms
    real = pl._reasons
    monkeypatch.setattr(pl, "_reasons", lambda stage, *a: ['output /x/"]:::done<img src=x> `changed`'] if
                        stage.name == "index" else real(stage, *a))
    hostile = stage_graph(path, "mermaid")
    line = next(x for x in hostile.splitlines() if "index (index)" in x)
    assert line == ('  s1["index (index)<br/>stale: output /x/#quot;]:::done#lt;img src=x#gt; #96;changed#96;"]'
                    ":::stale")
    line = next(x for x in stage_graph(path, "dot").splitlines() if "index (index)" in x)
    assert '\\"]:::done<img src=x> `changed`", fillcolor="#fce5cd"];' in line


def _tree(store: Path) -> dict[str, str]:
    """Every file of a store but its run record (times), by content digest."""
    return {str(f.relative_to(store)): hashlib.sha256(f.read_bytes()).hexdigest() for f in sorted(store.rglob("*"))
            if f.is_file() and f.name not in ("build.json", "manifest.json") and "zarr.json" not in f.name}


@pytest.mark.slow
def test_a_budget_stops_a_build_at_a_checkpoint_and_the_next_call_continues_it(tmp_path, monkeypatch, capsys,
                                                                               fas_fitted):
    """``--budget``: a build stopped at a checkpoint, exit status 75 with what is left; the next
    call resumes it (nothing finished redone) and runs the rest, and the store is the bytes of an
    uninterrupted build."""
    path = _pipeline(tmp_path)
    real = time.time
    # the pipeline's clock 100 s behind: the budget's end, 50 s after its start, has already passed
    # when the build's first pass looks, so the build stops at its first checkpoint whatever the machine
    monkeypatch.setattr(pl, "time", types.SimpleNamespace(time=lambda: real() - 100, perf_counter=time.perf_counter))
    assert main(["run", str(path), "build", "index", "--budget", "50s"]) == EXIT_MORE
    out = capsys.readouterr().out
    assert "pipeline t: more to do; ran 0 of 2 stages" in out
    assert "more to do: 2 stage(s) left (build, index), no estimate (never measured); run the same command" in out
    summary = json.loads(next((tmp_path / "data" / "runs").glob("*.json")).read_text())
    assert summary["status"] == "more to do" and [s["status"] for s in summary["stages"]] == ["stopped"]
    state = json.loads((tmp_path / "data" / "pipeline-state.json").read_text())
    assert set(state) == {".stopped"} and state[".stopped"]["build"]["seconds"] > 0
    assert (tmp_path / "data" / ".20K.zarr.partial").is_dir() and not (tmp_path / "data" / "20K.zarr").exists()
    plan = run_pipeline(path, dry_run=True, stages=["build", "index"])["stages"]
    assert plan[0]["reasons"][0].startswith("stopped at a checkpoint by a budget after")
    monkeypatch.undo()
    assert main(["run", str(path), "build", "index"]) == 0
    log = sorted((tmp_path / "data" / "runs").glob("*.log"))[-1].read_text()
    assert "resuming the unfinished build" in log
    second = json.loads(sorted((tmp_path / "data" / "runs").glob("*.json"))[-1].read_text())
    assert [s["status"] for s in second["stages"]] == ["ran", "ran"]
    assert second["stages"][0]["seconds"] > state[".stopped"]["build"]["seconds"]  # both calls' time
    assert not json.loads((tmp_path / "data" / "pipeline-state.json").read_text()).get(".stopped")
    assert main(["build", "--scale", "20K", "--out", str(tmp_path / "whole"), "--workers", "2"]) == 0
    assert _tree(tmp_path / "data" / "20K.zarr") == _tree(tmp_path / "whole" / "20K.zarr")
    assert main(["run", str(path), "build", "index", "--budget", "1h"]) == 0  # nothing left: done, exit 0


@pytest.mark.slow
def test_a_terminated_run_is_recorded_stops_its_stage_and_the_next_run_goes_on(tmp_path, fas_fitted):
    """SIGTERM (a batch scheduler's time limit, ``kill``): the run stops its stage, records itself as
    interrupted and exits 143; no stage process is left behind; the next run finishes the work."""
    import signal
    import subprocess

    from vprscale.jobs.child import vprscale_argv

    path = _pipeline(tmp_path)
    proc = subprocess.Popen(vprscale_argv("run", str(path), "build"), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if line.startswith("$ vprscale build"):  # the stage's process is starting
            break
    time.sleep(1.0)
    proc.send_signal(signal.SIGTERM)
    seen.append(proc.stdout.read())
    assert proc.wait(timeout=60) == 143, "".join(seen)
    summary = json.loads(next((tmp_path / "data" / "runs").glob("*.json")).read_text())
    assert summary["status"] == "interrupted"
    out = str(tmp_path / "data")
    left = [p for p in Path("/proc").glob("[0-9]*") if out.encode() in _cmdline(p)]
    assert not left, "a stage's process outlived its run"
    assert main(["run", str(path), "build"]) == 0
    assert (tmp_path / "data" / "20K.zarr" / "manifest.json").is_file()


def _cmdline(proc: Path) -> bytes:
    try:
        return (proc / "cmdline").read_bytes()
    except OSError:
        return b""


def test_a_budget_no_call_could_keep_is_refused_before_any_stage_runs(tmp_path, capsys):
    """An index measured at 20 minutes cannot stop midway: a 5-minute budget is refused in one line,
    exit 2, before the build before it starts (and so is the dry run's plan)."""
    path = _pipeline(tmp_path)
    runs = tmp_path / "data" / "runs"
    runs.mkdir(parents=True)
    (runs / "20261201T100000Z.json").write_text(json.dumps({"name": "t", "started": "20261201T100000Z", "stages": [
        {"name": "index", "kind": "index", "params": {"store": "build"}, "status": "ran", "seconds": 1200.0,
         "outputs": {"peak_rss_bytes": 1, "bytes_on_disk": 1}}]}))
    message = ("--budget 5 min: stage 'index' cannot stop midway and is estimated at 20 min, longer than the whole "
               "budget")
    for argv in (["--dry-run"], []):
        assert main(["run", str(path), "--budget", "5m", *argv]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "data" / ".20K.zarr.partial").exists() and not (tmp_path / "data" / "20K.zarr").exists()


def test_every_call_progresses_however_short_its_budget(tmp_path, monkeypatch):
    """``run --budget 1s``: a process whose deadline passed before its first checkpoint (its start
    alone took longer) still finishes one unit of work, then stops at the next; so a job requeued
    on the same short budget advances on every call and ends, where it would stop at the same
    checkpoint for ever. A pipeline call likewise starts its first stage, however little is left."""
    monkeypatch.setenv(deadline_mod.ENV, repr(time.time() - 60))  # spent before the job began
    bounds = [(i, i + 1) for i in range(8)]
    calls = 0
    while True:
        monkeypatch.setattr(deadline_mod, "_progressed", False)  # a new process
        try:
            total = passes.reduce_pass(tmp_path, "sum", bounds, lambda a, b: a, lambda s, r: s + r, 0, group=2,
                                       quiet=True)
            break
        except BudgetSpent:
            calls += 1
            assert calls < 8, "a call made no progress"
    assert total == sum(range(8)) and calls == 3  # two chunks a call: four calls in all
    assert may_start(Pending("index", "index", 1200.0), left=-5.0, first=True) is None
    assert may_start(Pending("index", "index", 1200.0), left=-5.0, first=False) == "the budget is spent"


def test_a_checkpoint_another_user_could_have_written_is_not_loaded(tmp_path, caplog):
    """A pass's checkpoint is a pickle: one writable by others (or planted by them) would run their
    code when loaded. It is written for this user alone, and one that is not is ignored: the pass
    starts over, with the same result."""
    import os
    import pickle

    bounds = [(i, i + 1) for i in range(6)]
    assert passes.reduce_pass(tmp_path, "sum", bounds, lambda a, b: a, lambda s, r: s + r, 0, quiet=True) == 15
    ckpt = tmp_path / "sum.pass"
    assert ckpt.stat().st_mode & 0o777 == 0o600
    planted = tmp_path / "planted"

    class Plant:
        def __reduce__(self):
            return (open, (str(planted), "w"))

    ckpt.write_bytes(pickle.dumps((3, Plant())))
    os.chmod(ckpt, 0o666)  # as a file anybody could have written
    assert passes.reduce_pass(tmp_path, "sum", bounds, lambda a, b: a, lambda s, r: s + r, 0, quiet=True) == 15
    assert not planted.exists() and "not loaded" in caplog.text


def test_a_dry_run_says_when_a_stage_needs_more_memory_than_the_machine_has(tmp_path, capsys):
    """An index measured at a peak beyond this machine's memory: the dry run says so beside it,
    what will happen and what it needs, rather than printing 65 GB on a 24 GB machine without a word."""
    path = _pipeline(tmp_path)
    runs = tmp_path / "data" / "runs"
    runs.mkdir(parents=True)
    (runs / "20261201T100000Z.json").write_text(json.dumps({"name": "t", "started": "20261201T100000Z", "stages": [
        {"name": "index", "kind": "index", "params": {"store": "build"}, "status": "ran", "seconds": 60.0,
         "outputs": {"peak_rss_bytes": 10**15, "bytes_on_disk": 1}}]}))
    assert main(["run", str(path), "--dry-run"]) == 0
    out = capsys.readouterr().out.splitlines()
    at = next(i for i, line in enumerate(out) if line.startswith("run   index (index)"))
    assert "is more than this machine's" in out[at + 1] and "at least 1000000 GB" in out[at + 1]
    assert not any("is more than this machine's" in line for line in out[:at])  # the build fits
