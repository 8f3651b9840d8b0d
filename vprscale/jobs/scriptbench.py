"""``vprscale bench build SCALE --script preProcData.py``: the build beside the paper authors' own
dataset script on the same files, run alternately, with the ratio of their wall times.

The authors' ``preProcData.py`` (github.com/oravus/CoarseHash) makes the 20K, 1M and 10M
datasets with ``createDataset(dataPath, dStr)``: it reads ``Deep1B/base/base_00`` (fvecs) and
``FAS/FAS_uniSam5_all.npz`` under ``dataPath``, and its ``main`` saves the two arrays with
``np.savez``. The benchmark lays the given files out under those names (symbolic links in a
temporary folder), calls ``createDataset`` and saves as ``main`` does, in a child process of
its own; the build runs as ``vprscale build --scale SCALE --deep1b … --fas …``. The first build
starts from an empty cache, so it computes the FAS fit (the PCA of FAS100K); the later ones
find it cached (:mod:`vprscale.dataset.fascache`), as every rung of a ladder after the first
does: both are printed. The script recomputes its FAS PCA on every run (twice a run).
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

from vprscale.core.errors import InputError
from vprscale.jobs.bench import run_child, spawn

SCRIPT_SCALES = {"20K": 20_000, "1M": 1_000_000, "10M": 10_000_000}  # Deep1B rows the script reads (its loadD1B)
FVECS_ROW = 4 * 97  # a 96-d fvecs record: its dimension, then 96 float32
# The child that runs the script as its main() does, for another scale and data folder
_RUN_SCRIPT = """
import importlib.util, sys
import numpy as np
spec = importlib.util.spec_from_file_location("preProcData", sys.argv[1])
script = importlib.util.module_from_spec(spec)
spec.loader.exec_module(script)
f1, f2 = script.createDataset(sys.argv[2], sys.argv[3], sigScale=1)
np.savez(sys.argv[4], f1, f2)
"""


def _checked(script: str, scale: str, deep1b: str | None, fas: str | None) -> tuple[Path, Path, Path]:
    """The script, Deep1B and FAS files, or one line naming what is wrong with them."""
    if scale not in SCRIPT_SCALES:
        raise InputError(f"bench build --script: the authors' script makes 20K, 1M or 10M, not {scale}")
    if not deep1b or not fas:
        raise InputError("bench build --script: give --deep1b (one fvecs file) and --fas (the FAS100K .npz): "
                         "both read the same files")
    paths = Path(script), Path(deep1b), Path(fas)
    for flag, p in zip(("--script", "--deep1b", "--fas"), paths, strict=True):
        if not p.is_file():
            raise InputError(f"bench build {flag} {p}: not a file")
    need = SCRIPT_SCALES[scale] * FVECS_ROW
    if paths[1].stat().st_size < need:
        raise InputError(f"bench build --deep1b {paths[1]}: {paths[1].stat().st_size // FVECS_ROW:,} rows of 96-d "
                         f"fvecs; the script reads {SCRIPT_SCALES[scale]:,} at {scale}")
    return paths


def _run_script(script: Path, deep1b: Path, fas: Path, scale: str) -> dict[str, Any]:
    """One run of the script in a child process: its wall time and peak memory."""
    with tempfile.TemporaryDirectory(prefix="vprscale-script-") as tmp:
        root = Path(tmp)
        (root / "Deep1B" / "base").mkdir(parents=True)
        (root / "FAS").mkdir()
        (root / "Deep1B" / "base" / "base_00").symlink_to(deep1b.resolve())
        (root / "FAS" / "FAS_uniSam5_all.npz").symlink_to(fas.resolve())
        r = spawn([sys.executable, "-c", _RUN_SCRIPT, str(script.resolve()), f"{root}/", scale,
                   str(root / "out.npz")])
    if r["code"] != 0:
        raise InputError(f"bench build --script {script}: the script failed on these files (its error is above)")
    return r


def bench_against_script(script: str, scale: str, out: str, deep1b: str | None, fas: str | None, workers: int,
                         runs: int) -> str:
    """``runs`` builds and ``runs`` script runs, alternating (build first), and their ratios."""
    script_path, deep1b_path, fas_path = _checked(script, scale, deep1b, fas)
    argv = ["build", "--scale", scale, "--out", out, "--workers", str(workers),
            "--deep1b", str(deep1b_path), "--fas", str(fas_path)]
    builds, scripts = [], []
    with tempfile.TemporaryDirectory(prefix="vprscale-cache-") as cache:
        env = {**os.environ, "VPRSCALE_CACHE": cache}  # the first build computes the FAS fit, the later find it
        for _ in range(runs):
            builds.append(run_child(argv, fresh=Path(out) / f"{scale}.zarr", env=env))
            scripts.append(_run_script(script_path, deep1b_path, fas_path, scale))
    script_s = statistics.median(r["wall_s"] for r in scripts)
    lines = [f"build {scale} from {deep1b_path.name} and {fas_path.name} beside {script_path.name}, "
             f"{runs} run(s) each, alternating"]
    for i, (b, s) in enumerate(zip(builds, scripts, strict=True)):
        fit = "FAS fit computed" if i == 0 else "FAS fit cached"
        lines.append(f"  run {i + 1}: vprscale build {b['wall_s']:.1f} s ({fit}), peak "
                     f"{b['peak_rss_bytes'] / 2**30:.2f} GiB; {script_path.name} {s['wall_s']:.1f} s, peak "
                     f"{s['peak_rss_bytes'] / 2**30:.2f} GiB")
    lines.append(f"  {script_path.name} median {script_s:.1f} s: {script_s / builds[0]['wall_s']:.1f}× the first "
                 f"build's time")
    if runs > 1:
        cached = statistics.median(b["wall_s"] for b in builds[1:])
        lines.append(f"  {script_s / cached:.1f}× the median build with the FAS fit cached ({cached:.1f} s)")
    return "\n".join(lines)
