"""Reader of the FAS100K traverse pair (docs/dataset.md): one ``.npz`` holding NetVLAD descriptors.

``arr_0`` reference descriptors, ``arr_1`` query descriptors, ``arr_2`` the ground-truth
reference index of each query, ``arr_3`` / ``arr_4`` reference / query positions. The
descriptor arrays (~780 MB) are memory-mapped straight out of the zip when stored
uncompressed, as ``numpy.savez`` writes them; a compressed member is streamed once into a
cache file and mapped from there.
"""

from __future__ import annotations

import os
import shutil
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.errors import InputError
from vprscale.core.objects import cache_root, is_url, public
from vprscale.dataset.sources.base import RowSource
from vprscale.dataset.sources.fetched import check_fetched
from vprscale.dataset.sources.fingerprint import file_fingerprint


@dataclass
class Traverse:
    """A reference and a query traverse with ground truth, from a file or the generator."""

    ref: RowSource
    query: RowSource
    gt: np.ndarray
    ref_pos: np.ndarray
    query_pos: np.ndarray

    def fingerprint(self) -> dict[str, Any]:
        return {"ref": self.ref.fingerprint(), "query": self.query.fingerprint()}


class NpyMemberSource(RowSource):
    """A 2-D float32 ``.npy`` array at a byte offset of a file (a stored zip member).

    Of a file given by URL (``origin``), the file is this machine's copy in the cache; a task on
    a Dask worker that shares no disk with the client finds no such file and opens the URL
    itself, fetching its own copy once."""

    def __init__(self, path: Path, offset: int, shape: tuple[int, int], fortran: bool,
                 name: str, fingerprint: dict[str, Any], origin: str | None = None) -> None:
        if fortran:
            raise InputError(f"{name}: Fortran-ordered arrays are not supported")
        self.path, self.offset, self.origin = path, offset, origin
        self.n_rows, self.dim = shape
        self.name = name
        self._fp = fingerprint

    def _read(self, start: int, stop: int) -> np.ndarray:
        if self.origin is not None and not self.path.is_file():
            here = open_fas(self.origin, quiet=True)
            return (here.ref if self._fp["member"] == "arr_0" else here.query).read(start, stop)
        mm = np.memmap(self.path, dtype="<f4", mode="r", offset=self.offset + 4 * start * self.dim,
                       shape=(stop - start, self.dim))
        out = np.array(mm, dtype=np.float32)
        del mm
        return out

    def fingerprint(self) -> dict[str, Any]:
        return self._fp


def _member_layout(zf: zipfile.ZipFile, fh, info: zipfile.ZipInfo) -> tuple[int, tuple, bool, np.dtype]:
    """Offset of the array data of a stored member, and its npy header."""
    fh.seek(info.header_offset)
    local = fh.read(30)
    name_len, extra_len = struct.unpack("<HH", local[26:30])
    start = info.header_offset + 30 + name_len + extra_len
    fh.seek(start)
    shape, fortran, dtype = _npy_header(fh)
    return fh.tell(), shape, fortran, dtype


def _npy_header(fh) -> tuple[tuple, bool, np.dtype]:
    """Parse an ``.npy`` header at the file position; leaves the position at the data."""
    major, _ = np.lib.format.read_magic(fh)
    read = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
    return read(fh)


def _member_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo, shown: str) -> tuple[tuple, np.dtype]:
    """The shape and dtype a member's ``.npy`` header declares, read before any of its data (a
    small compressed file may unpack to gigabytes), checked to agree with the member's size."""
    key = info.filename.removesuffix(".npy")
    try:
        with zf.open(info) as member:
            shape, _, dtype = _npy_header(member)
            start = member.tell()
    except (ValueError, zipfile.BadZipFile, EOFError, OSError) as exc:
        raise InputError(f"{shown}: {key} is not an .npy array ({str(exc).splitlines()[0]})") from None
    size = start + int(np.prod(shape, dtype=object)) * np.dtype(dtype).itemsize
    if size != info.file_size:
        raise InputError(f"{shown}: {key}'s header declares shape {shape} {dtype} ({size:,} bytes) but the member "
                         f"holds {info.file_size:,}")
    return shape, np.dtype(dtype)


ARRAYS = ("arr_0", "arr_1", "arr_2", "arr_3", "arr_4")  # the members read (arr_5, arr_6 are unused)


