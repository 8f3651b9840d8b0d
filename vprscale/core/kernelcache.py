"""Where numba caches vprscale's compiled kernels: one folder per state of their sources, shared
by every install of that state.

numba's own cache sits beside each module (``__pycache__``) or under ``$NUMBA_CACHE_DIR`` by the
module's path, so every install compiles everything again: a new virtual environment, a wheel, a
second checkout, each a minute or more of a first command. And numba checks only the file that
defines a kernel, while vprscale's kernels call kernels of other modules: a cached kernel could
hold the old code of a callee that changed. Here every vprscale kernel is cached under
``<cache>/vprscale/<state>/<module>``: ``<state>`` a digest of every kernel module's source and
the numba release, ``<cache>`` ``$NUMBA_CACHE_DIR`` if set, else numba's user cache folder
(``~/.cache/numba``). An install of the same code finds its kernels compiled; any change to a
kernel module compiles them all again, in a new folder. Folders unused for ``KEEP_DAYS`` are
removed when a new one is made. Where the folder cannot be written, numba's own places serve;
``$NUMBA_CACHE_LOCATOR_CLASSES`` overrides all of this, as numba documents.

A kernel is compiled once per machine, not once per process: processes started together (Dask
workers, the stages of a pipeline, test workers) each miss the cache and would each compile the
same kernels, tens of seconds of CPU apiece. A process about to compile a kernel holds a lock
file beside its cache entry (``flock``: released by the kernel, whether its compilation ended or
failed, or by the end of the process however it ends); another process that needs the same
kernel waits, then finds it cached and loads it. Locks are taken under numba's own compiler lock,
one thread of a process at a time, and in the order kernels call each other (a kernel's lock
before its callees'), so two processes never wait on each other. A wait longer than
``WAIT_S`` compiles anyway.
"""

from __future__ import annotations

import fcntl
import functools
import hashlib
import logging
import os
import re
import shutil
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path

import numba
from numba.core import caching, config, sigutils
from numba.core.compiler_lock import global_compiler_lock
from numba.core.dispatcher import Dispatcher
from numba.misc.appdirs import AppDirs

log = logging.getLogger(__name__)
PACKAGE = Path(__file__).resolve().parents[1]
KEEP_DAYS = 30
WAIT_S = 600.0  # the longest a process waits for another's compilation of a kernel
_IMPORTS_NUMBA = re.compile(rb"^(import|from) numba\b", re.M)


@cache
def kernel_sources() -> tuple[Path, ...]:
    """vprscale's modules that compile with numba, in a fixed order."""
    found = (p for p in PACKAGE.rglob("*.py") if _IMPORTS_NUMBA.search(p.read_bytes()))
    return tuple(sorted(found, key=lambda p: p.relative_to(PACKAGE).as_posix()))


@cache
def state() -> str:
    """A digest of every kernel module's source and the numba release that compiles them."""
    digest = hashlib.blake2b(numba.__version__.encode(), digest_size=10)
    for path in kernel_sources():
        digest.update(path.relative_to(PACKAGE).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


@cache
def state_folder() -> Path | None:
    """This state's folder (made, and marked used, once per process), or None if it cannot be written."""
    root = Path(config.CACHE_DIR or AppDirs(appname="numba", appauthor=False).user_cache_dir) / "vprscale"
    folder = root / state()
    try:
        made = not folder.is_dir()
        folder.mkdir(parents=True, exist_ok=True)
        os.utime(folder)
    except OSError:
        return None
    if made:
        _prune(root, keep=folder)
    return folder


def _prune(root: Path, keep: Path) -> None:
    """Remove the folders of other states unused for ``KEEP_DAYS`` (another process may still
    load from one: it then compiles, as on a first run)."""
    old = time.time() - KEEP_DAYS * 86400
    for folder in root.iterdir():
        try:
            if folder != keep and folder.is_dir() and folder.stat().st_mtime < old:
                shutil.rmtree(folder, ignore_errors=True)
        except OSError:
            continue


def _ours(py_func) -> bool:
    """Whether ``py_func`` is one of vprscale's kernels (others keep numba's own ways)."""
    return (getattr(py_func, "__module__", "") or "").startswith("vprscale.")


class _StateLocator(caching._CacheLocator):
    """numba's cache locator for vprscale's kernels: the module's folder in this state's folder,
    stamped with the state (a kernel is valid while no kernel module changed)."""

    def __init__(self, py_func, folder: Path) -> None:
        self._path = folder / py_func.__module__
        self._lineno = py_func.__code__.co_firstlineno

    def get_cache_path(self) -> str:
        return str(self._path)

    def get_source_stamp(self) -> str:
        return state()

    def get_disambiguator(self) -> str:
        return str(self._lineno)

    @classmethod
    def from_function(cls, py_func, py_file):
        if not _ours(py_func):
            return None
        folder = state_folder()
        if folder is None:
            return None
        self = cls(py_func, folder)
        try:
            self.ensure_cache_path()
        except OSError:
            return None
        return self


def compile_lock(py_func) -> Path | None:
    """The lock file a process holds while it compiles the kernel ``py_func`` (None if it is not
    vprscale's or the state's folder cannot be written)."""
    if not _ours(py_func):
        return None
    folder = state_folder()
    if folder is None:
        return None
    return folder / py_func.__module__ / f"{py_func.__qualname__}-{py_func.__code__.co_firstlineno}.lock"


@contextmanager
def _held(path: Path, kernel: str) -> Iterator[None]:
    """``path`` locked for this process (``flock``), waited for up to ``WAIT_S`` (saying so,
    since the wait is a compilation's, seconds to a minute); past that, or where the file cannot
    be made or locked, the lock is not taken."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError:
        yield
        return
    try:
        deadline = time.monotonic() + WAIT_S
        waited = False
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if not waited:
                    log.info("  waiting for another process compiling the numba kernel %s", kernel)
                    waited = True
                if time.monotonic() > deadline:
                    break
                time.sleep(0.05)
            except OSError:  # a file system without locks
                break
        yield
    finally:
        os.close(fd)  # releases the lock


def _compile_once(compile: Callable) -> Callable:
    """numba's ``Dispatcher.compile``, which, for a signature of a vprscale kernel this process
    has not compiled or loaded yet, first holds the kernel's :func:`compile_lock`: numba then
    looks in the cache again, and finds what another process compiled while this one waited."""

    @functools.wraps(compile)
    def compile_locked(self: Dispatcher, sig):
        if tuple(sigutils.normalize_signature(sig)[0]) in self.overloads:
            return compile(self, sig)
        lock = compile_lock(self.py_func)
        if lock is None:
            return compile(self, sig)
        with global_compiler_lock, _held(lock, self.py_func.__qualname__):
            return compile(self, sig)

    compile_locked.vprscale_compile_once = True
    return compile_locked


def share_kernels() -> None:
    """Cache vprscale's kernels by state (:class:`_StateLocator`, numba's first choice) and
    compile each once per machine (:func:`_compile_once`): called by every module that defines
    kernels, before it defines them (numba picks a kernel's cache folder when it is decorated)."""
    if _StateLocator not in caching.CacheImpl._locator_classes:
        caching.CacheImpl._locator_classes.insert(0, _StateLocator)
    if not getattr(Dispatcher.compile, "vprscale_compile_once", False):
        Dispatcher.compile = _compile_once(Dispatcher.compile)
