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
removed when a new one is made (never through a link). numba unpickles what the cache holds, so
``<cache>/vprscale`` must be a folder only this user can write (:mod:`vprscale.core.private`);
where it is not, a process caches its kernels in a folder of its own, shared with nobody, and an
entry that cannot be read back is compiled again. ``$NUMBA_CACHE_LOCATOR_CLASSES`` overrides all
of this, as numba documents.

A kernel is compiled once per machine, not once per process: processes started together (Dask
workers, the stages of a pipeline, test workers) each miss the cache and would each compile the
same kernels, tens of seconds of CPU apiece. A process about to compile a kernel holds a lock
file beside its cache entry (``flock``: released by the kernel, whether its compilation ended or
failed, or by the end of the process however it ends); another process that needs the same
kernel waits, then finds it cached and loads it. Locks are taken under numba's own compiler lock,
one thread of a process at a time, and in the order kernels call each other (a kernel's lock
before its callees'), so two processes never wait on each other. A wait longer than
``WAIT_S``, or for a process that is stopped, compiles anyway; a signal that stops the process
ends its waits in every thread.
"""

from __future__ import annotations

import atexit
import fcntl
import functools
import hashlib
import logging
import os
import re
import shutil
import signal
import tempfile
import threading
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

from vprscale.core.errors import STOPPING, Interrupted
from vprscale.core.private import entries, private_folder

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
    """This state's folder (made, and marked used, once per process), or None if it cannot be
    written. It lies in ``<cache>/vprscale``, a folder only this user can write
    (:func:`~vprscale.core.private.private_folder`), since numba unpickles what it finds there;
    where that folder is a link, another user's or writable by others, the kernels are cached in
    a folder of this process's own, removed when it ends (compiled, not shared)."""
    cache_dir = Path(config.CACHE_DIR or AppDirs(appname="numba", appauthor=False).user_cache_dir)
    root = private_folder(cache_dir / "vprscale", "numba kernels are compiled by this process for itself")
    if root is None:
        return _own_folder()
    folder = root / state()
    try:
        made = not folder.is_dir()
        folder.mkdir(exist_ok=True)
        os.utime(folder)
    except OSError:
        return None
    if made:
        _prune(root, keep=folder)
    return folder


def _own_folder() -> Path | None:
    """A kernel cache for this process alone (mode 0700), removed at its end."""
    try:
        folder = Path(tempfile.mkdtemp(prefix="vprscale-kernels-"))
    except OSError:
        return None
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    return folder


def _prune(root: Path, keep: Path) -> None:
    """Remove the folders of other states unused for ``KEEP_DAYS`` (another process may still
    load from one: it then compiles, as on a first run). Only real folders of ``root`` are
    looked at; a link is never followed, so nothing outside the cache is removed."""
    old = time.time() - KEEP_DAYS * 86400
    for folder in entries(root):
        try:
            if folder != keep and folder.lstat().st_mtime < old:
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
    """``path`` locked for this process (``flock``, the holder's pid written in it), waited for up
    to ``WAIT_S`` (saying so, since the wait is a compilation's, seconds to a minute). The wait ends
    early, and the lock is not taken, where the holder is stopped (Ctrl-Z, a suspended batch job:
    it would hold the lock for as long as it stays stopped) or the file cannot be made or locked;
    it ends with :class:`Interrupted` once a signal asked this process to stop, whichever thread
    waits, or when the main thread has ended."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
    except OSError:
        yield
        return
    try:
        deadline = time.monotonic() + WAIT_S
        waited = 0
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                os.ftruncate(fd, 0)
                os.pwrite(fd, str(os.getpid()).encode(), 0)
                break
            except BlockingIOError:
                if STOPPING.is_set() or not threading.main_thread().is_alive():
                    raise Interrupted(signal.SIGTERM) from None
                if not waited:
                    log.info("  waiting for another process compiling the numba kernel %s", kernel)
                if waited % 20 == 0 and _stopped(fd):  # once a second
                    log.info("  the process compiling the numba kernel %s is stopped: compiling it here", kernel)
                    break
                waited += 1
                if time.monotonic() > deadline:
                    break
                time.sleep(0.05)
            except OSError:  # a file system without locks
                break
        yield
    finally:
        os.close(fd)  # releases the lock


def _stopped(fd: int) -> bool:
    """Whether the process whose pid the lock file ``fd`` holds is stopped (state T or t)."""
    try:
        pid = int(os.pread(fd, 32, 0) or b"0")
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rpartition(b")")[2].split()[0] in (b"T", b"t")
    except (OSError, ValueError, IndexError):
        return False


def _load_or_none(load: Callable) -> Callable:
    """numba's ``Cache.load_overload``, which, for a vprscale kernel whose cache entry cannot be
    read (a disk that filled while numba wrote it, a file cut short), says so, removes the entry's
    index and returns None: numba compiles the kernel and caches it again."""

    @functools.wraps(load)
    def load_checked(self: caching.Cache, sig, target_context):
        try:
            return load(self, sig, target_context)
        except Exception as exc:  # noqa: BLE001 - numba unpickles: any error means a damaged entry
            if not _ours(self._py_func):
                raise
            index = Path(self._cache_file._index_path)
            why = str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__
            log.warning("the cached numba kernel %s cannot be read (%s): compiling it again",
                        self._py_func.__qualname__, why)
            index.unlink(missing_ok=True)
            return None

    load_checked.vprscale_checked = True
    return load_checked


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
    """Cache vprscale's kernels by state (:class:`_StateLocator`, numba's first choice), compile
    each once per machine (:func:`_compile_once`) and compile again what the cache cannot give
    back (:func:`_load_or_none`): called by every module that defines
    kernels, before it defines them (numba picks a kernel's cache folder when it is decorated)."""
    if _StateLocator not in caching.CacheImpl._locator_classes:
        caching.CacheImpl._locator_classes.insert(0, _StateLocator)
    if not getattr(Dispatcher.compile, "vprscale_compile_once", False):
        Dispatcher.compile = _compile_once(Dispatcher.compile)
    if not getattr(caching.Cache.load_overload, "vprscale_checked", False):
        caching.Cache.load_overload = _load_or_none(caching.Cache.load_overload)