def _check_headers(shown: str, headers: dict[str, tuple[tuple, np.dtype]]) -> None:
    """Every member's shape and the descriptors' dtype, from the headers alone (``(shape, dtype)``
    by member): checked before a byte of any member is unpacked (the descriptors unpack to
    gigabytes; a header may claim billions)."""
    shapes = {key: shape for key, (shape, _) in headers.items()}
    for key in ("arr_0", "arr_1"):
        shape, dtype = headers[key]
        if len(shape) != 2 or dtype != np.dtype("<f4"):
            raise InputError(f"{shown}: {key} must be a 2-D float32 array, got shape {shape} dtype {dtype}")
    (n_ref, width), (n_query, width_q) = shapes["arr_0"], shapes["arr_1"]
    if width != width_q:
        raise InputError(f"{shown}: arr_0 has {width} columns but arr_1 has {width_q}")
    if shapes["arr_2"] != (n_query,):
        raise InputError(f"{shown}: arr_2 must be {n_query} integer ground-truth indices, got shape {shapes['arr_2']}")
    for key, rows in (("arr_3", n_ref), ("arr_4", n_query)):
        shape = shapes[key]
        if len(shape) != 2 or shape[0] != rows or shape[1] not in (2, 3):
            raise InputError(f"{shown}: {key} must hold {rows} positions (n × 2 or n × 3), got shape {shape}")


def open_fas(path: str | os.PathLike, quiet: bool = False) -> Traverse:
    """Open and validate an FAS100K ``.npz`` (shapes, dtypes, ``0 ≤ gt < len(ref)``), a local file
    or a URL (fetched once into the cache: the FAS PCA reads it whole several times)."""
    if is_url(path):
        from vprscale.dataset.sources.remote import fetched_copy

        local, fp = fetched_copy(str(path), quiet)
        return _open_npz(local, fp, public(str(path)), str(path))
    p = Path(path).absolute()  # tasks may run in another directory (a cluster's workers)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    check_fetched(p)  # a file fetch wrote, as it wrote it
    return _open_npz(p, file_fingerprint(p), str(p))


def _open_npz(p: Path, fp: dict[str, Any], shown: str, origin: str | None = None) -> Traverse:
    """:func:`open_fas` of a local file, shown as ``shown`` and fingerprinted as ``fp`` (a copy of
    the file at URL ``origin``, if given)."""
    try:
        zf = zipfile.ZipFile(p)
    except zipfile.BadZipFile as exc:
        raise InputError(f"{shown}: not an .npz (zip) file: {exc}") from None
    with zf, open(p, "rb") as fh:
        members = {i.filename.removesuffix(".npy"): i for i in zf.infolist()}
        for key in ("arr_0", "arr_1", "arr_2", "arr_3", "arr_4"):
            if key not in members:
                raise InputError(f"{shown}: missing array {key}")
        _check_headers(shown, {k: _member_header(zf, members[k], shown) for k in ARRAYS})

        def descriptors(key: str) -> NpyMemberSource:
            info = members[key]
            if info.compress_type == zipfile.ZIP_STORED:
                offset, shape, fortran, dtype = _member_layout(zf, fh, info)
                target = p
            else:
                target = cache_root() / f"{fp['sha256_head_tail'][:16]}-{fp['bytes']}" / f"{key}.npy"
                if not target.is_file() or target.stat().st_size != info.file_size:  # missing, or cut short
                    target.parent.mkdir(parents=True, exist_ok=True)
                    free = shutil.disk_usage(target.parent).free
                    if info.file_size > free:
                        raise InputError(f"{shown}: {key} unpacks to {info.file_size / 2**30:,.1f} GiB and the "
                                         f"cache, {target.parent}, has {free / 2**30:,.1f} GiB free "
                                         "($VPRSCALE_CACHE moves it)")
                    tmp = target.with_suffix(".tmp")
                    try:
                        with zf.open(info) as src, open(tmp, "wb") as dst:
                            shutil.copyfileobj(src, dst, 1 << 24)
                    except BaseException:
                        tmp.unlink(missing_ok=True)  # a full cache leaves nothing half-written behind
                        raise
                    tmp.replace(target)
                with open(target, "rb") as cf:
                    shape, fortran, dtype = _npy_header(cf)
                    offset = cf.tell()
            return NpyMemberSource(target, offset, shape, fortran, f"{shown}:{key}", {**fp, "member": key}, origin)

        ref, query = descriptors("arr_0"), descriptors("arr_1")
        small = {}
        for k in ("arr_2", "arr_3", "arr_4"):
            try:
                small[k] = np.load(zf.open(members[k]), allow_pickle=False)
            except ValueError as exc:  # a pickled (object) array, or not an .npy member at all
                raise InputError(f"{shown}: {k} is not a plain numeric array ({str(exc).splitlines()[0]})") from None
    gt, ref_pos, query_pos = small["arr_2"], small["arr_3"], small["arr_4"]  # shapes checked from the headers
    if not np.issubdtype(gt.dtype, np.integer):
        raise InputError(f"{shown}: arr_2 must be {query.n_rows} integer ground-truth indices, "
                         f"got shape {gt.shape} dtype {gt.dtype}")
    bad = np.flatnonzero((gt < 0) | (gt >= ref.n_rows))
    if bad.size:
        raise InputError(f"{shown}: arr_2 row {int(bad[0])}: ground truth {int(gt[bad[0]])} "
                         f"outside [0, {ref.n_rows})")
    return Traverse(ref, query, gt.astype(np.int64), ref_pos, query_pos)
