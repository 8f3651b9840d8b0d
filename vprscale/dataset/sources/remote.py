"""Descriptor files read where they live: a ``bin`` file (``.fbin``, ``.f16bin``, ``.u8bin``,
``.i8bin``), a vecs file (fvecs, bvecs) or (on object storage) a prefix of chunk objects, their
rows fetched by byte ranges as the build reads them, with no local
copy. Over http(s) through :mod:`vprscale.core.ranged` (each read checked to be exactly the
range asked, a dropped answer retried from where it stopped); over any other scheme (``s3://``,
``gs://`` …) through the storage's fsspec filesystem, each read checked the same way."""

from __future__ import annotations

import hashlib
import os
import re
import struct
import threading
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.errors import InputError
from vprscale.core.objects import Remote, cache_root, public, storage_errors
from vprscale.core.progress import ChunkProgress
from vprscale.core.ranged import probe, read_range
from vprscale.dataset.sources.base import RowSource
from vprscale.dataset.sources.binfile import HEADER, bin_type, check_header
from vprscale.dataset.sources.fvecs import read_vecs, record_bytes, vecs_type

HTTP = re.compile(r"^https?://", re.IGNORECASE)
PART = 64 << 20  # bytes a request of a whole-file fetch asks for


class Ranges:
    """Byte ranges of one remote file; holds its URL (and, off HTTP, its picklable filesystem), so
    tasks in other processes or on other machines read for themselves. Once probed, every HTTP
    read must come from the version of the file the probe saw."""

    def __init__(self, url: str) -> None:
        self.url, self.name = url, public(url)
        self._remote = None if HTTP.match(url) else Remote(url)
        self._version = ""  # the HTTP validator reads are held to, from probe()

    def read(self, start: int, stop: int) -> bytes:
        if self._remote is None:
            return read_range(self.url, start, stop, self._version)
        with storage_errors(self.url):
            data = self._remote.fs.cat_file(self._remote.path, start=start, end=stop)
        if len(data) != stop - start:
            raise InputError(f"{self.name}: bytes {start:,}–{stop - 1:,} asked, {len(data):,} came: the object is "
                             "shorter than it was (changed while read?)")
        return data

    def probe(self) -> tuple[int, str | None]:
        """The file's size and its version (an HTTP validator, an object's ETag)."""
        if self._remote is None:
            size, self._version = probe(self.url)
            return size, self._version
        with storage_errors(self.url):
            info = self._remote.fs.info(self._remote.path)
        if info.get("type") == "directory":
            raise InputError(f"{self.name}: a folder, not a file")
        version = info.get("ETag") or info.get("etag") or info.get("LastModified") or info.get("mtime")
        return int(info["size"]), None if version is None else str(version)


class RemoteBinSource(RowSource):
    """A ``bin`` file at a URL: its header and size checked once, its rows read by range.

    Shown, and fingerprinted, without credentials or query string."""

    def __init__(self, url: str) -> None:
        self.ranges = Ranges(url)
        self.name = self.ranges.name
        self.values = bin_type(self.name)
        if self.values is None:
            raise InputError(f"{self.name}: not a bin file (.fbin, .f16bin, .u8bin, .i8bin or .ibin)")
        size, self.version = self.ranges.probe()
        n, d = struct.unpack("<II", self.ranges.read(0, HEADER))
        check_header(self.name, n, d, self.values, size)
        self.n_rows, self.dim, self.bytes = n, d, size

    def _read(self, start: int, stop: int) -> np.ndarray:
        if stop == start:
            return np.empty((0, self.dim), np.float32)
        width = self.values.itemsize * self.dim
        data = self.ranges.read(HEADER + width * start, HEADER + width * stop)
        return np.frombuffer(data, self.values).reshape(stop - start, self.dim).astype(np.float32)

    def fingerprint(self) -> dict[str, Any]:
        return {"format": self.name.rpartition(".")[2], "rows": self.n_rows, "dim": self.dim, "url": self.name,
                "bytes": self.bytes, "version": self.version}


