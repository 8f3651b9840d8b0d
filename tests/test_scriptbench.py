"""``vprscale bench build SCALE --script PREPROCDATA_PY``: the build beside the authors' dataset script."""

from __future__ import annotations

import dataclasses
import textwrap

import pytest

from vprscale.cli import main
from vprscale.dataset.sources.synthetic import SyntheticFAS
from vprscale.dataset.sources.writers import write_fas_npz

from .conftest import SMALL_FAS

# A script with the interface of the authors' preProcData.py (``createDataset(dataPath, dStr,
# sigScale)`` reading ``Deep1B/base/base_00`` and ``FAS/FAS_uniSam5_all.npz`` under
# ``dataPath``); their code is theirs, and a user gives its path. This one checks the layout
# it is given and notes each run in the file ``$RUNS_LOG`` names.
STAND_IN = textwrap.dedent("""
    import os
    import numpy as np

    def createDataset(dataPath, dStr, sigScale=1):
        n = {"20K": 20000, "1M": 1000000, "10M": 10000000}[dStr]
        raw = np.fromfile(os.path.join(dataPath, "Deep1B/base/base_00"), "int32", count=n * 97)
        deep = raw.reshape(-1, 97)[:, 1:].view("float32")
        fas = np.load(os.path.join(dataPath, "FAS/FAS_uniSam5_all.npz"))
        ref, query = fas["arr_0"][:, :96], fas["arr_1"][:, :96]
        assert deep.shape == (n, 96) and len([k for k in fas.files if k.startswith("arr_")]) == 7
        with open(os.environ["RUNS_LOG"], "a") as log:
            log.write(f"{dStr} {len(deep)}\\n")
        return np.concatenate([deep, ref]), np.concatenate([deep, query])
""")


@pytest.mark.slow
def test_the_build_and_the_script_run_alternately_on_the_same_files(sources, tmp_path, monkeypatch, capsys):
    script = tmp_path / "preProcData.py"
    script.write_text(STAND_IN)
    runs = tmp_path / "runs.log"
    monkeypatch.setenv("RUNS_LOG", str(runs))
    fas = tmp_path / "fas.npz"  # the 20K recipe takes 10,000 FAS places
    write_fas_npz(SyntheticFAS(3, dataclasses.replace(SMALL_FAS, n_ref=12_000, n_query=11_000)).traverse(), fas)
    argv = ["bench", "build", "20K", "--script", str(script), "--deep1b", str(sources["fvecs"] / "base_00"),
            "--fas", str(fas), "--out", str(tmp_path / "out"), "--workers", "2", "--runs", "2"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert runs.read_text().splitlines() == ["20K 20000", "20K 20000"]  # the script ran twice, on 20,000 rows
    assert "run 1: vprscale build" in out and "(FAS fit computed)" in out
    assert "run 2: vprscale build" in out and "(FAS fit cached)" in out
    assert "the first build's time" in out and "the median build with the FAS fit cached" in out
    assert (tmp_path / "out" / "20K.zarr" / "manifest.json").is_file()  # the last build's store


def test_bad_script_benchmarks_are_one_line(sources, tmp_path, capsys):
    script = tmp_path / "preProcData.py"
    script.write_text(STAND_IN)
    short = tmp_path / "short.fvecs"
    short.write_bytes((sources["fvecs"] / "base_00").read_bytes()[: 100 * 4 * 97])
    base = ["bench", "build", "20K", "--script", str(script), "--out", str(tmp_path / "out")]
    for argv, words in (
        (["bench", "build", "100M", "--script", str(script), "--deep1b", str(short), "--fas", str(sources["fas"])],
         "makes 20K, 1M or 10M, not 100M"),
        ([*base, "--deep1b", str(short)], "give --deep1b (one fvecs file) and --fas"),
        ([*base, "--deep1b", str(short), "--fas", str(sources["fas"])],
         "100 rows of 96-d fvecs; the script reads 20,000"),
        ([*base, "--deep1b", str(tmp_path), "--fas", str(sources["fas"])], f"--deep1b {tmp_path}: not a file"),
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], err
    assert not (tmp_path / "out").exists()
