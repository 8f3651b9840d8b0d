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


def test_a_cache_folder_that_is_a_link_or_writable_by_others_is_neither_trusted_nor_pruned(tmp_path):
    """numba unpickles what its cache holds: a kernel cache another user could have written is not
    read, and a prune never follows a link out of the cache (its target's old folders stay)."""
    install, cache = _install(tmp_path / "a"), tmp_path / "cache"
    target = tmp_path / "elsewhere"
    old = target / "a-user's-folder"
    old.mkdir(parents=True)
    os.utime(old, (time.time() - (KEEP_DAYS + 5) * 86400,) * 2)
    (cache / "numba").mkdir(parents=True)
    (cache / "numba" / "vprscale").symlink_to(target)
    linked = _probe(install, cache)
    assert old.is_dir() and [p.name for p in target.iterdir()] == [old.name]  # nothing made or removed there
    assert not Path(linked["path"]).is_relative_to(cache) and linked["misses"] == 1
    assert not Path(linked["path"]).exists()  # the process's own folder went with it

    (cache / "numba" / "vprscale").unlink()
    shared = cache / "numba" / "vprscale"
    shared.mkdir(mode=0o777)
    shared.chmod(0o777)  # as a folder anybody can write would be: a planted index would run code
    assert not Path(_probe(install, cache)["path"]).is_relative_to(shared) and not any(shared.iterdir())
    shared.chmod(0o700)
    first = _probe(install, cache)
    assert Path(first["path"]).is_relative_to(shared) and _probe(install, cache)["hits"] == 1


def test_a_damaged_kernel_cache_is_compiled_again_not_a_crash(tmp_path):
    """A cache entry cut short (a disk that filled while numba wrote it) is said, compiled and cached again."""
    install, cache = _install(tmp_path / "a"), tmp_path / "cache"
    assert _probe(install, cache)["misses"] == 1
    entries = list((cache / "numba" / "vprscale").rglob("*kmeans1d*/*_segment_cost*.nb*"))
    entries += list((cache / "numba" / "vprscale").rglob("*_segment_cost*.nb*"))
    assert entries
    for damaged in {p for p in entries if p.suffix in (".nbi", ".nbc")}:
        damaged.write_bytes(damaged.read_bytes()[:20])
    done = subprocess.run([sys.executable, "-c", PROBE], env=_env(install, cache), capture_output=True, text=True,
                          cwd=install)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["misses"] == 1
    assert _probe(install, cache)["hits"] == 1  # cached again, whole


HOLDER = """
import fcntl, os, sys
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)
fcntl.flock(fd, fcntl.LOCK_EX)
os.ftruncate(fd, 0)
os.write(fd, str(os.getpid()).encode())
print("held", flush=True)
sys.stdin.readline()
"""


def test_a_stopped_compiler_holds_nobody_up(tmp_path):
    """A process stopped while it holds a kernel's lock (Ctrl-Z, a suspended batch job): another
    process that wants the kernel compiles it instead of waiting for the stopped one."""
    import signal

    install, cache = _install(tmp_path / "a"), tmp_path / "cache"
    waiting = subprocess.Popen([sys.executable, "-c", WAITING], env=_env(install, cache), cwd=install, text=True,
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    lock = waiting.stdout.readline().strip()
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, lock], text=True, stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE)
    try:
        assert holder.stdout.readline().strip() == "held"
        holder.send_signal(signal.SIGSTOP)
        waiting.stdin.write("go\n")
        waiting.stdin.flush()
        out, err = waiting.communicate(timeout=300)  # far below the 600 s a running holder is waited for
        assert waiting.returncode == 0, err
        assert json.loads(out)["misses"] == 1
    finally:
        holder.kill()
        holder.wait()


# a command-line process's signal handling, the kernel wanted by a worker thread (a Dask task)
THREADED = """
import signal, sys, threading, numpy as np
from vprscale.core.errors import Interrupted
from vprscale.method import kmeans1d
def stop(signum, frame):
    raise Interrupted(signum)
signal.signal(signal.SIGTERM, stop)
worker = threading.Thread(target=kmeans1d._segment_cost, args=(np.arange(4.0), np.arange(4.0), np.arange(4.0), 0, 3))
print("go", flush=True)
worker.start()
try:
    worker.join()
except Interrupted:
    sys.exit(143)
"""


def test_a_process_waiting_for_a_kernel_ends_on_sigterm(tmp_path):
    """SIGTERM (a batch scheduler's time limit) ends a process whose worker thread waits for a
    kernel another process compiles, not after the wait's 600 s."""
    import signal

    install, cache = _install(tmp_path / "a"), tmp_path / "cache"
    probe = subprocess.Popen([sys.executable, "-c", WAITING], env=_env(install, cache), cwd=install, text=True,
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    lock = probe.stdout.readline().strip()
    probe.kill()
    probe.wait()
    fd = os.open(lock, os.O_RDWR | os.O_CREAT)
    fcntl.flock(fd, fcntl.LOCK_EX)  # held by this (running) test process
    try:
        env = _env(install, cache)
        proc = subprocess.Popen([sys.executable, "-c", THREADED], env=env, cwd=install, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        assert proc.stdout.readline().strip() == "go"
        time.sleep(3.0)  # the worker thread now waits for the lock
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=120)
        assert proc.returncode == 143
    finally:
        os.close(fd)


def test_which_folders_are_private(tmp_path, caplog):
    """A cache folder is used only where strangers cannot write it or swap it: under a parent of
    this user's that its group may write (``~/.cache`` under a umask of 002) or a sticky one
    (``/tmp``), never under one everybody can write, and never when it is itself writable by
    others (the warning says how to make it private)."""
    from vprscale.core.private import private_folder

    def parent(name: str, mode: int) -> Path:
        folder = tmp_path / name
        folder.mkdir()
        folder.chmod(mode)
        return folder

    made = private_folder(parent("group", 0o775) / "vprscale", "compiled alone")
    assert made is not None and made.stat().st_mode & 0o777 == 0o700
    assert private_folder(parent("sticky", 0o1777) / "vprscale", "compiled alone") is not None
    assert private_folder(parent("open", 0o777) / "vprscale", "compiled alone") is None
    shared = parent("mine", 0o755) / "vprscale"
    shared.mkdir()
    shared.chmod(0o775)
    assert private_folder(shared, "compiled alone") is None
    assert f"chmod go-w {shared}" in caplog.text
