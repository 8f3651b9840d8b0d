"""Outputs and inputs on object storage (``s3://``, ``gs://``, ``az://``, ``memory://`` … any
fsspec scheme), and how an output is published there.

A local path keeps :mod:`vprscale.core.publish`'s lifecycle: a hidden work copy renamed into
place. Object storage has neither rename nor locks, so an output is written in place, under
its final prefix, and its manifest, written last, is what makes it complete: every reader
refuses an output on object storage without one (:func:`vprscale.core.manifest.check_manifest`),
so a killed job never leaves something that looks whole. The job's key and done-markers are
objects beside its files (``.job.json``, ``.done/``), so a re-run resumes from any client;
what only the client needs (a streamed pass's checkpoint, the fitted FAS rows) lives in a
local work folder under the cache (``$VPRSCALE_CACHE``), rebuilt if a new client lacks it.

Credentials are never handled here: each filesystem finds them as it always does (for S3 the
``AWS_*`` environment, ``~/.aws``, an instance role; ``AWS_ENDPOINT_URL`` for another
endpoint), and a URL is shown and recorded without user, password or query (:func:`public`).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import urllib.parse
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from vprscale.core.errors import InputError

SCHEME = re.compile(r"^([a-z][a-z0-9+.-]*)://", re.IGNORECASE)
BOOKKEEPING = (".job.json", ".done/", ".work/")
MANIFEST = "manifest.json"  # the name core.manifest writes; the commit point of an output here


def is_url(spec: str | os.PathLike | None) -> bool:
    """Whether an argument names a location by URL (``file://`` is a local path)."""
    if not isinstance(spec, str):
        return False
    m = SCHEME.match(spec)
    return bool(m) and m.group(1).lower() != "file"


def public(url: str) -> str:
    """``url`` as it may be shown or recorded: without user name, password, query or fragment."""
    parts = urllib.parse.urlsplit(url)
    host = parts.hostname or ""
    if parts.port:
        host = f"{host}:{parts.port}"
    return urllib.parse.urlunsplit((parts.scheme, host, parts.path, "", ""))


def location(spec: str | os.PathLike) -> Path | Remote:
    """Where an argument points: a :class:`Remote` for a URL, else a local path."""
    return Remote(spec) if is_url(spec) else Path(spec)


def zarr_url(where: Path | Remote) -> str:
    """How zarr opens a store there: its URL (zarr's fsspec store), or its absolute path
    (Dask workers may run in another directory)."""
    return where.url if isinstance(where, Remote) else str(Path(where).resolve())


def shown(where: Path | Remote) -> str:
    """How an output records where its input lives: an absolute path, or the URL as it may be shown."""
    return str(where) if isinstance(where, Remote) else str(Path(where).resolve())


def cache_root() -> Path:
    """Where vprscale keeps what it can always remake: ``$VPRSCALE_CACHE``, else ``~/.cache/vprscale``."""
    return Path(os.environ.get("VPRSCALE_CACHE", Path.home() / ".cache" / "vprscale"))


@contextmanager
def storage_errors(url: str) -> Iterator[None]:
    """Turn a filesystem's errors about ``url`` into one line (exit 2): a missing bucket or
    object, denied credentials, an endpoint that does not answer."""
    shown = public(url)
    try:
        yield
    except InputError:
        raise
    except FileNotFoundError as exc:
        raise InputError(f"{shown}: not found ({_first_line(exc)}); check the bucket and the path") from None
    except PermissionError as exc:
        raise InputError(f"{shown}: access denied ({_first_line(exc)}); the credentials come from the storage's "
                         "usual environment and configuration (for S3: AWS_* variables, ~/.aws)") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{shown}: the storage failed: {_first_line(exc)}") from None


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0][:200] if text else type(exc).__name__


