"""Parallel ranged HTTP downloads of the first bytes of a remote file, resumable and checked.

A billion-row source is hundreds of GB, and a scale needs only its first rows: so a download
asks for exactly the byte ranges it needs (``Range: bytes=a-b``), several at once, each written
where it belongs in a hidden work file beside the output. Every finished part is recorded with
its CRC32C; a killed run, or one whose connection dropped, starts again from the record, keeps
the parts whose bytes still check out and fetches the rest. Nothing is trusted blindly: a part
must come back as ``206 Partial Content`` for exactly the range asked (a server that ignores
ranges, or lies about lengths, is an error naming the URL), an answer cut short is retried
from where it stopped, and one that trickles in slower than ``MIN_RATE`` is cut off and retried
(a per-read timeout alone lets a server that sends a byte a second hold a job forever). Every
answer must carry the validator (ETag, else Last-Modified) the file had when it was first asked
for, so the bytes of two versions of a file are never stitched together; a server that names no
version is refused, since nothing could tell two versions apart. What a URL carries
besides its address (a user name, a password, a signed query string) is never logged or
recorded (:func:`public`), and its credentials are never sent to another origin that a
redirect names.
"""

from __future__ import annotations

import base64
import http.client
import json
import logging
import os
import socket
import time
import urllib.error
import urllib.parse
import urllib.request
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import google_crc32c

from vprscale.core.errors import InputError
from vprscale.core.objects import public
from vprscale.core.progress import ChunkProgress

log = logging.getLogger(__name__)

PART_BYTES = 64 << 20  # one request's range, and the unit a resumed run keeps or fetches again
BLOCK = 1 << 20  # bytes read from a response at a time
RETRIES = 5  # attempts a part gets before the run stops (resumable) with one line
TIMEOUT_S = 30.0  # a connection silent this long counts as dropped
BACKOFF_S = 0.5  # the first retry's pause; doubled for each further one
MIN_RATE = 64 << 10  # bytes a second an answer must average (after TIMEOUT_S of grace), else it counts as dropped


class Dropped(OSError):
    """A transfer that stopped before its range was whole (retried; resumable)."""


def _origin(url: str) -> tuple[str, str, int | None]:
    parts = urllib.parse.urlsplit(url)
    return parts.scheme.lower(), (parts.hostname or "").lower(), parts.port


class _SameOriginAuth(urllib.request.HTTPRedirectHandler):
    """Follows a redirect with the URL's credentials only where it stays on their origin (scheme,
    host and port): a mirror that redirects elsewhere (a CDN, anyone) never receives them."""

    def redirect_request(self, req, fp, code, msg, headers, newurl):
        new = super().redirect_request(req, fp, code, msg, headers, newurl)
        if new is not None and _origin(newurl) != _origin(req.full_url):
            new.remove_header("Authorization")
        return new


_OPENER = urllib.request.build_opener(_SameOriginAuth)


def _validator(resp: http.client.HTTPResponse) -> str:
    """What names the version of the file an answer came from: its ETag, else its Last-Modified."""
    return resp.headers.get("ETag") or resp.headers.get("Last-Modified") or ""


def _request(url: str, start: int, stop: int) -> urllib.request.Request:
    """A range request; a user name and password in the URL (a mirror's) become Basic authorisation."""
    try:
        parts = urllib.parse.urlsplit(url)
        parts.port  # noqa: B018 - raises for a port out of range
    except ValueError as exc:
        raise InputError(f"{public(url)}: not a URL that can be fetched ({exc})") from None
    if not parts.hostname:
        raise InputError(f"{public(url)}: names no host")
    headers = {"Range": f"bytes={start}-{stop - 1}", "User-Agent": "vprscale", "Accept-Encoding": "identity"}
    if parts.username is not None:
        pair = f"{urllib.parse.unquote(parts.username)}:{urllib.parse.unquote(parts.password or '')}"
        headers["Authorization"] = "Basic " + base64.b64encode(pair.encode()).decode()
        url = urllib.parse.urlunsplit((parts.scheme, public(url).split("://", 1)[1].split("/", 1)[0], parts.path,
                                       parts.query, ""))
    return urllib.request.Request(url, headers=headers)


