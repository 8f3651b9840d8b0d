"""Compiled kernels are cached by the state of vprscale's kernel sources, not by where vprscale
is installed (vprscale.core.kernelcache): another install of the same code loads them, a changed
kernel module compiles them again."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import vprscale
from vprscale.core.kernelcache import KEEP_DAYS

PACKAGE = Path(vprscale.__file__).parent
# one small kernel, called: where numba looked for it, and whether it was loaded or compiled
PROBE = """
import json, numpy as np
from vprscale.method import kmeans1d
kmeans1d._segment_cost(np.arange(4.0), np.arange(4.0), np.arange(4.0), 0, 3)
s = kmeans1d._segment_cost.stats
print(json.dumps({"path": s.cache_path, "hits": sum(s.cache_hits.values()), "misses": sum(s.cache_misses.values())}))
"""


def _install(where: Path) -> Path:
    shutil.copytree(PACKAGE, where / "vprscale", ignore=shutil.ignore_patterns("__pycache__"))
    return where


def _probe(install: Path, cache: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env.update(PYTHONPATH=str(install), XDG_CACHE_HOME=str(cache))
    done = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, cwd=install)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_another_install_of_the_same_code_loads_the_kernels_and_a_changed_kernel_module_compiles(tmp_path):
    """Two copies of the package (two installs) share one cache folder per code state."""
    cache = tmp_path / "cache"
    a, b = _install(tmp_path / "a"), _install(tmp_path / "b")
    first = _probe(a, cache)
    assert (first["hits"], first["misses"]) == (0, 1)
    assert Path(first["path"]).is_relative_to(cache / "numba" / "vprscale")
    assert not list((a / "vprscale").rglob("*.nbi"))  # nothing written beside the modules
    second = _probe(b, cache)
    assert (second["hits"], second["misses"]) == (1, 0) and second["path"] == first["path"]
    # kmeans1d itself is unchanged, but a kernel it could call changed: its cached code may be stale;
    # the new state's folder is made, and other states' folders unused for a month are removed
    states = cache / "numba" / "vprscale"
    stale, recent = states / "stale", states / "recent"
    for folder, days in ((stale, KEEP_DAYS + 1), (recent, KEEP_DAYS - 1)):
        folder.mkdir()
        os.utime(folder, (time.time() - days * 86400,) * 2)
    with (b / "vprscale" / "method" / "kernels.py").open("a") as f:
        f.write("\n# a change\n")
    changed = _probe(b, cache)
    assert (changed["hits"], changed["misses"]) == (0, 1) and changed["path"] != first["path"]
    assert not stale.exists() and recent.is_dir()
    assert _probe(a, cache)["hits"] == 1  # the first state's kernels are still there
