"""Compiled kernels are cached by the state of vprscale's kernel sources, not by where vprscale
is installed (vprscale.core.kernelcache): another install of the same code loads them, a changed
kernel module compiles them again."""

from __future__ import annotations

import fcntl
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


# the same kernel wanted by a process that says where its compile lock is, then waits for a line
WAITING = """
import json, sys, numpy as np
from vprscale.core.kernelcache import compile_lock
from vprscale.method import kmeans1d
print(compile_lock(kmeans1d._segment_cost.py_func), flush=True)
sys.stdin.readline()
kmeans1d._segment_cost(np.arange(4.0), np.arange(4.0), np.arange(4.0), 0, 3)
s = kmeans1d._segment_cost.stats
print(json.dumps({"hits": sum(s.cache_hits.values()), "misses": sum(s.cache_misses.values())}))
"""


def _env(install: Path, cache: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env.update(PYTHONPATH=str(install), XDG_CACHE_HOME=str(cache))
    return env


def _install(where: Path) -> Path:
    shutil.copytree(PACKAGE, where / "vprscale", ignore=shutil.ignore_patterns("__pycache__"))
    return where


def _probe(install: Path, cache: Path) -> dict:
    done = subprocess.run([sys.executable, "-c", PROBE], env=_env(install, cache), capture_output=True, text=True,
                          cwd=install)
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


def test_processes_that_want_the_same_kernel_compile_it_once(tmp_path):
    """Two processes that miss the cache together: one compiles, the other waits for it and loads
    what it cached. The lock is held here until both want the kernel, so that they overlap."""
    install, cache = _install(tmp_path / "a"), tmp_path / "cache"
    procs = [subprocess.Popen([sys.executable, "-c", WAITING], env=_env(install, cache), cwd=install, text=True,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
             for _ in range(2)]
    locks = {p.stdout.readline().strip() for p in procs}
    assert len(locks) == 1 and Path(next(iter(locks))).is_relative_to(cache)
    lock = os.open(next(iter(locks)), os.O_RDWR | os.O_CREAT)
    fcntl.flock(lock, fcntl.LOCK_EX)
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()
    time.sleep(1.0)  # both now wait for the lock (without it, both would compile now)
    os.close(lock)
    stats = []
    for p in procs:
        out, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
        stats.append(json.loads(out))
    assert sorted((s["hits"], s["misses"]) for s in stats) == [(0, 1), (1, 0)]