def _open(url: str, start: int, stop: int, version: str = "") -> http.client.HTTPResponse:
    """The response to ``GET`` bytes ``[start, stop)``, checked to be exactly that range of the
    file's version ``version`` (where the server names versions)."""
    try:
        resp = _OPENER.open(_request(url, start, stop), timeout=TIMEOUT_S)
    except urllib.error.HTTPError as exc:
        if exc.code == 416:
            raise InputError(f"{public(url)}: the server has no bytes {start:,}-{stop - 1:,} (the file is shorter "
                             "than its header says)") from None
        if exc.code in (401, 403):
            raise InputError(f"{public(url)}: access denied (HTTP {exc.code}); check the URL and its credentials") \
                from None
        if exc.code == 404:
            raise InputError(f"{public(url)}: not found (HTTP 404)") from None
        if exc.code >= 500:
            raise Dropped(f"HTTP {exc.code}") from None
        raise InputError(f"{public(url)}: HTTP {exc.code} {exc.reason}") from None
    except (urllib.error.URLError, TimeoutError, ConnectionError, http.client.HTTPException) as exc:
        reason = getattr(exc, "reason", exc)
        if isinstance(reason, ConnectionRefusedError | socket.gaierror) or (
                isinstance(reason, OSError) and not isinstance(reason, TimeoutError | ConnectionError)):
            raise InputError(f"{public(url)}: cannot connect ({getattr(reason, 'strerror', None) or reason})") \
                from None
        raise Dropped(str(reason)) from None
    if resp.status != 206:
        resp.close()
        raise InputError(f"{public(url)}: the server ignores byte ranges (HTTP {resp.status} for a range request); "
                         "vprscale fetches only the bytes it needs: use a server or mirror that serves ranges")
    want = f"bytes {start}-{stop - 1}/"
    got = resp.headers.get("Content-Range", "")
    length = resp.headers.get("Content-Length")
    if not got.startswith(want) or (length is not None and int(length) != stop - start):
        resp.close()
        raise InputError(f"{public(url)}: asked for bytes {start:,}-{stop - 1:,}, the server answered "
                         f"{got or 'no Content-Range'} with {length or 'no'} Content-Length")
    if version and _validator(resp) != version:
        resp.close()
        raise InputError(f"{public(url)}: the file changed while it was read (it was {version}, now "
                         f"{_validator(resp) or 'unnamed'}); run the command again: it starts over from the new file")
    return resp


def probe(url: str) -> tuple[int, str]:
    """``(size, version)`` of the remote file: its size from the ``Content-Range`` of a one-byte
    range request, its version from the ``ETag`` (else ``Last-Modified``) the server gives, so that
    a resumed download never mixes the bytes of two versions of a file."""
    try:
        with _open(url, 0, 1) as resp:
            total = resp.headers["Content-Range"].rpartition("/")[2]
            version = _validator(resp)
            resp.read()
    except Dropped as exc:
        raise InputError(f"{public(url)}: no answer ({exc}); check the URL and the network") from None
    if not total.isdigit():
        raise InputError(f"{public(url)}: the server does not say the file's size (Content-Range {total!r})")
    if not version:
        raise InputError(f"{public(url)}: the server names no version of the file (no ETag, no Last-Modified), so "
                         "bytes read at different times could come from two versions of it, undetected; serve it "
                         "from a server that does (any web server or object store), or copy the file here first")
    return int(total), version


def read_range(url: str, start: int, stop: int, version: str = "") -> bytes:
    """Bytes ``[start, stop)`` of a remote file (a header, a small file), retried as a part is, of
    its version ``version`` (:func:`probe`'s) where given."""
    buf = bytearray(stop - start)
    try:
        _fetch_into(url, start, stop, lambda at, data: buf.__setitem__(slice(at - start, at - start + len(data)),
                                                                        data), version)
    except Dropped as exc:
        raise InputError(f"{exc}; check the URL and the network") from None
    return bytes(buf)


def _fetch_into(url: str, start: int, stop: int, write, version: str = "") -> None:
    """Bytes ``[start, stop)`` handed to ``write(offset, data)`` as they arrive; a dropped
    connection, or an answer slower than ``MIN_RATE``, is retried from the first byte not yet
    written."""
    at, failures = start, 0
    while at < stop:
        try:
            with _open(url, at, stop, version) as resp:
                deadline = time.monotonic() + TIMEOUT_S + (stop - at) / MIN_RATE
                while at < stop:
                    data = resp.read1(min(BLOCK, stop - at))
                    if not data:
                        raise Dropped(f"the answer stopped at byte {at:,} of {start:,}-{stop - 1:,}")
                    write(at, data)
                    at += len(data)
                    if at < stop and time.monotonic() > deadline:
                        raise Dropped(f"the answer came slower than {MIN_RATE >> 10} KiB/s")
                if resp.read(1):
                    raise InputError(f"{public(url)}: the server sent more than bytes {start:,}-{stop - 1:,}")
        except (Dropped, ConnectionError, TimeoutError, http.client.HTTPException) as exc:
            failures += 1
            if failures > RETRIES:
                raise Dropped(f"{public(url)}: bytes {at:,}-{stop - 1:,}: {exc} ({RETRIES} retries)") from None
            time.sleep(BACKOFF_S * 2 ** (failures - 1))


