"""Lifecycle of an output: lock, work in a hidden partial copy, publish atomically.

A build (or an index) writes into ``.<name>.partial`` beside its final path, records each
finished unit of work as a marker file, and only when everything is written sets
``complete`` and renames the partial copy into place. So a reader never finds an
incomplete output at the public path, a killed job resumes from its markers, and
``--force`` replaces an existing output only once the new one is whole.

On object storage (no rename, no lock) an output is written in place under its final prefix
and its manifest, written last, is what makes it complete (:class:`ObjectOutput`): every
reader refuses an output there without one, so a killed job never leaves something that
looks whole. Its key and done-markers are objects beside its files (``.job.json``,
``.done/``), so a re-run resumes from any client; what only the client needs (a pass's
checkpoint, the fitted FAS rows) lives in a local work folder under the cache.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from filelock import FileLock, Timeout

from vprscale.core import deadline
from vprscale.core.errors import InputError
from vprscale.core.manifest import FORMAT, NAME, write_manifest
from vprscale.core.objects import BOOKKEEPING, Remote, cache_root, check_bucket, storage_errors

NAME_BYTES = 255  # the longest file name POSIX filesystems take
MARKS = (".partial", ".sealed", ".lock", ".old", ".previous.999")  # what publishing adds to a name, at most


def check_name(path: Path) -> None:
    """Refuse an output whose name leaves no room for the files publishing puts beside it
    (``.<name>.partial``, ``.lock``, a kept copy's ``.previous.N``): they would fail midway,
    as a traceback, after the work."""
    longest = len(f".{path.name}".encode()) + max(len(m) for m in MARKS)
    if longest > NAME_BYTES:
        room = NAME_BYTES - 1 - max(len(m) for m in MARKS)
        raise InputError(f"{path}: the output's name is {len(path.name.encode())} bytes; at most {room} leave room "
                         "for the files written beside it (file names are at most 255 bytes)")


def _lock_file(path: Path) -> Path:
    """The lock of ``path``: ``.<name>.lock`` beside it, taken by :func:`exclusive` and :func:`shared`."""
    check_name(path)
    return path.with_name(f".{path.name}.lock")


@contextmanager
def exclusive(path: Path | Remote):
    """Hold an advisory lock for ``path``; a second holder is refused at once (kill -9 frees it).

    The lock is ``filelock``'s (``flock`` on ``.<name>.lock`` beside the output), taken
    without waiting: a scheduled job that finds its output busy should say so, not queue.
    Object storage has no lock to take: there, two jobs must not write one output at once.
    """
    if isinstance(path, Remote):
        yield
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    lock = FileLock(_lock_file(path), timeout=0, thread_local=False)
    try:
        lock.acquire()
    except Timeout:
        raise InputError(f"{path}: another vprscale job is writing this output, or reading it "
                         f"(lock {lock.lock_file})") from None
    try:
        yield
    finally:
        lock.release()


@contextmanager
def shared(path: Path | Remote):
    """Hold a shared lock for ``path``, which this job reads: any number of readers hold it at
    once (two evaluations of one index, into different outputs), and :func:`exclusive` (a
    job replacing ``path``: re-indexing) is refused while they do, as they are while it runs.

    The same file and primitive as :func:`exclusive` (``flock`` of ``.<name>.lock``; filelock
    never removes the file), in shared mode; closing the descriptor, or a kill, releases it.
    """
    if isinstance(path, Remote):  # no locks on object storage (see exclusive)
        yield
        return
    lock_file = _lock_file(path)
    fd = os.open(lock_file, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise InputError(f"{path}: another vprscale job is writing it (lock {lock_file})") from None
    try:
        yield
    finally:
        os.close(fd)


class PartialOutput:
    """The hidden work copy of an output directory, with its done-markers.

    Publishing is a sequence of idempotent steps with one commit point: when the work is
    whole, a seal file ``.<name>.sealed`` is written beside it (atomically); then the
    work copy's bookkeeping (``.work``, ``.done``, ``.job.json``) is removed, an older
    output is moved aside to ``.<name>.old``, the work copy is renamed to the final path,
    and the old output and the seal are removed. A job killed anywhere in that sequence
    leaves the seal, and the next run of the job (:meth:`recover`) finishes the sequence
    instead of starting over; a job killed before the seal resumes from its markers.
    """

    def __init__(self, final: Path, key: dict[str, Any]) -> None:
        check_name(final)
        self.final = final
        self.path = final.with_name(f".{final.name}.partial")
        self.key = json.loads(json.dumps(key, sort_keys=True, default=str))
        self._markers = self.path / ".done"
        self.sealed = final.with_name(f".{final.name}.sealed")
        self.old = final.with_name(f".{final.name}.old")

    def _check_links(self) -> None:
        """Refuse symbolic links where publishing renames and removes whole directories: following
        one would publish through it or remove what it points to."""
        for path in (self.final, self.path, self.sealed, self.old):
            if path.is_symlink():
                raise InputError(f"{path}: a symbolic link{' (dangling)' if not path.exists() else ''}; vprscale "
                                 "replaces whole outputs and does not follow links: give the real directory, or "
                                 "remove the link")

    def recover(self) -> bool:
        """Finish a publish that a killed run sealed; True if there was one (the output is then published)."""
        self._check_links()
        if not self.sealed.is_file():
            if self.old.exists() and self.final.exists():
                shutil.rmtree(self.old)  # an old output the last publish did not get to remove
            return False
        self._publish_steps()
        return True

    def open(self) -> bool:
        """Create the work copy, or keep it if it belongs to the same job; True if resumed."""
        self._check_links()
        key_file = self.path / ".job.json"
        if self._job_key(key_file) == self.key:
            return True
        if self.path.exists():
            shutil.rmtree(self.path)
        self._markers.mkdir(parents=True)
        tmp = key_file.with_name(".job.json.tmp")
        tmp.write_text(json.dumps(self.key, sort_keys=True, indent=1))
        tmp.replace(key_file)
        return False

    @staticmethod
    def _job_key(key_file: Path) -> Any:
        """The key of the job that owns a work copy; None if unreadable (a kill while it was written):
        the work copy is then started over, which is always safe."""
        try:
            return json.loads(key_file.read_text())
        except (OSError, ValueError):
            return None

    @property
    def work(self) -> Path:
        """The job's own folder (checkpoints of its passes), removed when the output is published."""
        work = self.path / ".work"
        work.mkdir(exist_ok=True)
        return work

    def write_text(self, name: str, text: str) -> None:
        (self.path / name).write_text(text)

    def done(self, unit: str) -> bool:
        return (self._markers / unit).exists()

    def mark(self, unit: str) -> None:
        tmp = self._markers / f".{unit}.tmp"
        tmp.write_text("")
        tmp.replace(self._markers / unit)
        deadline.progressed()

    def publish(self) -> None:
        """Seal the finished work copy, then move it to the final path, replacing an older output last.

        Before sealing, temporary files a killed writer left (``.*.tmp``) are removed and the
        manifest of every file is written (:mod:`vprscale.core.manifest`).
        """
        for leftover in self.path.rglob(".*.tmp"):
            if leftover.is_file():
                leftover.unlink()
        write_manifest(self.path)
        tmp = self.sealed.with_name(self.sealed.name + ".tmp")
        tmp.write_text(json.dumps(self.key, sort_keys=True))
        tmp.replace(self.sealed)
        self._publish_steps()

    def _publish_steps(self) -> None:
        if self.path.exists():
            for name in (".work", ".done"):
                shutil.rmtree(self.path / name, ignore_errors=True)
            (self.path / ".job.json").unlink(missing_ok=True)
            if self.final.exists():
                if self.old.exists():
                    shutil.rmtree(self.old)
                self.final.replace(self.old)
            self.path.replace(self.final)
        if self.old.exists():
            shutil.rmtree(self.old)
        self.sealed.unlink(missing_ok=True)


def keep_beside(path: Path, kept: Path | None = None) -> Path:
    """Move ``path`` aside, to ``kept`` (default ``<path>.previous``): what ``--force`` replaces is
    kept, not deleted; returns where it went. Nothing kept before is deleted either: a copy
    already at ``kept`` moves on to ``<kept>.1`` (then ``.2``, …: the higher, the later), so
    ``kept`` always holds the latest and a run of ``--force`` keeps every earlier copy. A kill
    between the two moves leaves both copies where a later ``--force`` still finds them."""
    kept = path.with_name(f"{path.name}.previous") if kept is None else kept
    if kept.exists():
        taken = [int(p.name.rpartition(".")[2]) for p in kept.parent.glob(f"{kept.name}.*")
                 if p.name.rpartition(".")[2].isdigit()]
        kept.rename(kept.with_name(f"{kept.name}.{max(taken, default=0) + 1}"))
    path.rename(kept)
    return kept


def check_file_output(out: Path, force: bool, flag: str = "--out") -> None:
    """Refuse, before any work, to write a single-file output over an existing file without
    ``force`` (or over a directory or a link at all): the file counterpart of an output folder's
    rules (:func:`publish_file` publishes it)."""
    if out.is_symlink() or out.is_dir():
        raise InputError(f"{flag} {out}: is a {'symbolic link' if out.is_symlink() else 'directory'}; give a "
                         "file name")
    if out.exists() and not force:
        raise InputError(f"{flag} {out}: exists; --force replaces it and keeps it beside, as {out.name}.previous")


def publish_file(tmp: Path, out: Path) -> None:
    """Put a finished file in place (``out`` whole or not at all), an existing one kept beside
    (``.previous``: what ``--force`` replaces is kept, as for folders)."""
    if out.exists():
        keep_beside(out)
    tmp.replace(out)


class ObjectOutput:
    """The lifecycle of one output on object storage; the same calls as
    :class:`~vprscale.core.publish.PartialOutput` (``open``, ``done``, ``mark``, ``publish``).

    ``path`` is the URL the work is written to: the output's own. An output there that is
    complete (its manifest present) is moved to ``<name>.previous`` before a new job starts
    writing (``--force``; a copy on the storage's side), as a local ``--force`` keeps it.
    """

    def __init__(self, final: Remote, key: dict[str, Any]) -> None:
        self.final = final
        self.path = final.url
        self.key = json.loads(json.dumps(key, sort_keys=True, default=str))
        self._done: set[str] = set()
        # the client's own part of the work, of this job only: another job's checkpoints are never read
        job = json.dumps({"url": final.url, "key": self.key}, sort_keys=True)
        self.work = cache_root() / "work" / hashlib.sha256(job.encode()).hexdigest()[:16]

    def recover(self) -> bool:
        """Remove bookkeeping a job killed after its manifest left behind. Publishing here has no
        later steps, so there is never a publish to finish: False. A prefix holding objects
        vprscale did not write is refused first (:func:`refuse_foreign`): nothing of it is touched."""
        refuse_foreign(self.final)
        if (self.final / NAME).exists():
            for name in BOOKKEEPING:
                (self.final / name.rstrip("/")).remove()
        return False

    def open(self) -> bool:
        """Resume the job if its key is the one stored beside the output; else start it over
        (an older complete output moved aside). True if resumed."""
        job = self.final / ".job.json"
        try:
            stored = json.loads(job.read_text()) if job.exists() else None
        except ValueError:
            stored = None
        if stored == self.key and not (self.final / NAME).exists():
            self._done = set((self.final / ".done").files())
            self.work.mkdir(parents=True, exist_ok=True)
            return True
        refuse_foreign(self.final)  # before anything is moved aside or removed
        if (self.final / NAME).exists():
            keep_remote_beside(self.final)
        clear_remote_output(self.final)
        shutil.rmtree(self.work, ignore_errors=True)
        self.work.mkdir(parents=True)
        job.write_text(json.dumps(self.key, sort_keys=True, indent=1))
        return False

    def done(self, unit: str) -> bool:
        return unit in self._done

    def mark(self, unit: str) -> None:
        (self.final / ".done" / unit).write_bytes(b"")
        self._done.add(unit)
        deadline.progressed()

    def write_text(self, name: str, text: str) -> None:
        (self.final / name).write_text(text)

    def publish(self) -> None:
        """Write the manifest (the commit point), then remove the job's bookkeeping."""
        write_manifest(self.final)
        self.recover()
        shutil.rmtree(self.work, ignore_errors=True)


def refuse_foreign(path: Remote) -> None:
    """Refuse, in one line, an output prefix that holds objects no vprscale job wrote (neither listed
    by a vprscale manifest nor a job's work in progress beside its key): they are someone's data,
    and vprscale replaces only its own outputs (a local output folder is refused alike). Another
    tool's ``manifest.json`` makes nothing vprscale's."""
    found = path.files()
    if not found:
        return
    foreign = list(found) if NAME not in found else _unlisted(path, list(found))
    if NAME not in found and ".job.json" in found:
        foreign = []  # a vprscale job's work in progress: its own files
    if foreign:
        some = ", ".join(sorted(foreign)[:3]) + (", …" if len(foreign) > 3 else "")
        raise InputError(f"{path}: holds {len(foreign):,} objects that are not a vprscale output ({some}); "
                         "vprscale removes none of them: give another --out, or remove them yourself")


def _unlisted(path: Remote, found: list[str]) -> list[str]:
    """The objects under ``path`` that its manifest does not list: all of them if the manifest is
    not a vprscale one (another tool's ``manifest.json``), none if it lists every object there."""
    try:
        manifest = json.loads((path / NAME).read_text())
        listed = manifest["files"] if manifest.get("format") == FORMAT else None
    except (ValueError, KeyError, TypeError, AttributeError):
        listed = None
    if not isinstance(listed, dict):
        return found
    return [name for name in found if name != NAME and name not in listed
            and not any(name == b.rstrip("/") or name.startswith(b) for b in BOOKKEEPING)]


def clear_remote_output(path: Remote) -> None:
    """Remove what an earlier vprscale job left under ``path`` (a job that did not finish, an
    output already kept beside) before a new one is written there: the one way vprscale empties a
    prefix, and never one that holds someone else's objects (:func:`refuse_foreign`)."""
    refuse_foreign(path)
    (path / NAME).remove()  # first: a reader finds no output, not a complete one losing its files
    path.remove()


def keep_remote_beside(path: Remote) -> Remote:
    """Copy a complete output to ``<name>.previous`` (an earlier copy there moves on to
    ``.previous.N``, as :func:`keep_beside` numbers them), then remove it."""
    kept = path.with_name(f"{path.name}.previous")
    if kept.exists():
        taken = [int(name.rpartition(".")[2]) for name in _siblings(kept) if name.rpartition(".")[2].isdigit()]
        moved = kept.with_name(f"{kept.name}.{max(taken, default=0) + 1}")
        kept.copy_to(moved)
        kept.remove()
    path.copy_to(kept)
    path.remove()
    return kept


def _siblings(path: Remote) -> list[str]:
    """Names beside ``path`` that start with its name and a dot."""
    with storage_errors(path.url):
        names = [n.rpartition("/")[2] for n in path.fs.ls(path.parent.path, detail=False)]
    return [n for n in names if n.startswith(f"{path.name}.")]


Output = PartialOutput | ObjectOutput  # an output being written, on a local disk or on object storage


def output_for(final: Path | Remote, key: dict[str, Any]) -> Output:
    """The lifecycle of an output: a work copy renamed into place on a local disk, written in
    place and completed by its manifest on object storage."""
    return ObjectOutput(final, key) if isinstance(final, Remote) else PartialOutput(final, key)


def check_writable(out: Path | Remote, flag: str = "--out") -> None:
    """Fail early, naming the directory, if outputs cannot be written there."""
    if isinstance(out, Remote):
        check_bucket(out, flag)
        return
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{flag} {out}: cannot create the output directory: {exc.strerror}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise InputError(f"{flag} {out}: the output directory is not writable")
