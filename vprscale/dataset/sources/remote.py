"""Descriptor files read where they live: a ``bin`` file (``.fbin``, ``.f16bin``, ``.u8bin``,
``.i8bin``), a vecs file (fvecs, bvecs), a ``.npy`` file or (on object storage) a prefix of chunk
or shard objects, their rows fetched by byte ranges as the build reads them, with no local
copy; HDF5 and Parquet files are read through :class:`RangedFile`, a file object over the same
ranges. Over http(s) through :mod:`vprscale.core.ranged` (each read checked to be exactly the
range asked, a dropped answer retried from where it stopped); over any other scheme (``s3://``,
``gs://`` …) through the storage's fsspec filesystem, each read checked the same way."""

from __future__ import annotations

import ast
import hashlib
import io
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
from vprscale.dataset.sources.base import RowSource, part_spans
from vprscale.dataset.sources.binfile import HEADER, bin_type, check_header
from vprscale.dataset.sources.chunks import check_numbering, natural_order
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
        self.parts = [Ranges(u) for u in remote_objects(url)]
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


class RangedFile(io.RawIOBase):
    """A read-only, seekable file object over a remote file's byte ranges (:class:`Ranges`), for
    libraries that read a file their own way (h5py, pyarrow's Parquet reader); wrap it in an
    ``io.BufferedReader`` so that small reads share one request."""

    def __init__(self, url: str) -> None:
        self.ranges = Ranges(url)
        self.size, self.version = self.ranges.probe()
        self._at = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._at

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        self._at = {io.SEEK_SET: 0, io.SEEK_CUR: self._at, io.SEEK_END: self.size}[whence] + offset
        return self._at

    def readinto(self, buffer: Any) -> int:
        stop = min(self.size, self._at + len(buffer))
        if stop <= self._at:
            return 0
        data = self.ranges.read(self._at, stop)
        buffer[: len(data)] = data
        self._at = stop
        return len(data)


def remote_file(url: str, buffer: int = 1 << 20) -> io.BufferedReader:
    """:class:`RangedFile` of ``url``, buffered (``buffer`` bytes a request at least)."""
    return io.BufferedReader(RangedFile(url), buffer_size=buffer)


def remote_fingerprint(url: str) -> dict[str, Any]:
    """How a store records a file read by URL: the URL shown, its size and version."""
    size, version = Ranges(url).probe()
    return {"url": public(url), "bytes": size, "version": version}


class RemoteNpySource(RowSource):
    """A 2-D ``.npy`` file at a URL, or on object storage a prefix of ``.npy`` shard objects read
    as one array in name order: each header parsed and checked once (2-D, C order, numbers, one
    width), rows read by range."""

    def __init__(self, url: str) -> None:
        self.name = public(url)
        self.parts = [Ranges(u) for u in remote_objects(url, ".npy")]
        self.sizes, self.versions, shapes, self.offsets, self.values = [], [], [], [], None
        for part in self.parts:
            size, version = part.probe()
            shape, values, offset = _npy_header(part, size)
            if self.values is not None and (values != self.values or shape[1] != shapes[0][1]):
                raise InputError(f"{part.name}: {shape[1]} columns of {values}, the shards before it "
                                 f"{shapes[0][1]} of {self.values}")
            self.values = values
            self.sizes.append(size)
            self.versions.append(version)
            shapes.append(shape)
            self.offsets.append(offset)
        self.dim = int(shapes[0][1])
        self.starts = np.concatenate([[0], np.cumsum([s[0] for s in shapes], dtype=np.int64)])
        self.n_rows = int(self.starts[-1])

    def _read(self, start: int, stop: int) -> np.ndarray:
        out = np.empty((stop - start, self.dim), np.float32)
        width = self.values.itemsize * self.dim
        for k, lo, hi in part_spans(self.starts, start, stop):
            data = self.parts[k].read(self.offsets[k] + width * lo, self.offsets[k] + width * hi)
            a = int(self.starts[k]) + lo - start
            out[a : a + hi - lo] = np.frombuffer(data, self.values).reshape(hi - lo, self.dim)
        return out

    def fingerprint(self) -> dict[str, Any]:
        return {"format": "npy", "rows": self.n_rows, "dim": self.dim, "urls": [p.name for p in self.parts],
                "bytes": self.sizes, "versions": self.versions}


def _npy_header(part: Ranges, size: int) -> tuple[tuple[int, int], np.dtype, int]:
    """``(shape, values, data offset)`` of a remote ``.npy``, checked against its size."""
    head = part.read(0, min(size, 12))
    if len(head) < 10 or head[:6] != b"\x93NUMPY":
        raise InputError(f"{part.name}: not a .npy file (no NUMPY magic)")
    wide = head[6] >= 2  # format 2 and 3: a 4-byte header length
    begin = 12 if wide else 10
    length = int.from_bytes(head[8:begin], "little")
    try:
        header = ast.literal_eval(part.read(begin, begin + length).decode("latin1"))
        values, shape, fortran = np.dtype(header["descr"]), tuple(header["shape"]), header["fortran_order"]
    except (ValueError, SyntaxError, KeyError, TypeError):
        raise InputError(f"{part.name}: a .npy header that cannot be read") from None
    if len(shape) != 2 or fortran or values.kind not in "fiu" or shape[1] == 0:
        raise InputError(f"{part.name}: a 2-D C-order array of numbers expected, not {shape} of {values}"
                         + (" in Fortran order" if fortran else ""))
    offset = begin + length
    if size != offset + values.itemsize * shape[0] * shape[1]:
        raise InputError(f"{part.name}: {size:,} bytes, but its header says {shape[0]:,} rows of {shape[1]} "
                         f"{values}: a truncated or foreign file")
    return (int(shape[0]), int(shape[1])), values, offset


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


def prefix_suffixes(url: str) -> set[str]:
    """The name endings (``.npy``, ``.parquet`` …) of the objects directly under ``url`` when it is
    a prefix on object storage (a folder); empty for a single object or an http(s) URL."""
    if HTTP.match(url):
        return set()
    remote = Remote(url)
    with storage_errors(url):
        if remote.fs.isfile(remote.path):
            return set()
        return {Path(rel).suffix for rel in remote.files() if "/" not in rel and not rel.startswith(".")}


def remote_objects(url: str, suffix: str = "") -> list[str]:
    """The object at ``url``, or (a prefix on object storage) the chunk objects under it whose
    names end in ``suffix``, in name order (with a suffix, numbers as numbers, as local shards)."""
    if HTTP.match(url):
        return [url]
    remote = Remote(url)
    with storage_errors(url):
        if remote.fs.isfile(remote.path):
            return [url]
        names = sorted((rel for rel in remote.files() if "/" not in rel and not rel.startswith(".")
                        and rel.endswith(suffix)), key=natural_order if suffix else None)  # vecs: as always
    if not names:
        kind = f"{suffix} object" if suffix else "fvecs object"
        raise InputError(f"{public(url)}: no {kind} there, nor chunk objects under it")
    check_numbering(public(url), names)
    return [f"{remote.url}/{n}" for n in names]
