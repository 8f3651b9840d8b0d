"""Resumability, locking, refusal of bad input and the distributed path of the build."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zarr

from vprscale.cli import main
from vprscale.core.publish import exclusive

from .conftest import write_recipe
from .test_build import ARRAYS, run_build


def _bytes(path: Path) -> dict[str, bytes]:
    g = zarr.open_group(path, mode="r")
    return {k: g[k][:].tobytes() for k in ARRAYS}


@pytest.mark.slow
def test_killed_build_resumes_to_identical_bytes(tmp_path, sources):
    recipe = write_recipe(tmp_path / "tiny.toml", deep1b_rows_read=600_000, deep1b_rows_kept=600_000)
    cmd = [sys.executable, "-m", "vprscale.cli", "build", "--scale", str(recipe), "--fas",
           str(sources["fas"]), "--out", str(tmp_path / "a"), "--workers", "1"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    done = tmp_path / "a" / ".tiny.zarr.partial" / ".done"
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if done.is_dir() and len([p for p in done.iterdir() if p.name.startswith("chunk-")]) >= 3:
            os.kill(proc.pid, signal.SIGKILL)
            break
        time.sleep(0.02)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the build finished before it could be killed"
    assert not (tmp_path / "a" / "tiny.zarr").exists()  # nothing incomplete at the public path
    finished = len([p for p in done.iterdir() if p.name.startswith("chunk-")])
    assert 3 <= finished < 37
    out = subprocess.run(cmd, capture_output=True, text=True, check=True)
    assert "resumed" in out.stdout
    run_build(recipe, tmp_path / "b", sources | {"none": None}, layout="none")
    assert _bytes(tmp_path / "a" / "tiny.zarr") == _bytes(tmp_path / "b" / "tiny.zarr")


def test_second_build_into_a_locked_store_is_refused(tmp_path, sources, capsys):
    recipe = write_recipe(tmp_path / "tiny.toml")
    with exclusive(tmp_path / "out" / "tiny.zarr"):
        code = main(["build", "--scale", str(recipe), "--deep1b", str(sources["fbin"]), "--fas",
                     str(sources["fas"]), "--out", str(tmp_path / "out")])
    assert code == 2
    assert "another vprscale job is writing" in capsys.readouterr().err


def test_complete_store_is_kept_unless_forced_and_survives_a_failed_rebuild(tmp_path, sources, capsys):
    recipe = write_recipe(tmp_path / "tiny.toml")
    args = ["build", "--scale", str(recipe), "--deep1b", str(sources["fbin"]), "--fas", str(sources["fas"]),
            "--out", str(tmp_path / "out")]
    assert main(args) == 0
    store = tmp_path / "out" / "tiny.zarr"
    before = _bytes(store)
    stamp = (store / "zarr.json").stat().st_mtime_ns
    assert main(args) == 0
    assert "is complete; use --force" in capsys.readouterr().err
    assert (store / "zarr.json").stat().st_mtime_ns == stamp
    bad = tmp_path / "bad.fbin"
    bad.write_bytes(sources["fbin"].read_bytes()[:-7])
    args_bad = [*args, "--force"]
    args_bad[args_bad.index(str(sources["fbin"]))] = str(bad)
    assert main(args_bad) == 2
    assert "bad.fbin" in capsys.readouterr().err
    assert _bytes(store) == before
    assert main([*args, "--force"]) == 0
    assert _bytes(store) == before


@pytest.mark.parametrize(("args", "message"), [
    (["--scale", "3K"], "--scale 3K: unknown scale"),
    (["--scale", "{recipe_big}"], "needs 100,000 Deep1B rows but .*base.fbin holds 70,000"),
    (["--scale", "{recipe_bad}"], "key 'window' has the wrong type"),
    (["--scale", "{recipe}", "--out", "{file}/sub"], "cannot create the output directory"),
    (["--scale", "{recipe}", "--deep1b", "{missing}"], "missing.fbin: no such file"),
])
def test_bad_input_exits_2_with_a_named_message(tmp_path, sources, capsys, args, message):
    names = {"recipe": write_recipe(tmp_path / "tiny.toml"),
             "recipe_big": write_recipe(tmp_path / "big.toml", deep1b_rows_read=100_000),
             "recipe_bad": write_recipe(tmp_path / "bad.toml", window="forty"),
             "file": tmp_path / "plain-file", "missing": tmp_path / "missing.fbin"}
    (tmp_path / "plain-file").write_text("x")
    args = [a.format(**names) for a in args]
    base = ["build", "--deep1b", str(sources["fbin"]), "--fas", str(sources["fas"]),
            "--out", str(tmp_path / "out")]
    code = main(base + args)
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("vprscale build: error:")
    import re
    assert re.search(message, err), err
    assert not list((tmp_path / "out").glob("*.zarr")) if (tmp_path / "out").exists() else True


def test_dry_run_prints_the_plan_and_writes_nothing(tmp_path, sources, capsys):
    recipe = write_recipe(tmp_path / "tiny.toml")
    code = main(["build", "--scale", str(recipe), "--deep1b", str(sources["fbin"]), "--fas",
                 str(sources["fas"]), "--out", str(tmp_path / "out"), "--dry-run"])
    assert code == 0
    text = capsys.readouterr().out
    assert "ref rows" in text and "52,500" in text and "estimated" in text
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_distributed_build_equals_local_build(tmp_path, sources):
    from distributed import LocalCluster

    recipe = write_recipe(tmp_path / "tiny.toml")
    run_build(recipe, tmp_path / "local", sources)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        run_build(recipe, tmp_path / "dist", sources, scheduler=cluster.scheduler_address)
    assert _bytes(tmp_path / "local" / "tiny.zarr") == _bytes(tmp_path / "dist" / "tiny.zarr")
    # Every file that defines the dataset, metadata included (the run's timings live in build.json).
    files = [_files(tmp_path / where / "tiny.zarr") for where in ("local", "dist")]
    assert files[0].keys() == files[1].keys() and files[0] == files[1]


def _files(store: Path) -> dict[str, bytes]:
    """Every file but the run's timings, and the manifest without build.json's entry."""
    import json

    files = {str(p.relative_to(store)): p.read_bytes() for p in store.rglob("*")
             if p.is_file() and p.name != "build.json"}
    listed = json.loads(files.pop("manifest.json"))["files"]
    files["manifest.json"] = json.dumps({k: v for k, v in listed.items() if k != "build.json"}, sort_keys=True).encode()
    return files