class RemoteFvecsSource(RowSource):
    """An fvecs (or bvecs) file at a URL, or on object storage a prefix of such chunk objects
    (``base/base_00`` …) read as one array in name order: every object's size and first record
    checked once, rows read by range and every record's dimension checked as it arrives."""

    def __init__(self, url: str) -> None:
        self.name = public(url)
        self.parts = [Ranges(u) for u in _objects(url)]
        sizes, versions = zip(*(p.probe() for p in self.parts), strict=True)
        self.form, self.values = vecs_type(self.parts[0].name.split("?", 1)[0])
        self.dim = _first_dim(self.parts[0])
        record = record_bytes(self.dim, self.values)
        for part, size in zip(self.parts, sizes, strict=True):
            if size % record:
                raise InputError(f"{part.name}: size {size:,} is not a multiple of the record size {record} "
                                 f"(d = {self.dim}); the record at offset {size - size % record:,} is truncated")
            if size and _first_dim(part) != self.dim:
                raise InputError(f"{part.name}: offset 0: record dimension {_first_dim(part)}, expected {self.dim}")
        self.sizes, self.versions = list(sizes), list(versions)
        self.starts = np.concatenate([[0], np.cumsum([s // record for s in sizes], dtype=np.int64)])
        self.n_rows = int(self.starts[-1])

    def _read(self, start: int, stop: int) -> np.ndarray:
        record = record_bytes(self.dim, self.values)

        def records(i: int, lo: int, hi: int) -> np.ndarray:
            return np.frombuffer(self.parts[i].read(lo * record, hi * record), "u1").reshape(hi - lo, record)

        return read_vecs(self.starts, self.dim, self.values, start, stop, records, lambda i: self.parts[i].name)

    def fingerprint(self) -> dict[str, Any]:
        return {"format": self.form, "rows": self.n_rows, "dim": self.dim,
                "urls": [p.name for p in self.parts], "bytes": self.sizes, "versions": self.versions}


def fetched_copy(url: str, quiet: bool = False) -> tuple[Path, dict[str, Any]]:
    """A source read whole several times (FAS100K's ``.npz``: every FAS PCA pass) fetched once
    into the cache, ``$VPRSCALE_CACHE/sources/<digest of URL, size and version>/<name>``, and its
    fingerprint as a store records it: the URL shown, size, version and sampled hash, none of
    which change when the cache is cleared and the file fetched again."""
    from vprscale.dataset.sources.fingerprint import file_fingerprint

    ranges = Ranges(url)
    size, version = ranges.probe()
    key = hashlib.sha256(f"{ranges.name}|{size}|{version}".encode()).hexdigest()[:16]
    target = cache_root() / "sources" / key / (ranges.name.rpartition("/")[2] or "source")
    if not (target.is_file() and target.stat().st_size == size and (version or _same_ends(ranges, target))):
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f".{target.name}.{os.getpid()}.{threading.get_ident()}.tmp")  # tasks fetch at once
        bar = None if quiet else ChunkProgress(f"fetch {ranges.name}", -(-size // PART), unit="parts")
        try:
            with open(tmp, "wb") as fh:
                for a in range(0, size, PART):
                    fh.write(ranges.read(a, min(size, a + PART)))
                    if bar:
                        bar.update(1)
            tmp.replace(target)
        finally:
            tmp.unlink(missing_ok=True)
    sampled = file_fingerprint(target)["sha256_head_tail"]
    return target, {"url": ranges.name, "bytes": size, "version": version, "sha256_head_tail": sampled}


def _same_ends(ranges: Ranges, copy: Path, sample: int = 1 << 20) -> bool:
    """Whether a cached copy still holds the remote file's first and last ``sample`` bytes: where
    the server names no version (no ETag, no Last-Modified), what the cache may be trusted on (a
    zip's, an ``.npz``'s, last bytes hold every member's CRC32)."""
    size = copy.stat().st_size
    with open(copy, "rb") as fh:
        head = fh.read(min(sample, size))
        fh.seek(max(0, size - sample))
        tail = fh.read()
    return ranges.read(0, len(head)) == head and ranges.read(size - len(tail), size) == tail


def _first_dim(part: Ranges) -> int:
    d = struct.unpack("<i", part.read(0, 4))[0]
    if not 0 < d <= 1 << 16:
        raise InputError(f"{part.name}: offset 0: implausible record dimension {d}")
    return d


def _objects(url: str) -> list[str]:
    """The fvecs object at ``url``, or the chunk objects under it (a prefix on object storage)."""
    if HTTP.match(url):
        return [url]
    remote = Remote(url)
    with storage_errors(url):
        if remote.fs.isfile(remote.path):
            return [url]
        names = sorted(rel for rel in remote.files() if "/" not in rel and not rel.startswith("."))
    if not names:
        raise InputError(f"{public(url)}: no fvecs object there, nor chunk objects under it")
    return [f"{remote.url}/{n}" for n in names]
