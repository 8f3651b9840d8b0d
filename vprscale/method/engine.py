"""The query engine's arrays as files: the form an index's Parquet tables are decoded into.

The engine (:mod:`vprscale.method.invlists`, the kernels) reads succinct arrays: ``codes.npy``
(P1: for K = 2 the bit planes the windows are scored on, else bit-packed addresses),
``ids.npy`` (the ids grouped by address, bit-packed at ⌈log2 N⌉ bits, each list's single
best first and the rest ascending), ``occupied.npy`` (the occupied addresses: a rank bitmap
or Elias–Fano, whichever is smaller) and ``starts.npy`` (the lists' starts, Elias–Fano).
An index directory keeps its lists and codes as Parquet tables that any reader opens
(:mod:`vprscale.method.indexfile`); loading it decodes them into these files once:

- a small index (up to :data:`IN_MEMORY_PLACES` places) in memory, on every load (a
  fraction of a second);
- a larger one into a local cache folder (``$VPRSCALE_CACHE/engines/``, one per index
  location; used only if no other user can write it), checksummed by its own manifest and
  memory-mapped by later loads for as long as the index's manifest is the one it was decoded
  from; a re-published index is decoded again, never read stale. Where the cache cannot be
  written the arrays are decoded in memory.

This module owns the cache folder's format (``engine.json``, the four files, a manifest).
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.errors import InputError
from vprscale.core.manifest import NAME, check_manifest, write_manifest
from vprscale.core.objects import cache_root
from vprscale.core.private import private_folder
from vprscale.method.invlists import InvertedLists
from vprscale.method.kernels import plane_words, planes_into
from vprscale.method.succinct import (
    EliasFano,
    occupancy_structure,
    pack_bits_into,
    packed_words,
    structure_from_words,
    width,
)

log = logging.getLogger(__name__)

FILES = {"codes": "codes.npy", "ids": "ids.npy", "occupied": "occupied.npy", "starts": "starts.npy"}
IN_MEMORY_PLACES = 1 << 22  # up to here decoding costs well under a second: no cache folder
ENGINE = "engine.json"


def code_bits(d: int, k: int) -> int:
    """Bits of one place's code: ⌈d·log2 K⌉ (d for K = 2)."""
    return d if k == 2 else width(k**d - 1)


def code_words(n_ref: int, d: int, k: int) -> int:
    return plane_words(n_ref, d) if k == 2 else packed_words(n_ref, code_bits(d, k))


class _Appender:
    """A 1-D ``.npy`` file written by appending; its header (numpy's own) gets the final length at close.

    The header is given a fixed 128 bytes up front, which numpy's 1.0 header of any 1-D
    shape below 10^40 elements fills exactly.
    """

    HEADER = 128

    def __init__(self, path: Path, dtype: np.dtype) -> None:
        self.path, self.dtype, self.n = path, np.dtype(dtype), 0
        self.f = path.open("wb")
        self.f.write(b"\0" * self.HEADER)

    def append(self, x: np.ndarray) -> None:
        np.ascontiguousarray(x, self.dtype).tofile(self.f)
        self.n += len(x)

    def close(self) -> None:
        head = io.BytesIO()
        np.lib.format.write_array_header_1_0(head, {"descr": np.lib.format.dtype_to_descr(self.dtype),
                                                    "fortran_order": False, "shape": (self.n,)})
        assert len(head.getvalue()) == self.HEADER, "numpy's .npy header changed length"
        self.f.seek(0)
        self.f.write(head.getvalue())
        self.f.close()


class _WordsFile:
    """A uint64 ``.npy`` file of ``n_words`` words, written front to back from runs that may
    share their boundary word (bit-packed values) or row (bit planes) with the next run.

    Only the words a later run may still change are held in memory; every word before them
    is final and written out, so writing a billion places' codes or ids holds a few words,
    not a gigabyte-sized mapped file (whose written pages count as resident memory).
    """

    def __init__(self, path: Path, n_words: int, unit: int) -> None:
        self.path, self.n_words, self.unit = path, n_words, unit  # unit: words that are final together
        self.f = path.open("wb")
        np.lib.format.write_array_header_1_0(self.f, {"descr": "<u8", "fortran_order": False, "shape": (n_words,)})
        self.written = 0  # words in the file
        self.tail = np.zeros(0, np.uint64)  # words from ``written`` on that a later run may still change

    def run(self, last: int) -> np.ndarray:
        """The words from the first unwritten one to ``last − 1``, to fill: the held tail, then zeros."""
        out = np.zeros(last - self.written, np.uint64)
        out[: len(self.tail)] = self.tail
        return out

    def done(self, words: np.ndarray, final: int) -> None:
        """``words`` (from :meth:`run`) are filled; those before word ``final`` will not change."""
        cut = (final - self.written) // self.unit * self.unit
        self.f.write(words[:cut].tobytes())
        self.written += cut
        self.tail = words[cut:].copy()

    def close(self) -> None:
        rest = np.zeros(self.n_words - self.written, np.uint64)
        rest[: len(self.tail)] = self.tail
        self.f.write(rest.tobytes())
        self.f.close()