@dataclass
class Plan:
    """What :func:`download` writes: the first ``size`` bytes of ``url`` into ``out``."""

    url: str
    out: Path
    size: int
    version: str = ""  # the remote file's ETag or Last-Modified (:func:`probe`)


def _crc(data: bytes | memoryview) -> str:
    return google_crc32c.Checksum(bytes(data)).hexdigest().decode()


def download(plan: Plan, connections: int = 4, quiet: bool = False) -> Path:
    """Fetch ``plan`` into ``<out>`` (whole, or not at all: a hidden ``.<name>.partial`` and its
    record of finished parts ``.<name>.parts.json`` until every byte is there), ``connections``
    parts at a time; a second run resumes, keeping the recorded parts whose CRC32C still matches."""
    out = plan.out
    work = out.with_name(f".{out.name}.partial")
    record_file = out.with_name(f".{out.name}.parts.json")
    parts = [(a, min(plan.size, a + PART_BYTES)) for a in range(0, plan.size, PART_BYTES)]
    for path in (work, record_file, out):
        if path.is_symlink():
            raise InputError(f"{path}: a symbolic link; a download writes and publishes only files of its own: "
                             "remove the link")
    done = _kept_parts(work, record_file, plan)
    fd = os.open(work, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
    try:
        os.ftruncate(fd, plan.size)
        todo = [p for p in parts if str(p[0]) not in done]
        if done and not quiet:
            log.info(f"… resuming {out.name}: {len(parts) - len(todo)} of {len(parts)} parts kept (checked)")
        got = plan.size - sum(b - a for a, b in todo)
        progress = None if quiet else ChunkProgress(f"fetch {out.name}", max(1, plan.size >> 20), done=got >> 20,
                                                    unit="MiB")

        def one(part: tuple[int, int]) -> tuple[int, str]:
            a, b = part
            crc = google_crc32c.Checksum()

            def write(at: int, data: bytes) -> None:
                os.pwrite(fd, data, at)

            _fetch_into(plan.url, a, b, write, plan.version)
            crc.update(os.pread(fd, b - a, a))  # what is on disk, not what was sent
            return a, crc.hexdigest().decode()

        with ThreadPoolExecutor(max(1, connections)) as pool:
            futures = [pool.submit(one, p) for p in todo]
            try:
                for future in as_completed(futures):
                    a, crc = future.result()
                    done[str(a)] = crc
                    _save(record_file, plan, done)
                    before, got = got, got + min(plan.size, a + PART_BYTES) - a
                    if progress:
                        progress.update((got >> 20) - (before >> 20))
            except BaseException:
                for f in futures:
                    f.cancel()
                raise
        os.fsync(fd)
    except Dropped as exc:
        raise InputError(f"{exc}; the parts already fetched are kept: run the same command again to resume") \
            from None
    finally:
        os.close(fd)
    return work


def _kept_parts(work: Path, record_file: Path, plan: Plan) -> dict[str, str]:
    """The parts a previous run finished, each checked against its CRC32C (a part whose bytes
    changed, or a record of another download, is fetched again)."""
    try:
        record = json.loads(record_file.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(record, dict) or record.get("url") != public(plan.url) or record.get("size") != plan.size \
            or record.get("version", "") != plan.version or not work.is_file():
        return {}  # another download, or the remote file changed since: started over
    kept = {}
    with open(work, "rb") as fh:
        for a, crc in (record.get("parts") or {}).items():
            start = int(a)
            fh.seek(start)
            if _crc(fh.read(min(plan.size, start + PART_BYTES) - start)) == crc:
                kept[a] = crc
    return kept


def _save(record_file: Path, plan: Plan, done: dict[str, str]) -> None:
    tmp = record_file.with_name(record_file.name + ".tmp")
    tmp.write_text(json.dumps({"url": public(plan.url), "size": plan.size, "version": plan.version,
                               "part_bytes": PART_BYTES, "parts": done}, sort_keys=True))
    tmp.replace(record_file)


def finish(plan: Plan, work: Path, out: Path | None = None) -> None:
    """Publish a finished download: its work file (or what was made of it) renamed into place, at
    ``out`` (default: the plan's), its record of parts removed."""
    work.replace(out or plan.out)
    plan.out.with_name(f".{plan.out.name}.parts.json").unlink(missing_ok=True)