class Remote:
    """A location on an fsspec filesystem: the filesystem (picklable: Dask workers reopen it
    with their own credentials) and a path on it; joined with ``/`` like a :class:`~pathlib.Path`."""

    def __init__(self, url: str, fs: Any = None, path: str | None = None) -> None:
        self.url = url.rstrip("/")
        if fs is None:
            import fsspec

            try:
                fs, path = fsspec.core.url_to_fs(self.url)
            except ImportError as exc:
                raise InputError(f"{public(url)}: this scheme needs a package vprscale does not install by default "
                                 f"({_first_line(exc)}); for S3: pip install 'vprscale[cloud]'") from None
            except ValueError as exc:
                raise InputError(f"{public(url)}: not a URL vprscale can open ({_first_line(exc)})") from None
        self.fs, self.path = fs, path.rstrip("/")

    def __truediv__(self, name: str) -> Remote:
        return Remote(f"{self.url}/{name}", self.fs, f"{self.path}/{name}")

    def __str__(self) -> str:
        return public(self.url)

    def __repr__(self) -> str:
        return f"Remote({public(self.url)!r})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Remote) and other.url == self.url

    def __hash__(self) -> int:
        return hash(self.url)

    @property
    def name(self) -> str:
        return self.url.rpartition("/")[2]

    @property
    def parent(self) -> Remote:
        return Remote(self.url.rpartition("/")[0], self.fs, self.path.rpartition("/")[0])

    def with_name(self, name: str) -> Remote:
        return self.parent / name

    def is_file(self) -> bool:
        with storage_errors(self.url):
            return self.fs.isfile(self.path)

    def exists(self) -> bool:
        with storage_errors(self.url):
            return self.fs.exists(self.path)

    def read_bytes(self) -> bytes:
        with storage_errors(self.url):
            return self.fs.cat_file(self.path)

    def read_text(self) -> str:
        return self.read_bytes().decode()

    def write_bytes(self, data: bytes) -> None:
        with storage_errors(self.url):
            self.fs.pipe_file(self.path, data)

    def write_text(self, text: str) -> None:
        self.write_bytes(text.encode())

    def open(self, mode: str = "rb") -> Any:
        with storage_errors(self.url):
            return self.fs.open(self.path, mode)

    def files(self) -> dict[str, int]:
        """Every object under this prefix: its name relative to it, and its size (one listing)."""
        self.fs.invalidate_cache(self.path)  # a listing cached before this job's writes would miss them
        with storage_errors(self.url):
            found = self.fs.find(self.path, detail=True)
        start = len(self.path) + 1
        return {name[start:]: int(info["size"]) for name, info in found.items()
                if info.get("type") != "directory" and name.startswith(self.path + "/")}

    def remove(self) -> None:
        """Remove every object under this prefix (nothing if there is none)."""
        with storage_errors(self.url):
            if self.fs.exists(self.path):
                self.fs.rm(self.path, recursive=True)

    def copy_to(self, other: Remote) -> None:
        """Copy every object under this prefix to ``other`` (server-side where the storage can)."""
        with storage_errors(self.url):
            for rel in self.files():
                self.fs.copy(f"{self.path}/{rel}", f"{other.path}/{rel}")


def check_bucket(root: Remote, flag: str) -> None:
    """Fail early, in one line, if outputs cannot be written under ``root``: write a probe object
    and remove it (a missing bucket, denied credentials or a read-only endpoint are then named
    before any work)."""
    probe = root / f".vprscale-probe-{os.getpid()}"
    try:
        with storage_errors(root.url):
            root.fs.pipe_file(probe.path, b"")
            root.fs.rm_file(probe.path)
    except InputError as exc:
        raise InputError(f"{flag} {exc}") from None


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
        self.work = cache_root() / "work" / hashlib.sha256(final.url.encode()).hexdigest()[:16]

    def recover(self) -> bool:
        """Remove bookkeeping a job killed after its manifest left behind. Publishing here has no
        later steps, so there is never a publish to finish: False."""
        if (self.final / MANIFEST).exists():
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
        if stored == self.key and not (self.final / MANIFEST).exists():
            self._done = set((self.final / ".done").files())
            self.work.mkdir(parents=True, exist_ok=True)
            return True
        if (self.final / MANIFEST).exists():
            keep_beside(self.final)
        self.final.remove()
        shutil.rmtree(self.work, ignore_errors=True)
        self.work.mkdir(parents=True)
        job.write_text(json.dumps(self.key, sort_keys=True, indent=1))
        return False

    def done(self, unit: str) -> bool:
        return unit in self._done

    def mark(self, unit: str) -> None:
        (self.final / ".done" / unit).write_bytes(b"")
        self._done.add(unit)

    def write_text(self, name: str, text: str) -> None:
        (self.final / name).write_text(text)

    def publish(self) -> None:
        """Write the manifest (the commit point), then remove the job's bookkeeping."""
        from vprscale.core.manifest import write_manifest

        write_manifest(self.final)
        self.recover()
        shutil.rmtree(self.work, ignore_errors=True)


def keep_beside(path: Remote) -> Remote:
    """Copy a complete output to ``<name>.previous`` (an earlier copy there moves on to
    ``.previous.N``, as :func:`vprscale.core.publish.keep_beside` numbers them), then remove it."""
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
