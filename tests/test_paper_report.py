"""The committed flagship: on a fresh clone (no ``data/``), ``vprscale run paper report`` draws
``reports/paper`` from the parts kept in it, the same bytes as committed."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from vprscale.jobs.pipeline import load_pipeline

ROOT = Path(__file__).resolve().parents[1]


def _files(folder: Path) -> dict[str, bytes]:
    """Every file of a report as the repository holds it: report.html, 8 MB with plotly.js
    inside, is generated beside it and not committed (.gitignore)."""
    return {str(f.relative_to(folder)): f.read_bytes() for f in sorted(folder.rglob("*"))
            if f.is_file() and f.name != "report.html"}


@pytest.mark.slow
def test_the_committed_paper_report_is_what_its_kept_parts_draw(tmp_path):
    """Every part kept: the report drawn again equals the committed one, file for file, and the
    kept parts are left as they were. A part not yet kept: the command refuses in one line naming
    the command that keeps it, and the committed report is left whole."""
    committed = ROOT / "reports" / "paper"
    clone = tmp_path / "clone"
    shutil.copytree(committed, clone / "reports" / "paper")
    before = _files(clone / "reports" / "paper")
    parts = load_pipeline("paper").parts
    missing = [p.name for p in parts if not (committed / "parts" / p.name / "part.json").is_file()]
    run = subprocess.run([sys.executable, "-m", "vprscale.cli", "run", "paper", "report"], cwd=clone,
                         capture_output=True, text=True)
    assert not (clone / "data" / "paper" / "20K.zarr").exists()  # nothing was built
    if missing:
        assert run.returncode == 2, run.stderr
        named = "|".join(map(re.escape, missing))
        assert re.search(rf"has no kept results; run its part first: vprscale run paper --part ({named})$",
                         run.stderr.strip()), run.stderr
        assert _files(clone / "reports" / "paper") == before
        return
    assert run.returncode == 0, run.stderr
    assert _files(clone / "reports" / "paper") == before
    assert (clone / "reports" / "paper" / "report.html").is_file()
    # README quotes the ladder as the report has it, row for row
    assert _ladder_table(committed / "report.md") in (ROOT / "README.md").read_text()


def _ladder_table(report: Path) -> str:
    """The rows of the report's "ladder at a glance" table, header included."""
    lines = report.read_text().splitlines()
    start = lines.index("## The ladder at a glance")
    rows = []
    for line in lines[start + 1:]:
        if line.startswith("|"):
            rows.append(line)
        elif rows:
            break
    assert len(rows) >= 4  # header, rule and at least two scales
    return "\n".join(rows)
