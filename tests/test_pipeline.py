"""Pipelines: validation before work, the quickstart end to end, skipping, re-running, locking."""

from __future__ import annotations

import json
import os
import re
import shutil
import tomllib
from pathlib import Path

import pandas as pd
import pytest

from vprscale.cli import main
from vprscale.core.errors import InputError
from vprscale.core.publish import exclusive
from vprscale.jobs.pipeline import load_pipeline, run_pipeline, stage_command

from .conftest import seed_fas_fit

ROOT = Path(__file__).resolve().parents[1]
# a test whose stages build 20K stores finds the FAS fit cached (conftest.fas_fitted): these tests are
# about the pipeline; the others build nothing, and do not wait for the fit
builds_20k = pytest.mark.usefixtures("fas_fitted")


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


BASE = 'name = "t"\nout = "{out}"\n'
TWO = '[[stages]]\nname = "a"\nkind = "build"\nscale = "20K"\n[[stages]]\nname = "i"\nkind = "index"\nstore = "a"\n'


@pytest.mark.parametrize(("stages", "message"), [
    ('[[stages]]\nname = "a"\nkind = "bake"\n', "stage 'a': unknown stage kind 'bake'"),
    ('[[stages]]\nname = "a"\nkind = "build"\n', "stage 'a': give one of 'scale' (a recipe), 'ref'"),
    ('[[stages]]\nname = "a"\nkind = "build"\nscale = 20\n', "stage 'a': key 'scale' must be a string"),
    ('[[stages]]\nname = "a"\nkind = "build"\nscale = "20K"\nrescale = "no"\n', "key 'rescale' must be true or false"),
    ('[[stages]]\nname = "a"\nkind = "index"\nstore = "nothing"\n',
     "stage 'a': key 'store' must name an earlier build stage, got 'nothing'"),
    ('[[stages]]\nname = "a"\nkind = "build"\nscale = "20K"\n[[stages]]\nname = "e"\nkind = "eval"\n'
     'store = "a"\nL = [1, "fifty"]\n', "stage 'e': key 'L' must be a list of integers"),
    ('[[stages]]\nname = "a"\nkind = "build"\nscale = "20K"\ncolour = "red"\n', "unknown key 'colour'"),
    ('[[stages]]\nname = 5\nkind = "build"\nscale = "20K"\n', "'name' and 'kind' must be non-empty strings, got 5"),
    # a stage's name names its files under out: never a path out of it
    ('[[stages]]\nname = "/../../x"\nkind = "build"\nscale = "20K"\n', "stage name '/../../x' must be letters"),
    ('[[stages]]\nname = ".."\nkind = "build"\nscale = "20K"\n', "stage name '..' must be letters"),
    ('[[stages]]\nname = "a/b"\nkind = "build"\nscale = "20K"\n', "stage name 'a/b' must be letters"),
    (f'[[stages]]\nname = "{"x" * 101}"\nkind = "build"\nscale = "20K"\n', "at most 100 characters"),
    ("x = " + "[" * 5000 + "]" * 5000 + "\n", "nested too deeply to be a pipeline"),
    # a FAISS code no stage could build, refused before the stages before it run for hours
    ('[[stages]]\nname = "a"\nkind = "build"\nscale = "20K"\n[[stages]]\nname = "e"\nkind = "eval"\nstore = "a"\n'
     'compare = ["PQ3", "PQ5x4fs"]\n', "stage 'e': key 'compare': --compare PQ5x4fs: not a FAISS index_factory string "
     "with standalone codes for 96-d rows"),
    ('[[stages]]\nname = "a"\nkind = "build"\nscale = "20K"\n[[stages]]\nname = "e"\nkind = "encode"\nstore = "a"\n'
     'compare = ["seq:PQ3"]\n', "stage 'e': key 'compare': --compare seq:PQ3: a pooled sequence descriptor is encoded "
     "by its evaluation"),
    ('[[stages]]\nname = "a"\nkind = "build"\nscale = "20K"\n[[stages]]\nname = "e"\nkind = "eval"\nstore = "a"\n'
     'compare = ["HNSW0"]\n', "stage 'e': key 'compare': --compare HNSW0: an HNSW graph of M = 0"),
    ('[[stages]]\nname = "a"\nkind = "build"\nscale = "20K"\n[[stages]]\nname = "e"\nkind = "eval"\nstore = "a"\n'
     'compare = ["seq:PQ3+rerank99999999999999"]\n', "+rerank99999999999999: re-ranks at least one"),
    # parts: each runs from nothing, so it holds what its stages read; the report is assembled, not a part's
    (TWO + '[[parts]]\nname = "p"\nstages = ["i"]\n', "parts[0] (p): 'i' reads 'a', which the part does not run"),
    (TWO + '[[parts]]\nname = "p"\nstages = ["a", "zz"]\n', "parts[0] (p): no stage 'zz'"),
    (TWO + '[[parts]]\nname = "p"\nstages = ["a"]\n', "stage 'i' is in no part"),
    (TWO + '[[parts]]\nname = "p"\nstages = ["a", "i"]\n[[parts]]\nname = "p"\nstages = ["a"]\n',
     "parts[1]: 'name' must be a new name"),
    (TWO + '[[parts]]\nname = "p"\nstages = []\n', "parts[0]: 'stages' must be a non-empty list"),
    (TWO + '[[parts]]\nname = "p"\nstages = ["a", "i"]\nwhen = "now"\n', "a part is a table of 'name' and 'stages'"),
])
def test_bad_pipeline_is_refused_before_any_work(tmp_path, capsys, stages, message):
    out = tmp_path / "out"
    path = _write(tmp_path / "p.toml", BASE.format(out=out) + stages)
    with pytest.raises(InputError, match=re.escape(message)):
        load_pipeline(path)
    assert main(["run", str(path)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_an_eval_stage_passes_its_flat_noise_levels(tmp_path):
    stages = ('[[stages]]\nname = "b"\nkind = "build"\nscale = "20K"\n[[stages]]\nname = "i"\nkind = "index"\n'
              'store = "b"\n[[stages]]\nname = "e"\nkind = "eval"\nstore = "b"\nindex = "i"\ncompare = ["PQ4"]\n'
              'flat_noise = ["qm1"]\nradius_m = [10, 25.5]\n')
    pipe = load_pipeline(_write(tmp_path / "p.toml", BASE.format(out=tmp_path / "out") + stages))
    outputs = {"b": {"store": "s.zarr"}, "i": {"index": "s.index"}}
    cmd = stage_command(pipe, pipe.stages[2], outputs, None)
    assert cmd[cmd.index("--flat-noise") + 1] == "qm1" and cmd[cmd.index("--compare") + 1] == "PQ4"
    assert cmd[cmd.index("--radius-m") + 1] == "10,25.5"
    bad = stages.replace("radius_m = [10, 25.5]", 'radius_m = ["far"]')
    with pytest.raises(InputError, match="radius_m.*a list of numbers"):
        load_pipeline(_write(tmp_path / "q.toml", BASE.format(out=tmp_path / "out") + bad))


def test_shipped_pipelines_are_valid():
    for name in ("quickstart", "paper"):
        pipe = load_pipeline(ROOT / "pipelines" / f"{name}.toml")
        assert [s.kind for s in pipe.stages][-1] == "report"


def _quickstart(tmp_path: Path) -> Path:
    """The shipped quickstart pipeline, writing under ``tmp_path`` instead of the repository."""
    text = (ROOT / "pipelines" / "quickstart.toml").read_text()
    data = tomllib.loads(text)
    text = text.replace(f'out = "{data["out"]}"', f'out = "{tmp_path / "data"}"')
    text = text.replace('out = "data/quickstart/report"', f'out = "{tmp_path / "report"}"')
    # one operating point per FAISS code keeps the suite's time (test_compare covers the lists)
    text = "\n".join(line for line in text.splitlines() if not line.startswith(("faiss_k", "faiss_nprobe")))
    return _write(tmp_path / "quickstart.toml", text)


@pytest.fixture(scope="module")
def quickstart_run(tmp_path_factory, fas_fit_20k):
    tmp = tmp_path_factory.mktemp("quickstart")
    path = _quickstart(tmp)
    seed_fas_fit(tmp / "cache", fas_fit_20k)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("VPRSCALE_CACHE", str(tmp / "cache"))
        return tmp, path, run_pipeline(path)


@pytest.mark.slow
@builds_20k
def test_quickstart_runs_end_to_end(quickstart_run):
    tmp, _, summary = quickstart_run
    assert summary["status"] == "ok"
    assert all(s["status"] == "ran" for s in summary["stages"])
    report = tmp / "report" / "report.md"
    assert report.is_file()
    for fig in ("fig3_recall", "fig4b_single_frame", "fig4c_storage", "fig4d_balance", "fig_compare_qm1",
                "fig_compare_qm2"):
        assert (tmp / "report" / f"{fig}.png").is_file() and (tmp / "report" / f"{fig}.pdf").is_file()
    # The synthetic sources are calibrated to the paper's regime at 20K (SPEC §1.3).
    import pandas as pd

    evaluation = next(st["outputs"]["eval"] for st in summary["stages"] if st["name"] == "eval-20K")
    res = pd.read_parquet(Path(evaluation) / "results.parquet")
    at20 = res[(res.radius == 20) & (res.part == "all") & (res.noise == "qm1") & (res.method == "coarsehash")]
    assert at20[at20.L == 1]["recall"].iloc[0] < 0.5
    assert at20[(at20.L == 50) & (at20["mode"] == "paper")]["recall"].iloc[0] > 0.7
    saved = json.loads(Path(summary["summary_file"]).read_text())
    assert saved["status"] == "ok"
    per_noise = [f"{fig}_{noise}" for noise in ("qm1", "qm2")
                 for fig in ("fig_compare", "fig_compare_bytes", "fig_compare_trends", "fig_pr")]
    whole = ["fig3_recall", "fig4b_single_frame", "fig4c_storage", "fig4d_balance", "fig_nn"]
    assert sorted({Path(f).stem for f in saved["figures"]}) == sorted([*whole, *per_noise])
    assert len(saved["figures"]) == 2 * (len(whole) + len(per_noise))  # PNG and PDF each
    assert Path(summary["summary_file"]).with_suffix(".log").stat().st_size > 0


def _dry_run(path: Path, pythonpath: Path | None = None, *flags: str) -> dict[str, dict]:
    """``vprscale run --dry-run`` as a user runs it, stage by stage: (run, reasons, estimate)."""
    return _plan(path, pythonpath, *flags)[0]


def _plan(path: Path, pythonpath: Path | None = None, *flags: str) -> tuple[dict[str, dict], str]:
    """``vprscale run --dry-run``'s stages (:func:`_dry_run`) and its last line, the run's estimate."""
    import subprocess
    import sys

    env = {**os.environ, **({"PYTHONPATH": str(pythonpath)} if pythonpath else {})}
    done = subprocess.run([sys.executable, "-m", "vprscale.cli", "run", str(path), "--dry-run", *flags],
                          capture_output=True, text=True, env=env, cwd=path.parent)
    assert done.returncode == 0, done.stderr
    *stages, total = done.stdout.splitlines()
    found = {}
    for line in stages:
        verdict, name, why, cost = re.fullmatch(r"(run|skip)\s+(\S+) \(\w+\): (.*?)(?: \[(.*)\])?", line).groups()
        found[name] = {"run": verdict == "run", "why": why, "cost": cost}
    return found, total


@pytest.mark.slow
@builds_20k
@pytest.mark.parametrize(("module", "reruns"), [
    ("evaluation/report.py", {"report"}),  # the report's code: the report alone
    ("cli/report.py", {"report"}),  # the report command: the report alone
    ("cli/sql.py", set()),  # a command no stage runs: nothing
])
def test_a_changed_module_reruns_only_the_stages_that_run_it(quickstart_run, tmp_path, module, reruns):
    """The code a stage depends on is the modules its job imports and its own command: a change
    to the report code or the report command re-runs the report stage, not the builds, indexes
    or evaluations; a change to another command re-runs nothing."""
    _, path, _ = quickstart_run
    assert not any(s["run"] for s in _dry_run(path).values())
    import vprscale

    copy = tmp_path / "pkg"
    shutil.copytree(Path(vprscale.__file__).parent, copy / "vprscale", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(ROOT / "datasets", copy / "datasets")  # the recipes live beside the package
    with (copy / "vprscale" / module).open("a") as f:
        f.write("\n# a change\n")
    plan = _dry_run(path, pythonpath=copy)
    assert {name for name, s in plan.items() if s["run"]} == reruns
    name = "vprscale." + module.removesuffix(".py").replace("/", ".")
    assert all(f"code changed ({name})" in plan[stage]["why"] for stage in reruns)


@pytest.mark.slow
@builds_20k
def test_a_deleted_output_reruns_its_stage_and_what_reads_it(quickstart_run, tmp_path):
    tmp, path, summary = quickstart_run
    figure = next(Path(f) for f in summary["figures"] if f.endswith("fig3_recall.png"))
    results = Path(next(s["outputs"]["eval"] for s in summary["stages"] if s["name"] == "eval-20K"))
    kept = tmp_path / "kept"
    kept.mkdir()
    shutil.move(figure, kept / figure.name)
    plan = _dry_run(path)
    assert {name for name, s in plan.items() if s["run"]} == {"report"}
    assert f"output {figure} missing" in plan["report"]["why"]
    shutil.move(kept / figure.name, figure)
    shutil.move(results / "results.parquet", kept / "results.parquet")
    plan = _dry_run(path)
    assert {name for name, s in plan.items() if s["run"]} == {"eval-20K", "report"}
    assert f"output {results} changed" in plan["eval-20K"]["why"]
    assert "upstream stage eval-20K re-runs" in plan["report"]["why"]
    shutil.move(kept / "results.parquet", results / "results.parquet")
    assert not any(s["run"] for s in _dry_run(path).values())


@pytest.mark.slow
@builds_20k
def test_a_pipelines_report_states_each_stages_code_and_its_time(quickstart_run, monkeypatch, capsys):
    """The report of a pipeline lists every stage it reads, the code each ran and whether that is
    this vprscale's code; its time table is the pipeline's record (stages.json beside it)."""
    import vprscale.jobs.pipeline as pl
    from vprscale.evaluation.stagerecord import provenance_lines, read_record

    tmp, path, summary = quickstart_run
    record = read_record(tmp / "report" / "stages.json")
    ran = {s["name"]: s for s in summary["stages"]}
    assert [s["name"] for s in record["stages"]] == [n for n in ran if n != "report"]
    for s in record["stages"]:
        assert s["differs"] == [] and s["commit"] == summary["provenance"]["commit"]
        assert s["seconds"] == pytest.approx(ran[s["name"]]["seconds"])
        assert s["peak_rss_bytes"] == ran[s["name"]]["outputs"]["peak_rss_bytes"]
    md = (tmp / "report" / "report.md").read_text()
    assert "**every stage's code is this vprscale's**" in md and "different commits" not in md
    eval_row = next(line for line in md.splitlines() if line.startswith("| eval-20K | eval | 20,000 |"))
    assert f"| {ran['eval-20K']['seconds']:,.1f} |" in eval_row
    # a stage whose recorded code is not this vprscale's is named, with its modules
    pipe = load_pipeline(path)
    state = json.loads((tmp / "data" / "pipeline-state.json").read_text())
    real = pl.stage_code
    monkeypatch.setattr(pl, "stage_code", lambda kind, graph: {**real(kind, graph), "vprscale.evaluation.metrics": "x"}
                        if kind == "eval" else real(kind, graph))
    pl._write_stage_record(pipe, pipe.stages[-1], state, pl._import_graph())
    changed = read_record(pl.stage_record_path(pipe, pipe.stages[-1]))
    assert {s["name"]: s["differs"] for s in changed["stages"]}["eval-20K"] == ["vprscale.evaluation.metrics"]
    lines = provenance_lines(changed, lambda header, rows: "")
    assert "**1 stage(s) ran code that differs from this vprscale's**" in lines[0]
    assert lines[1].startswith("  - **eval-20K** ran other code than this vprscale's in 1 module(s) "
                               "(vprscale.evaluation.metrics)")
    bad = tmp / "bad-stages.json"
    for text, message in [("{", "not JSON"), ('{"pipeline": "p", "stages": [{"name": "a"}]}',
                                               "stages[0] ('a'): 'kind' is missing or of the wrong type")]:
        bad.write_text(text)
        assert main(["report", str(tmp / "data" / "20K-d15-k2.index" / "eval"), "--out", str(tmp / "r2"),
                     "--stages", str(bad)]) == 2
        assert f"--stages {bad}: " in (err := capsys.readouterr().err) and message in err
        assert not (tmp / "r2").exists()


@pytest.mark.slow
@builds_20k
def test_dry_run_estimates_each_stage_and_the_run_from_measured_figures(quickstart_run, capsys):
    """``--dry-run --force`` gives each stage its last run's time and the run's total; ``--save-costs``
    writes those figures beside the pipeline, and a dry run into an empty directory reads them."""
    tmp, path, summary = quickstart_run
    plan, total = _plan(path, None, "--force")
    for stage in summary["stages"]:
        cost = plan[stage["name"]]["cost"]
        assert plan[stage["name"]]["run"] and cost.endswith(f"measured in the run of {_stamp(summary['started'])}")
    seconds = sum(s["seconds"] for s in summary["stages"])
    found = re.fullmatch(r"estimated: ([\d.]+) (min|s) of wall time, peak memory ([\d.]+) GB, ([\d.]+) GB on disk",
                         total)
    assert found, total
    shown = float(found[1]) * (60 if found[2] == "min" else 1)
    assert abs(shown - seconds) <= 3.5  # printed to a tenth of a minute
    assert all(s["outputs"]["peak_rss_bytes"] > 50e6 for s in summary["stages"])  # every stage's process
    assert all(s["outputs"]["bytes_on_disk"] > 0 for s in summary["stages"])  # every stage's output, a report's too
    peak = max(s["outputs"]["peak_rss_bytes"] for s in summary["stages"])
    assert float(found[3]) == pytest.approx(peak / 1e9, abs=0.006)
    assert main(["run", str(path), "--save-costs"]) == 0  # every stage skipped: the figures of the run that ran them
    costs = path.with_name(path.stem + ".costs.json")
    assert str(costs) in capsys.readouterr().out
    text = path.read_text()
    try:
        path.write_text(text.replace(str(tmp / "data"), str(tmp / "elsewhere")))
        fresh, _ = _plan(path)
        assert all(s["run"] and s["cost"].endswith("measured on the reference machine") for s in fresh.values())
    finally:
        path.write_text(text)


def _stamp(started: str) -> str:
    return f"{started[:4]}-{started[4:6]}-{started[6:8]} {started[9:11]}:{started[11:13]} UTC"


@pytest.mark.slow
@builds_20k
def test_rerun_does_no_work_and_a_changed_stage_reruns_with_dependants(quickstart_run):
    tmp, path, _ = quickstart_run
    again = run_pipeline(path)
    assert [s["status"] for s in again["stages"]] == ["skipped"] * len(again["stages"])
    text = path.read_text()  # the evaluation's parameters changed (and made cheaper: one noise level, no L = 100)
    changed = text.replace("L = [1, 50, 100]", "L = [1, 50]").replace('noise = ["qm1", "qm2"]', 'noise = ["qm1"]')
    assert changed.count("L = [1, 50]") == 1 and 'noise = ["qm1"]' in changed
    path.write_text(changed)
    third = run_pipeline(path)
    status = {s["name"]: s["status"] for s in third["stages"]}
    assert status == {"build-20K": "skipped", "index-20K": "skipped", "eval-20K": "ran",
                      "build-20K-norescale": "skipped", "index-20K-norescale": "skipped", "report": "ran"}


def test_two_runs_on_one_output_are_refused(tmp_path, capsys):
    path = _quickstart(tmp_path)
    with exclusive(tmp_path / "data" / "pipeline"):
        assert main(["run", str(path)]) == 2
    assert "another vprscale job" in capsys.readouterr().err


def test_failed_stage_exits_non_zero_with_a_failed_summary(tmp_path, capsys):
    path = _write(tmp_path / "p.toml", BASE.format(out=tmp_path / "out") +
                  '[[stages]]\nname = "a"\nkind = "build"\nscale = "20K"\ndeep1b = "/nonexistent.fbin"\n')
    assert main(["run", str(path)]) == 2
    assert "/nonexistent.fbin" in capsys.readouterr().err
    summaries = list((tmp_path / "out" / "runs").glob("*.json"))
    assert len(summaries) == 1 and json.loads(summaries[0].read_text())["status"] == "failed"


def test_a_changed_recipe_source_or_code_reruns_the_stage(tmp_path, sources, monkeypatch):
    """The stage's fingerprint covers what it reads and the code, not just its parameters."""
    import vprscale.jobs.pipeline as pl

    from .conftest import write_recipe

    recipe = write_recipe(tmp_path / "r.toml")
    deep = tmp_path / "deep.fbin"
    shutil.copy(sources["fbin"], deep)
    path = _write(tmp_path / "p.toml", BASE.format(out=tmp_path / "out") +
                  f'[[stages]]\nname = "b"\nkind = "build"\nscale = "{recipe}"\ndeep1b = "{deep}"\n'
                  f'fas = "{sources["fas"]}"\n')
    ran = []

    (tmp_path / "store").mkdir()

    def fake_stage(pipe, stage, outputs, scheduler, console, end):  # the decision is under test, not the build
        ran.append(stage.name)
        return {"store": str(tmp_path / "store")}

    monkeypatch.setattr(pl, "_run_stage", fake_stage)

    def status() -> str:
        return run_pipeline(path)["stages"][0]["status"]

    assert status() == "ran" and status() == "skipped"
    recipe.write_text(recipe.read_text().replace("seed = 5", "seed = 6"))
    assert status() == "ran" and status() == "skipped"
    with deep.open("r+b") as f:  # a source file changes in place
        f.seek(8 + 4 * 96 * 30_000)
        f.write(b"\x00\x00\x80\x3f")
    later = deep.stat().st_mtime_ns + 1_000_000_000
    os.utime(deep, ns=(later, later))
    assert status() == "ran" and status() == "skipped"
    kept = deep.stat()
    with deep.open("r+b") as f:  # changed in the middle again, its size and times put back as they were
        f.seek(8 + 4 * 96 * 40_000)
        f.write(b"\x00\x00\x00\x40")
    os.utime(deep, ns=(kept.st_atime_ns, kept.st_mtime_ns))
    assert deep.stat().st_size == kept.st_size and deep.stat().st_mtime_ns == kept.st_mtime_ns
    decided = run_pipeline(path, dry_run=True)["stages"][0]
    assert decided["run"] and decided["reasons"] == ["input deep1b changed"]
    assert status() == "ran" and status() == "skipped"
    real = pl.stage_code
    monkeypatch.setattr(pl, "stage_code", lambda kind, graph: {**real(kind, graph), "vprscale.dataset.build": "new"})
    assert status() == "ran" and status() == "skipped"
    (tmp_path / "store" / "chunk").write_text("a file the build did not write")
    assert status() == "ran" and status() == "skipped"
    assert ran == ["b"] * 6


def test_an_input_digest_is_computed_once_while_the_file_is_untouched(tmp_path, monkeypatch):
    """The cache serves a file's digest until its identity (ctime included) changes."""
    from vprscale.core import digests as dg

    data = tmp_path / "data.bin"
    data.write_bytes(bytes(range(256)) * 1000)
    reads = []
    real = dg.hashlib.file_digest
    monkeypatch.setattr(dg.hashlib, "file_digest", lambda fh, name: reads.append(1) or real(fh, name))
    first = dg.DigestCache(tmp_path / "c.json")
    sha = first.digest(data)
    first.save()
    assert dg.DigestCache(tmp_path / "c.json").digest(data) == sha and len(reads) == 1
    kept = data.stat()
    with data.open("r+b") as f:
        f.seek(1000)
        f.write(b"x")
    os.utime(data, ns=(kept.st_atime_ns, kept.st_mtime_ns))
    again = dg.DigestCache(tmp_path / "c.json").digest(data)
    assert again != sha and len(reads) == 2
    assert again == __import__("hashlib").sha256(data.read_bytes()).hexdigest()


@pytest.mark.slow
@builds_20k
def test_an_encode_stage_feeds_the_evaluation_and_is_skipped_when_up_to_date(tmp_path):
    """``kind = "encode"`` stores FAISS encodings beside the store; the evaluation that lists it
    in ``encodings`` reads them (its eval.json says so); a second run does nothing."""
    out = tmp_path / "data"
    path = _write(tmp_path / "p.toml", BASE.format(out=out) + """
[[stages]]
name = "build"
kind = "build"
scale = "20K"

[[stages]]
name = "enc"
kind = "encode"
store = "build"
compare = ["PQ4"]

[[stages]]
name = "index"
kind = "index"
store = "build"

[[stages]]
name = "eval"
kind = "eval"
store = "build"
index = "index"
encodings = ["enc"]
noise = ["qm1"]
L = [1]
baseline = false
compare = ["PQ4"]
repeats = 1
""")
    first = run_pipeline(path)
    assert [s["status"] for s in first["stages"]] == ["ran"] * 4
    encoding = out / "20K.faiss" / "PQ4"
    assert (encoding / "encoding.json").is_file() and (encoding / "manifest.json").is_file()
    evaluation = json.loads(next(out.glob("20K-*.index/eval/eval.json")).read_text())
    assert evaluation["compare"]["faiss:PQ4"]["encoding"] == str(encoding)
    assert [s["status"] for s in run_pipeline(path)["stages"]] == ["skipped"] * 4
    shutil.rmtree(encoding)  # a deleted encoding: its stage and the evaluation reading it re-run
    assert [s["status"] for s in run_pipeline(path)["stages"]] == ["skipped", "ran", "skipped", "ran"]


def test_stages_import_this_vprscale_not_a_folder_of_the_current_directory(tmp_path):
    """A stage's process is ``vprscale_argv``: run from a directory holding a ``vprscale/`` folder
    (the parent of a clone, an untrusted directory), it imports the vprscale that spawned it."""
    import subprocess

    from vprscale.jobs.child import vprscale_argv

    trap = tmp_path / "vprscale"
    trap.mkdir()
    (trap / "__init__.py").write_text(f"open({str(tmp_path / 'ran')!r}, 'w').write('x')\nraise SystemExit(7)\n")
    done = subprocess.run(vprscale_argv("methods"), cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "coarsehash" in done.stdout
    assert not (tmp_path / "ran").exists()


def test_a_stage_urls_password_and_signature_are_never_recorded(tmp_path, sources, monkeypatch):
    """A build stage reading Deep1B by a URL with a password and a presigned query: the pipeline's
    state, run summaries and log hold neither secret, and a URL signed anew (the same file) leaves
    the stage up to date."""
    import vprscale.jobs.pipeline as pl

    from .conftest import write_recipe
    from .test_fetch import Server

    data = sources["fbin"].read_bytes()
    server = Server(lambda a, b: data[a:b], len(data))
    recipe = write_recipe(tmp_path / "r.toml")
    (tmp_path / "store").mkdir()
    monkeypatch.setattr(pl, "_run_stage", lambda *args: {"store": str(tmp_path / "store")})

    def run(signature: str) -> str:
        url = server.url.replace("http://", "http://user:hunter2@") + f"?X-Amz-Signature={signature}"
        path = _write(tmp_path / "p.toml", BASE.format(out=tmp_path / "out") +
                      f'[[stages]]\nname = "b"\nkind = "build"\nscale = "{recipe}"\ndeep1b = "{url}"\n'
                      f'fas = "{sources["fas"]}"\n')
        return run_pipeline(path)["stages"][0]["status"]

    try:
        assert run("s3cr3t") == "ran" and run("an0ther") == "skipped"
    finally:
        server.close()
    recorded = [p.read_text() for p in (tmp_path / "out").rglob("*") if p.is_file()]
    assert recorded and not [t for t in recorded if "hunter2" in t or "s3cr3t" in t or "an0ther" in t]
    assert any(server.url in t for t in recorded)


def test_planning_runs_no_code_of_a_stages_method(tmp_path, monkeypatch, capsys):
    """``run --dry-run`` of an eval stage whose method is ``evilpkg.sub:Meth`` in the working
    directory digests the method's source file without importing anything: neither the package's
    ``__init__`` nor the module runs; a method that is not there is one line."""
    package = tmp_path / "evilpkg"
    package.mkdir()
    for name in ("__init__.py", "sub.py"):
        (package / name).write_text(f"open({str(tmp_path / ('ran-' + name))!r}, 'w').write('x')\nclass Meth: pass\n")
    stages = ('[[stages]]\nname = "b"\nkind = "build"\nscale = "20K"\n[[stages]]\nname = "i"\nkind = "index"\n'
              'store = "b"\n[[stages]]\nname = "e"\nkind = "eval"\nstore = "b"\nindex = "i"\n'
              'methods = ["evilpkg.sub:Meth"]\n')
    path = _write(tmp_path / "p.toml", BASE.format(out=tmp_path / "out") + stages)
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(path), "--dry-run"]) == 0
    assert not list(tmp_path.glob("ran-*"))
    gone = _write(tmp_path / "q.toml", BASE.format(out=tmp_path / "out") + stages.replace("sub:", "gone:"))
    assert main(["run", str(gone), "--dry-run"]) == 2
    assert "evilpkg.gone" in capsys.readouterr().err and not list(tmp_path.glob("ran-*"))


def test_a_plan_of_unmeasured_stages_gives_no_figure_rather_than_zero(tmp_path, capsys):
    """A dry run whose stages were never measured (no earlier run, no costs file) says it cannot
    estimate, instead of a total of 0 s and 0 GB."""
    path = _write(tmp_path / "p.toml", BASE.format(out=tmp_path / "out") +
                  '[[stages]]\nname = "b"\nkind = "build"\nscale = "20K"\n[[stages]]\nname = "i"\nkind = "index"\n'
                  'store = "b"\n')
    capsys.readouterr()
    assert main(["run", str(path), "--dry-run"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("estimated: nothing") and "0 s" not in last and "0.00 GB" not in last


def test_an_output_changed_in_place_with_its_times_put_back_reruns_its_stage(tmp_path, monkeypatch):
    """An output is judged by more than its sizes and modification times: rewritten in place with
    both put back (``os.utime`` sets any mtime), the stage runs again."""
    import vprscale.jobs.pipeline as pl

    path = _write(tmp_path / "p.toml", BASE.format(out=tmp_path / "out") +
                  '[[stages]]\nname = "b"\nkind = "build"\nscale = "20K"\n')
    store = tmp_path / "store"
    store.mkdir()
    (store / "data.bin").write_bytes(b"\x01" * 4096)
    monkeypatch.setattr(pl, "_run_stage", lambda pipe, stage, outputs, scheduler, console, end: {"store": str(store)})
    assert run_pipeline(path)["stages"][0]["status"] == "ran"
    assert run_pipeline(path)["stages"][0]["status"] == "skipped"
    kept = (store / "data.bin").stat()
    with (store / "data.bin").open("r+b") as f:
        f.seek(2048)
        f.write(b"\x02")
    os.utime(store / "data.bin", ns=(kept.st_atime_ns, kept.st_mtime_ns))
    decided = run_pipeline(path, dry_run=True)["stages"][0]
    assert decided["run"] and decided["reasons"] == [f"output {store} changed"]


def test_a_part_runs_its_own_stages_and_each_part_has_an_estimate(tmp_path, capsys):
    """``run --part``: the part's stages, no other; ``--dry-run`` lists every part's estimate from
    nothing. The paper's parts cover its ladder."""
    path = _write(tmp_path / "p.toml", BASE.format(out=tmp_path / "out") + TWO
                  + '[[stages]]\nname = "b"\nkind = "build"\nscale = "1M"\n'
                  + '[[parts]]\nname = "small"\nstages = ["a", "i"]\n[[parts]]\nname = "big"\nstages = ["b"]\n')
    plan = run_pipeline(path, dry_run=True, part="small")
    assert [s["name"] for s in plan["stages"]] == ["a", "i"]
    assert [p["name"] for p in plan["parts"]] == ["small", "big"]
    assert main(["run", str(path), "--part", "huge", "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "--part huge: " in err and "parts: small, big" in err
    assert main(["run", str(path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "part small: not kept; 2 stages" in out and "part big: not kept; 1 stages" in out
    paper = load_pipeline(ROOT / "pipelines" / "paper.toml")
    covered = {s for part in paper.parts for s in part.stages}
    assert covered == {s.name for s in paper.stages if s.kind != "report"}


@pytest.mark.slow
@builds_20k
def test_a_part_keeps_its_results_whole_and_without_this_machines_paths(tmp_path, monkeypatch):
    """``run --part``: what the report needs is kept beside it (results, the curves' query columns,
    the indexes' metadata and sizes, each stage's code digests), every path relative to where the
    pipeline ran, and a part that fails keeps nothing over its previous results."""
    monkeypatch.chdir(tmp_path)
    text = ('name = "t"\nout = "data"\n' + '[[stages]]\nname = "b"\nkind = "build"\nscale = "20K"\n'
            '[[stages]]\nname = "i"\nkind = "index"\nstore = "b"\n'
            '[[stages]]\nname = "e"\nkind = "eval"\nstore = "b"\nindex = "i"\nL = [1, 50]\nbaseline = false\n'
            '[[stages]]\nname = "r"\nkind = "report"\nresults = ["e"]\nout = "reports/t"\n'
            '[[parts]]\nname = "small"\nstages = ["b", "i", "e"]\n')
    path = _write(tmp_path / "t.toml", text)
    summary = run_pipeline(path, part="small")
    kept = tmp_path / "reports" / "t" / "parts" / "small"
    assert summary["status"] == "ok" and Path(summary["kept"]).resolve() == kept
    record = json.loads((kept / "part.json").read_text())
    assert record["run"]["from_nothing"] and record["run"]["wall_s"] > 0
    assert isinstance(record["run"]["caches_empty"], bool)  # the FAS fit this test seeds: not empty
    assert [s["name"] for s in record["stages"]] == ["b", "i", "e"]
    assert all(s["parts"]["code"] and s["fingerprint"] for s in record["stages"])
    import pyarrow.parquet as pq

    ran = pq.read_table(tmp_path / "data" / "20K-d15-k2.index" / "eval" / "results.parquet")
    ours = pq.read_table(kept / "evals" / "e" / "results.parquet")
    assert ours.drop_columns(["index", "store"]).equals(ran.drop_columns(["index", "store"]))
    assert set(ours.column("store").to_pylist()) == {"data/20K.zarr"}
    assert set(ours.column("index").to_pylist()) == {"reports/t/parts/small/indexes/20K-d15-k2.index"}
    assert (kept / "indexes" / "20K-d15-k2.index" / "index.json").is_file()
    sizes = json.loads((kept / "indexes" / "20K-d15-k2.index" / "files.json").read_text())
    assert sizes["codes.parquet"] == (tmp_path / "data" / "20K-d15-k2.index" / "codes.parquet").stat().st_size
    assert set(pq.read_schema(kept / "evals" / "e" / "queries.parquet").names) >= {"error", "score", "method"}
    here = str(tmp_path.resolve())
    for f in kept.rglob("*"):
        if f.is_file():
            assert here.encode() not in f.read_bytes(), f  # no path of this machine, in any file or metadata
    # a report drawn into the folder keeps what the parts kept there, and so does one drawn again
    kept_eval = str(kept / "evals" / "e")
    assert main(["report", kept_eval, "--out", "reports/t", "-q"]) == 0
    assert main(["report", kept_eval, "--out", "reports/t", "--force", "-q"]) == 0
    assert (kept / "part.json").is_file() and (tmp_path / "reports" / "t" / "report.md").is_file()
    from vprscale.evaluation.report import _whole_index_bytes  # an index's bytes, from its kept copy
    from vprscale.method.indexmeta import read_index_meta

    copy = kept / "indexes" / "20K-d15-k2.index"
    whole = _whole_index_bytes({**read_index_meta(copy), "path": str(copy)})
    assert whole == sum(read_index_meta(copy)["parts"].values()) > 100_000
    assert not (tmp_path / "reports" / "t.previous" / "parts").exists()
    # kept again (here its stages are up to date): it says every result row is as kept before ...
    assert "as_kept_before" not in record
    run_pipeline(path, part="small")
    again = json.loads((kept / "part.json").read_text())["as_kept_before"]
    assert again["evals"]["e"] == {"rows": ours.num_rows, "same": ours.num_rows, "differing": {}}
    assert again["run"]["started"] == record["run"]["started"]
    # ... and counts, by method, a row it does not reproduce (times aside: they are measured)
    earlier = pd.read_parquet(kept / "evals" / "e" / "results.parquet")
    earlier.loc[0, "recall"] += 0.5
    earlier.loc[1, "us_per_query"] *= 3
    earlier.to_parquet(kept / "evals" / "e" / "results.parquet")
    run_pipeline(path, part="small")
    again = json.loads((kept / "part.json").read_text())["as_kept_before"]["evals"]["e"]
    assert again == {"rows": ours.num_rows, "same": ours.num_rows - 1, "differing": {earlier.method[0]: 1}}
    # a part that fails keeps nothing: its previous results stand
    before = (kept / "part.json").read_bytes()
    shutil.rmtree(tmp_path / "data")
    with pytest.raises(InputError):
        run_pipeline(path, part="small", settings=["e.L=[100000]"])
    assert (kept / "part.json").read_bytes() == before and not (kept.parent / ".small.partial").exists()


@pytest.mark.slow
@builds_20k
def test_a_report_is_assembled_from_kept_parts_on_a_machine_without_their_data(tmp_path, monkeypatch, capsys):
    """``vprscale run PIPELINE REPORT`` of a pipeline in parts: the report is drawn from what the
    parts kept (no stage of theirs runs, ``data/`` may be gone), says each stage's code state, and
    is the same bytes drawn twice; a part not kept is named, with the command that keeps it."""
    monkeypatch.chdir(tmp_path)
    text = ('name = "t"\nout = "data"\n' + '[[stages]]\nname = "b"\nkind = "build"\nscale = "20K"\n'
            '[[stages]]\nname = "i"\nkind = "index"\nstore = "b"\n'
            '[[stages]]\nname = "e"\nkind = "eval"\nstore = "b"\nindex = "i"\nL = [1, 50]\nbaseline = false\n'
            '[[stages]]\nname = "i14"\nkind = "index"\nstore = "b"\nd = 14\n'
            '[[stages]]\nname = "r"\nkind = "report"\nresults = ["e"]\nindexes = ["i14"]\nout = "reports/t"\n'
            '[[parts]]\nname = "main"\nstages = ["b", "i", "e"]\n[[parts]]\nname = "narrow"\nstages = ["b", "i14"]\n')
    path = _write(tmp_path / "t.toml", text)
    for part in ("main", "narrow"):
        assert run_pipeline(path, part=part)["status"] == "ok"
    shutil.rmtree(tmp_path / "data")  # a fresh machine: only the kept parts
    report = tmp_path / "reports" / "t"
    summary = run_pipeline(path, stages=["r"])
    assert [s["name"] for s in summary["stages"]] == ["r"] and not (tmp_path / "data" / "20K.zarr").exists()
    record = json.loads((report / "stages.json").read_text())
    assert {s["name"] for s in record["stages"]} == {"b", "i", "e", "i14"}
    first = {f.name: f.read_bytes() for f in report.iterdir() if f.is_file()}
    assert "fig4d_balance.png" in first and b"20K" in first["report.md"]
    run_pipeline(path, stages=["r"], force=True)
    again = {f.name: f.read_bytes() for f in report.iterdir() if f.is_file()}
    assert again == first  # the same kept results, the same report, byte for byte
    assert (report / "parts" / "main" / "part.json").is_file()
    plan = {p["name"]: p["kept"] for p in run_pipeline(path, dry_run=True)["parts"]}
    assert plan == {"main": "current", "narrow": "current"}
    md = first["report.md"].decode()
    assert "parts: 2 kept; **one code state**" in md and "refreshes it" not in md
    rows = {cells[0]: cells for cells in ([c.strip() for c in line.strip("|").split("|")]
                                          for line in md.splitlines() if line.startswith(("| main |", "| narrow |")))}
    # part, stages, commit, wall min, from nothing, caches empty, machine, kept KB, this vprscale's code
    assert rows["main"][1] == "3" and rows["main"][4] == "yes" and rows["narrow"][4] == "no"  # main built data/
    assert rows["main"][8] == rows["narrow"][8] == "yes"
    # a part kept at other code (its record as an older vprscale would have left it): named, with its command
    kept = report / "parts" / "main" / "part.json"
    original = kept.read_text()
    older = json.loads(original)
    for stage in older["stages"]:
        if stage["name"] == "e":
            stage["parts"]["code"]["vprscale"] = "0" * 16
    kept.write_text(json.dumps(older))
    run_pipeline(path, stages=["r"], force=True)
    md = (report / "report.md").read_text()
    assert "**not one code state**" in md
    assert "part **main** ran other code than this vprscale's: `vprscale run t --part main` refreshes it" in md
    assert "part **narrow** ran other code" not in md
    assert run_pipeline(path, dry_run=True)["parts"][0]["kept"] == "stale: stage e's code changed (vprscale)"
    kept.write_text(original)
    plan = {p["name"]: p["kept"] for p in run_pipeline(path, dry_run=True, settings=["e.L=[1]"])["parts"]}
    assert plan["main"] == "stale: stage e's parameters changed" and plan["narrow"] == "current"
    shutil.rmtree(report / "parts" / "narrow")
    assert {p["name"]: p["kept"] for p in run_pipeline(path, dry_run=True)["parts"]}["narrow"] == "not kept"
    with pytest.raises(InputError, match="stage 'i14' has no kept results; run its part first: vprscale run t "
                                         "--part narrow"):
        run_pipeline(path, stages=["r"], force=True)
