"""vprscale as a user installs it: every package in the wheel, the recipes and pipelines shipped as
package data, and a wheel install in a fresh virtual environment that builds, plans and runs the
README's Python example from a folder that is not the checkout."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from vprscale import __version__

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_is_listed_for_the_wheel():
    """pyproject lists the packages (the recipes and pipelines map onto top-level folders), so a new
    subpackage left out of the list would be missing from every wheel."""
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "vprscale").rglob("__init__.py")}
    assert found <= listed
    assert {"vprscale.recipes", "vprscale.pipelines", "vprscale.docs"} <= listed


def test_the_version_is_the_changelogs_newest_section_and_the_citations():
    """The version the code carries is the newest section of CHANGELOG.md (so an output's version
    says which changes made it) and the one CITATION.cff asks readers to cite."""
    newest = re.search(r"^## (\d+\.\d+\.\d+)\b", (ROOT / "CHANGELOG.md").read_text(), re.M)
    assert newest and newest.group(1) == __version__
    assert re.search(r"^version: (\S+)$", (ROOT / "CITATION.cff").read_text(), re.M).group(1) == __version__
    assert not re.search(r"^## Unreleased", (ROOT / "CHANGELOG.md").read_text(), re.M | re.I)


def test_a_build_records_the_checkouts_commit_and_an_install_reads_it(tmp_path):
    """What setup.py writes into a wheel's or sdist's package is what provenance reads back there,
    and a folder that is no checkout has no commit of its own to give."""
    from vprscale.core import commit

    package = tmp_path / "site-packages" / "vprscale"
    commit.record(ROOT, package)
    assert commit.from_build(package) == commit.from_git(ROOT)
    assert commit.from_git(tmp_path) is None and commit.from_build(tmp_path) is None
    (tmp_path / commit.BUILD_FILE).write_text("not json")
    assert commit.from_build(tmp_path) is None


def test_recipes_and_pipelines_come_from_the_installed_package():
    from vprscale.dataset.recipe import known_scales, shipped
    from vprscale.jobs.pipeline import pipeline_path

    assert {"20K", "1M", "10M", "100M", "1B"} <= set(known_scales())
    assert pipeline_path("quickstart") == shipped("vprscale.pipelines") / "quickstart.toml"
    assert pipeline_path("quickstart").read_text() == (ROOT / "pipelines" / "quickstart.toml").read_text()


def test_an_unknown_pipeline_name_lists_the_shipped_ones(tmp_path):
    done = subprocess.run([sys.executable, "-m", "vprscale.cli", "run", "nightly"], capture_output=True, text=True,
                          cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "vprscale run: error: nightly: no such pipeline file, nor a shipped pipeline (shipped: paper, quickstart)"]


def _readme_python_example() -> str:
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert blocks, "the README has a Python example"
    return blocks[0]


def _readme_what_next() -> list[str]:
    """The shell lines of the README's "What next" (its one interactive line left out, and those
    that need a bucket and a cluster: tests/test_objects.py runs the same commands against its own), in order."""
    part = (ROOT / "README.md").read_text().split("## What next", 1)[1].split("\n## ", 1)[0]
    lines = [line.split("  #")[0].strip() for block in re.findall(r"```bash\n(.*?)```", part, re.S)
             for line in block.strip().splitlines()]
    return [line for line in lines if line and not re.fullmatch(r"vprscale sql \$I", line) and "s3://" not in line]


def _byo_inputs() -> str:
    """docs/bring-your-own.md's numpy that makes a traverse pair (what the README's step 3 reads)."""
    return re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "bring-your-own.md").read_text(), re.S)[0]


def _venv_beside_this_environment(venv: Path) -> Path:
    """A new virtual environment, without system site packages, that sees this interpreter's
    site-packages (the dependencies: a venv's or the system's alike) after its own, through a
    ``.pth`` of paths (whose own ``.pth`` files, an editable vprscale's among them, are not read)."""
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    python = venv / "bin" / "python"
    own = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                         check=True, capture_output=True, text=True).stdout.strip()
    outer = [p for p in sys.path if p.endswith(("site-packages", "dist-packages")) and Path(p).is_dir()]
    (Path(own) / "outer-environment.pth").write_text("\n".join(outer) + "\n")
    return python