class EngineWriter:
    """The engine's four files in one folder, written in order.

    :meth:`codes` takes places' addresses chunk by chunk (any order of chunks), :meth:`lists`
    runs of lists in address order, each list's ids with its single best first;
    :meth:`close` builds the Elias–Fano directory from the appended addresses and offsets
    (read back once, memory-mapped) and returns the layout that ``index.json`` records.
    """

    def __init__(self, out: Path, n_ref: int, d: int, k: int) -> None:
        self.out, self.n_ref, self.d, self.k = out, n_ref, d, k
        self.code_bits, self.id_bits = code_bits(d, k), width(max(0, n_ref - 1))
        self.codes_file = _WordsFile(out / FILES["codes"], code_words(n_ref, d, k), d if k == 2 else 1)
        self.ids_file = _WordsFile(out / FILES["ids"], packed_words(n_ref, self.id_bits), 1)
        self.n_codes = 0
        self.addresses = _Appender(out / ".addresses.tmp", np.uint64)
        self.offsets = _Appender(out / ".offsets.tmp", np.int64)
        self.n_ids = self.longest = 0

    def codes(self, a: int, h: np.ndarray) -> None:
        """The addresses of the next places, ``a … a + len(h) − 1`` (runs in order, from 0)."""
        if a != self.n_codes:
            raise ValueError(f"codes of places from {a:,}: the next place is {self.n_codes:,}")
        h = np.asarray(h, np.uint64)
        f, b = self.codes_file, a + len(h)
        if self.k == 2:  # rows of d words per 64 places: the rows before place b's are final
            words = f.run(((b + 63) // 64) * self.d)
            planes_into(words, h, np.int64(a - 64 * (f.written // self.d)), self.d)
            f.done(words, (b // 64) * self.d)
        else:
            words = f.run(-(-b * self.code_bits // 64))
            pack_bits_into(words, self.code_bits, np.int64(a * self.code_bits - 64 * f.written), h)
            f.done(words, b * self.code_bits // 64)
        self.n_codes = b

    def lists(self, addresses: np.ndarray, sizes: np.ndarray, ids: np.ndarray) -> None:
        """The next run of occupied addresses (ascending), their lists' sizes and ids."""
        offsets = self.n_ids + np.r_[0, np.cumsum(sizes[:-1])].astype(np.int64) if len(sizes) else np.zeros(0, np.int64)
        f, b = self.ids_file, self.n_ids + len(ids)
        words = f.run(-(-b * self.id_bits // 64))
        pack_bits_into(words, self.id_bits, np.int64(self.n_ids * self.id_bits - 64 * f.written),
                       np.asarray(ids, np.uint64))
        f.done(words, b * self.id_bits // 64)
        self.addresses.append(addresses)
        self.offsets.append(offsets)
        self.n_ids += len(ids)
        self.longest = max(self.longest, int(np.max(sizes, initial=0)))

    def close(self) -> dict[str, Any]:
        self.offsets.append(np.array([self.n_ids]))
        for f in (self.addresses, self.offsets):
            f.close()
        self.codes_file.close()
        self.ids_file.close()
        layout: dict[str, Any] = {"code_bits": self.code_bits, "codes": "planes" if self.k == 2 else "packed",
                                  "id_bits": self.id_bits, "longest": self.longest}
        for name, tmp in (("occupied", self.addresses), ("starts", self.offsets)):
            values = np.load(tmp.path, mmap_mode="r")
            structure = occupancy_structure(values, self.k**self.d) if name == "occupied" else EliasFano.build(values)
            np.save(self.out / FILES[name], structure.words())
            layout[name] = structure.layout()
            del structure, values
            tmp.path.unlink()
        layout["occupied"]["count"] = self.addresses.n
        return layout


def open_engine(folder: Path, layout: dict[str, Any], n_ref: int, d: int, k: int,
                mmap: bool = True) -> tuple[np.ndarray, InvertedLists]:
    """``(codes, lists)`` of the engine files in ``folder`` (``layout``: what :meth:`EngineWriter.close`
    returned), memory-mapped or read whole."""
    mode = "r" if mmap else None
    files = {name: np.load(folder / file, mmap_mode=mode) for name, file in FILES.items()}
    lists = InvertedLists(structure_from_words(files["occupied"], layout["occupied"]),
                          EliasFano.from_words(files["starts"], layout["starts"]), files["ids"],
                          int(layout["id_bits"]), int(layout["longest"]))
    if len(files["codes"]) != code_words(n_ref, d, k) or len(files["ids"]) != packed_words(n_ref, lists.id_bits):
        raise ValueError(f"the engine's files do not hold {n_ref:,} places")
    return files["codes"], lists


Fill = Callable[[EngineWriter], None]


def engine_arrays(index: Path, n_ref: int, d: int, k: int, fill: Fill, in_memory: bool | None = None,
                  root: Path | None = None) -> tuple[np.ndarray, InvertedLists]:
    """The engine's ``(codes, lists)`` of the index directory ``index`` (published, with its
    manifest): ``fill`` streams the index's tables into an :class:`EngineWriter` where they
    must be decoded: in memory, or in the cache under ``root`` (default ``$VPRSCALE_CACHE``);
    ``in_memory`` None chooses by size (see the module's docstring)."""
    if in_memory or (in_memory is None and n_ref <= IN_MEMORY_PLACES):
        return decoded_in_memory(n_ref, d, k, fill)
    source = hashlib.sha256((index / NAME).read_bytes()).hexdigest()
    engines = private_folder((root or cache_root()) / "engines", f"decoding {index} in memory")
    if engines is None:
        return decoded_in_memory(n_ref, d, k, fill)
    folder = engines / hashlib.sha256(str(index.resolve()).encode()).hexdigest()[:16]
    cached = _cached(folder, source, n_ref, d, k)
    if cached is not None:
        return cached
    try:
        work = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".partial", dir=engines))
    except OSError as exc:
        log.warning(f"the engine cache {folder.parent} cannot be written ({exc.strerror}): decoding {index} in memory")
        return decoded_in_memory(n_ref, d, k, fill)
    try:
        log.info(f"decoding {index}'s tables into the engine cache, {folder} (once; later loads map it)")
        layout = _decode(work, n_ref, d, k, fill)
        (work / ENGINE).write_text(json.dumps({"index": str(index.resolve()), "manifest_sha256": source,
                                               "layout": layout}, indent=1))
        write_manifest(work)
        shutil.rmtree(folder, ignore_errors=True)  # a stale copy (a loader still mapping it keeps its files)
        os.replace(work, folder)
    except OSError as exc:
        shutil.rmtree(work, ignore_errors=True)
        log.warning(f"the engine cache {folder} cannot be written ({exc.strerror}): decoding {index} in memory")
        return decoded_in_memory(n_ref, d, k, fill)
    return open_engine(folder, layout, n_ref, d, k)


def _cached(folder: Path, source: str, n_ref: int, d: int, k: int) -> tuple[np.ndarray, InvertedLists] | None:
    """The cache folder's arrays if they were decoded from this very manifest and check out against
    their own manifest (which must be there: a folder without one was not left by vprscale whole),
    else None."""
    try:
        record = json.loads((folder / ENGINE).read_text())
        if record.get("manifest_sha256") != source:
            return None
        check_manifest(folder, remake="it is decoded again")
        return open_engine(folder, record["layout"], n_ref, d, k)
    except (OSError, ValueError, KeyError, TypeError, InputError):  # absent, damaged or stale: decoded again
        return None


def decoded_in_memory(n_ref: int, d: int, k: int, fill: Fill) -> tuple[np.ndarray, InvertedLists]:
    """The engine's arrays decoded into a temporary folder and read into memory."""
    with tempfile.TemporaryDirectory(prefix="vprscale-engine-") as tmp:
        layout = _decode(Path(tmp), n_ref, d, k, fill)
        return open_engine(Path(tmp), layout, n_ref, d, k, mmap=False)


def _decode(folder: Path, n_ref: int, d: int, k: int, fill: Fill) -> dict[str, Any]:
    writer = EngineWriter(folder, n_ref, d, k)
    fill(writer)
    if writer.n_codes != n_ref or writer.n_ids != n_ref:
        raise ValueError(f"the index's tables hold {writer.n_codes:,} codes and {writer.n_ids:,} ids, "
                         f"not {n_ref:,} of each")
    return writer.close()
