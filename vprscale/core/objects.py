"""Outputs and inputs on object storage (``s3://``, ``gs://``, ``az://``, ``memory://`` … any
fsspec scheme), named by URL.

How an output is published there (in place, completed by its manifest written last) is
:class:`vprscale.core.publish.ObjectOutput`'s; this module is the location itself: a
:class:`Remote` path on an fsspec filesystem, the errors of a storage as one line each, and
where the client keeps what it can always remake (:func:`cache_root`).

Credentials are never handled here: each filesystem finds them as it always does (for S3 the
``AWS_*`` environment, ``~/.aws``, an instance role; ``AWS_ENDPOINT_URL`` for another
endpoint), and a URL is shown and recorded without user, password or query (:func:`public`).
"""

from __future__ import annotations

import os
import re
import urllib.parse
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from vprscale.core.errors import InputError, raised_by

SCHEME = re.compile(r"^([a-z][a-z0-9+.-]*)://", re.IGNORECASE)
BOOKKEEPING = (".job.json", ".done/", ".work/")
CLIENTS = ("botocore", "aiobotocore", "s3fs", "gcsfs", "google", "adlfs", "azure", "aiohttp")  # storage clients


def is_url(spec: str | os.PathLike | None) -> bool:
    """Whether an argument names a location by URL (``file://`` is a local path)."""
    if not isinstance(spec, str):
        return False
    m = SCHEME.match(spec)
    return bool(m) and m.group(1).lower() != "file"


def public(url: str) -> str:
    """``url`` as it may be shown or recorded: without user name, password or query (a presigned
    URL's signature), nor, over http(s), the fragment; on object storage a ``#`` is part of a key's
    name, and is kept."""
    try:
        parts = urllib.parse.urlsplit(url)
    except ValueError:  # not even a URL (an unbalanced IPv6 bracket): its scheme alone
        return url.partition("://")[0] + "://…"
    host = parts.netloc.rpartition("@")[2]  # as written (a bad port too: named, not raised), without user:password
    fragment = "" if parts.scheme.lower() in ("http", "https") else parts.fragment
    return urllib.parse.urlunsplit((parts.scheme, host, parts.path, "", fragment))


def redact(value: Any) -> Any:
    """``value`` as it may be shown or recorded (a command line's arguments, a stage's parameters,
    a summary): every URL in it, whole or after a ``=`` (``--deep1b=URL``, ``night=URL``), as
    :func:`public` shows it (no user name, password or query); lists and mappings item by item."""
    if isinstance(value, dict):
        return {k: redact(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [redact(v) for v in value]
    if not isinstance(value, str):
        return value
    if is_url(value):
        return public(value)
    head, eq, tail = value.partition("=")
    return f"{head}={public(tail)}" if eq and is_url(tail) else value


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
    except Exception as exc:
        if not storage_failure(exc):
            raise
        # the storage client's own errors: an endpoint that does not answer, a bad region or configuration
        raise InputError(f"{shown}: the storage failed: {_first_line(exc)}") from None


def storage_failure(exc: BaseException) -> bool:
    """Whether an error came from a storage client (raised by it, or by fsspec translating one of
    its errors): the storage's failure (an endpoint gone, a connection dropped), not vprscale's."""
    return raised_by(exc, CLIENTS)


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

    @property
    def name(self) -> str:
        return self.url.rpartition("/")[2]

    @property
    def parent(self) -> Remote:
        return Remote(self.url.rpartition("/")[0], self.fs, self.path.rpartition("/")[0])

    def with_name(self, name: str) -> Remote:
        return self.parent / name

    def _fresh(self) -> None:
        """Forget what the filesystem listed of this place before: another process (a Dask worker,
        the job's own earlier run) may have written it since, and a cached listing would hide that."""
        self.fs.invalidate_cache(self.path)

    def _info(self) -> dict[str, Any] | None:
        """What the storage says of this place; None where nothing is there. Asked of ``info``, not
        of ``isfile``/``exists``, which answer False for a denied request or a dead endpoint too:
        those are the storage's failures, one line each (:func:`storage_errors`), never "not there"."""
        self._fresh()
        with storage_errors(self.url):
            try:
                return self.fs.info(self.path)
            except FileNotFoundError:
                return None

    def is_file(self) -> bool:
        info = self._info()
        return info is not None and info.get("type") == "file"

    def exists(self) -> bool:
        return self._info() is not None

    def read_bytes(self) -> bytes:
        self._fresh()
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
        self._fresh()
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