@pytest.mark.slow
def test_wheel_install_builds_plans_and_runs_the_python_example(tmp_path):
    """A wheel, built by ``python -m build`` from an sdist of a checkout, installed into a fresh
    venv (the dependencies come from this environment): from an empty folder it builds, indexes and
    evaluates the 20K store where the quickstart puts it, recording the checkout's commit, plans the
    shipped quickstart pipeline by name and runs the README's Python example on them."""
    source = tmp_path / "source"  # a copy: building writes build/ and egg-info beside the sources
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns("data", "build", "dist", "*.egg-info", "_build.json",
                                                                "__pycache__", ".*_cache"))
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "build", "--no-isolation", "--outdir", str(wheels), str(source)],
                   check=True, capture_output=True)  # the sdist, then the wheel from the sdist (no git there)
    (wheel,) = wheels.glob("vprscale-*.whl")
    venv = tmp_path / "venv"
    python = _venv_beside_this_environment(venv)
    subprocess.run([str(python), "-m", "pip", "install", "--no-deps", "-q", str(wheel)], check=True,
                   capture_output=True)
    work = tmp_path / "work"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VPRSCALE_DATASETS")}
    where = subprocess.run([str(python), "-c", "import vprscale; print(vprscale.__file__)"], cwd=work, env=env,
                           capture_output=True, text=True, check=True).stdout.strip()
    assert Path(where).is_relative_to(venv), f"the venv imports vprscale from {where}, not the wheel"

    def vprscale(*argv: str) -> subprocess.CompletedProcess:
        return subprocess.run([str(venv / "bin" / "vprscale"), *argv], cwd=work, env=env, capture_output=True,
                              text=True)

    q = "data/quickstart"  # where the quickstart leaves them, which the README's example reads
    for argv in (["build", "--scale", "20K", "--out", q], ["index", f"{q}/20K.zarr", "--out", f"{q}/20K-d15-k2.index"],
                 ["eval", f"{q}/20K.zarr", f"{q}/20K-d15-k2.index", "--L", "1", "--noise", "qm1", "--no-baseline",
                  "--repeats", "1"]):
        done = vprscale(*argv, "--quiet")
        assert done.returncode == 0, done.stderr
    assert (work / q / "20K.zarr" / "manifest.json").is_file()
    built = json.loads((work / q / "20K.zarr" / "build.json").read_text())["provenance"]
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
    assert built["vprscale"] == __version__
    assert built["commit"] == (head.stdout.strip() if head.returncode == 0 else None)
    shown = vprscale("build", "--help").stdout.rsplit("docs: ", 1)[1].strip()  # the pages, installed with it
    assert Path(shown).is_file() and Path(shown).is_relative_to(venv) and (Path(shown).parent / "protocol.md").is_file()
    plan = vprscale("run", "quickstart", "--dry-run")
    assert plan.returncode == 0, plan.stderr
    assert "build-20K (build)" in plan.stdout and "report (report)" in plan.stdout
    example = subprocess.run([str(python), "-c", _readme_python_example()], cwd=work, env=env, capture_output=True,
                             text=True)
    assert example.returncode == 0, example.stderr[-3000:]
    made = subprocess.run([str(python), "-c", _byo_inputs()], cwd=work, env=env, capture_output=True, text=True)
    assert made.returncode == 0, made.stderr
    shell_env = {**env, "PATH": f"{venv / 'bin'}:{env.get('PATH', '')}"}
    lines = _readme_what_next()
    assert any(line.startswith("vprscale results") for line in lines) and any("--compare PQ2" in x for x in lines)
    done = subprocess.run(["bash", "-ec", "\n".join(lines)], cwd=work, env=shell_env, capture_output=True, text=True)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr[-3000:]
    assert (work / "runs" / "mine" / "results.parquet").is_file()
