"""The index directory format: the one module that writes and reads it.

An index directory (format 3, docs/method.md "Storage") holds:

- ``index.json``: kind, format, parameters (``d``, ``k``, ``bins``, ``n_ref``, ``dim``,
  ``occupied``), the layout of the succinct files (``lists``) and whatever the writer adds
  (the store it came from, storage, timings);
- ``model/{mean,components,centres,explained_variance}.npy``: the fitted CoarseHasher;
- ``components.parquet``: per component and cluster: centre, reference count and share;
- the engine's files, memory-mapped by the query side (:mod:`vprscale.method.succinct`):
  ``codes.npy`` (P1, every place's address in ⌈d·log2 K⌉ bits: for K = 2 the bit planes
  the windows are scored on, else bit-packed), ``ids.npy`` (the ids grouped by address,
  bit-packed at ⌈log2 N⌉ bits, each list's single best first and the rest ascending),
  ``occupied.npy`` and ``starts.npy`` (the sorted occupied addresses and the lists'
  starts, Elias–Fano);
- ``buckets.parquet`` (``hash``, ``size``, ``offset``): one row per occupied address for
  the SQL console, its sorted integers delta-coded and compressed; the console's ``lists``
  view reads ``ids.npy`` itself (:mod:`vprscale.evaluation.sqlchild`), so the ids are never
  stored twice.

Three writers produce the same files through :class:`_Writer`: :func:`write_lists` streams a
job's references through the partitioned sort of :mod:`vprscale.method.lists` (bounded
memory at any scale), :func:`write_arrays` writes lists held in memory (``Index.save``) and
:func:`upgrade` converts a format-2 directory without refitting. :func:`read_arrays` opens
any of them. Publishing (hidden work copy, lock, atomic rename) is the caller's. ``index.json``
is read by :mod:`vprscale.method.indexmeta`, which imports nothing heavy, so that tools that
only check an index (``vprscale sql``, ``verify``) start fast.
"""

from __future__ import annotations

import io
import json
import math
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from vprscale.core.errors import InputError
from vprscale.core.progress import ChunkProgress
from vprscale.method.indexmeta import INDEX_FORMAT, KIND, load_index_meta
from vprscale.method.invlists import InvertedLists, best_first
from vprscale.method.kernels import plane_words, planes_into
from vprscale.method.lists import (
    PART_ROWS,
    PREFIX_BITS,
    Reader,
    address_dtype,
    inverted_lists,
    prefix_cuts,
    scatter,
)
from vprscale.method.succinct import (
    EliasFano,
    occupancy_structure,
    pack_bits_into,
    packed_words,
    structure_from_words,
    width,
)

if TYPE_CHECKING:  # the estimator (and scikit-learn) is imported only to read a model: see read_arrays
    from vprscale.method.coarsehash import CoarseHasher

MODEL = ("mean", "components", "centres", "explained_variance")
MODEL_FILES = {"P2": ["centres.npy"], "P3": ["components.npy", "explained_variance.npy"], "P4": ["mean.npy"]}
ENGINE_FILES = {"codes": "codes.npy", "ids": "ids.npy", "occupied": "occupied.npy", "starts": "starts.npy"}
SQL_FILES = ("buckets.parquet", "components.parquet")
ROW_GROUP = 1 << 16  # look-ups prune to one row group; fewer groups keep DuckDB's planning cheap
UPGRADE_LISTS = 1 << 22  # lists converted together by upgrade


def code_bits(d: int, k: int) -> int:
    """Bits of one place's code: ⌈d·log2 K⌉ (d for K = 2)."""
    return d if k == 2 else width(k**d - 1)


def code_words(n_ref: int, d: int, k: int) -> int:
    return plane_words(n_ref, d) if k == 2 else packed_words(n_ref, code_bits(d, k))


class _Buckets:
    """``buckets.parquet``, written a run of occupied addresses at a time.

    Sorted addresses and offsets are delta-coded (their deltas are small), sizes
    dictionary-coded (a few distinct values), all zstd-compressed: about 0.6 bytes per
    occupied address where plain words take 20.
    """

    def __init__(self, out: Path) -> None:
        self.writer = pq.ParquetWriter(out / "buckets.parquet",
                                       pa.schema([("hash", pa.uint64()), ("size", pa.uint32()),
                                                  ("offset", pa.uint64())]),
                                       compression="zstd", compression_level=9,
                                       use_dictionary=["size"],
                                       column_encoding={"hash": "DELTA_BINARY_PACKED",
                                                        "offset": "DELTA_BINARY_PACKED"})
        self.pending = [np.zeros(0, np.uint64), np.zeros(0, np.uint32), np.zeros(0, np.uint64)]

    def write(self, addresses: np.ndarray, sizes: np.ndarray, offsets: np.ndarray) -> None:
        """Append a run of buckets; whole row groups are written as they fill, so the file is the
        same bytes however the runs were cut (partitions, upgrade chunks)."""
        new = [np.asarray(x, t) for x, t in zip((addresses, sizes, offsets), (np.uint64, np.uint32, np.uint64),
                                                strict=True)]
        self.pending = new if not len(self.pending[0]) else [np.concatenate([p, x]) for p, x in
                                                              zip(self.pending, new, strict=True)]
        full = len(self.pending[0]) // ROW_GROUP * ROW_GROUP
        if full:
            self._flush(full)

    def _flush(self, n: int) -> None:
        hashes, sizes, offsets = (p[:n] for p in self.pending)
        self.writer.write_table(pa.table({"hash": pa.array(hashes), "size": pa.array(sizes),
                                          "offset": pa.array(offsets)}), row_group_size=ROW_GROUP)
        self.pending = [p[n:] for p in self.pending]

    def close(self) -> None:
        if len(self.pending[0]):
            self._flush(len(self.pending[0]))
        self.writer.close()


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


class _Writer:
    """The engine's files and the SQL buckets of one directory, written in order.

    :meth:`codes` takes places' addresses chunk by chunk (any order of chunks), :meth:`lists`
    runs of lists in address order, each list's ids with its single best first;
    :meth:`close` builds the Elias–Fano directory from the appended addresses and offsets
    (read back once, memory-mapped) and returns the layout that ``index.json`` records.
    """

    def __init__(self, out: Path, n_ref: int, d: int, k: int) -> None:
        self.out, self.n_ref, self.d, self.k = out, n_ref, d, k
        self.code_bits, self.id_bits = code_bits(d, k), width(max(0, n_ref - 1))
        self.codes_file = _WordsFile(out / ENGINE_FILES["codes"], code_words(n_ref, d, k), d if k == 2 else 1)
        self.ids_file = _WordsFile(out / ENGINE_FILES["ids"], packed_words(n_ref, self.id_bits), 1)
        self.n_codes = 0
        self.addresses = _Appender(out / ".addresses.tmp", np.uint64)
        self.offsets = _Appender(out / ".offsets.tmp", np.int64)
        self.buckets = _Buckets(out)
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
        self.buckets.write(addresses, sizes, offsets)
        self.n_ids += len(ids)
        self.longest = max(self.longest, int(np.max(sizes, initial=0)))

    def close(self) -> dict[str, Any]:
        self.offsets.append(np.array([self.n_ids]))
        for f in (self.addresses, self.offsets):
            f.close()
        self.buckets.close()
        self.codes_file.close()
        self.ids_file.close()
        layout: dict[str, Any] = {"code_bits": self.code_bits, "codes": "planes" if self.k == 2 else "packed",
                                  "id_bits": self.id_bits, "longest": self.longest}
        for name, tmp in (("occupied", self.addresses), ("starts", self.offsets)):
            values = np.load(tmp.path, mmap_mode="r")
            structure = occupancy_structure(values, self.k**self.d) if name == "occupied" else EliasFano.build(values)
            np.save(self.out / ENGINE_FILES[name], structure.words())
            layout[name] = structure.layout()
            del structure, values
            tmp.path.unlink()
        layout["occupied"]["count"] = self.addresses.n
        return layout


def _best_first_run(order: np.ndarray, sizes: np.ndarray, best: np.ndarray) -> np.ndarray:
    """``order`` (ids ascending per list) with each list's single best moved to its front."""
    order = np.array(order, np.int64)
    best_first(order, np.r_[0, np.cumsum(sizes)].astype(np.int64), np.asarray(best, np.int64))
    return order


_BYTE_BITS = (np.arange(256)[:, None] >> np.arange(8)[None, :]) & 1  # bit b of each byte value


def level_counts(addresses: np.ndarray, d: int, k: int) -> np.ndarray:
    """References per code level, (d × K), of addresses (the first component is the top digit).

    For K = 2 a component is a bit: a histogram of each byte of the addresses gives every
    bit's count at once (eight bincounts instead of d passes of division over the array).
    """
    if k == 2:
        raw = np.ascontiguousarray(addresses, np.dtype(np.asarray(addresses).dtype).newbyteorder("<"))
        columns = raw.view(np.uint8).reshape(len(raw), raw.dtype.itemsize)
        ones = np.concatenate([np.bincount(columns[:, i], minlength=256) @ _BYTE_BITS
                               for i in range(raw.dtype.itemsize)])[:d]  # ones[b]: addresses with bit b set
        ones = ones[::-1].astype(np.int64)  # bit d − 1 − j is component j
        return np.stack([len(raw) - ones, ones], axis=1)
    rest = np.asarray(addresses, np.uint64).copy()
    counts = np.zeros((d, k), np.int64)
    for j in range(d - 1, -1, -1):
        counts[j] += np.bincount((rest % np.uint64(k)).astype(np.int64), minlength=k)
        rest //= np.uint64(k)
    return counts


def write_lists(out: Path, addresses: Reader, errors: Reader, bounds: list[tuple[int, int]], n_ref: int, d: int,
                k: int, quiet: bool = False, part_rows: int = PART_ROWS) -> dict:
    """Sort references into inverted lists in ``out`` in bounded memory; returns counts and layout.

    ``addresses(a, b)`` and ``errors(a, b)`` give the addresses and quantisation errors of
    references ``[a, b)`` (``bounds`` are their chunks); each is read once. Returns
    ``level_counts`` (d × K references per code level), ``occupied``, ``partitions`` and
    ``layout`` (what ``index.json`` records of the engine's files).
    """
    bits = max(1, math.ceil(d * math.log2(k)))
    addr_t, id_t = address_dtype(d, k), np.dtype(np.uint32 if n_ref < 2**32 else np.uint64)
    shift = np.uint64(max(0, bits - PREFIX_BITS))
    writer = _Writer(out, n_ref, d, k)
    # every place's address once more, for the partitioned sort to read back; removed at the end
    ref_hash = np.lib.format.open_memmap(out / ".ref_hash.tmp", mode="w+", dtype=addr_t, shape=(n_ref,))
    prefix_counts = np.zeros(1 << min(bits, PREFIX_BITS), np.int64)
    counts = np.zeros((d, k), np.int64)
    progress = None if quiet else ChunkProgress("scan addresses", len(bounds))
    for a, b in bounds:
        h = np.asarray(addresses(a, b), np.uint64)
        ref_hash[a:b] = h
        writer.codes(a, h)
        prefix_counts += np.bincount((h >> shift).astype(np.int64), minlength=len(prefix_counts))
        counts += level_counts(h, d, k)
        if progress:
            progress.update(1)
    ref_hash.flush()
    cuts = prefix_cuts(prefix_counts, part_rows)
    parts = scatter(out / ".partitions", errors, bounds, ref_hash, cuts, shift, id_t, quiet)
    progress = None if quiet or len(cuts) == 1 else ChunkProgress("sort partitions", len(cuts))
    for part in parts:
        h, err, ids = part()
        lists = inverted_lists(h, err)
        del h, err
        writer.lists(lists["addresses"], lists["sizes"],
                     _best_first_run(ids[lists["order"]], lists["sizes"], ids[lists["best"]]))
        del ids, lists
        if progress:
            progress.update(1)
    shutil.rmtree(out / ".partitions", ignore_errors=True)
    del ref_hash
    (out / ".ref_hash.tmp").unlink()
    layout = writer.close()
    return {"level_counts": counts, "occupied": layout["occupied"]["count"], "partitions": len(cuts),
            "layout": layout}


def write_model(path: Path, hasher: CoarseHasher, counts: np.ndarray, n_ref: int) -> None:
    """``model/*.npy`` and ``components.parquet`` of a fitted hasher and its references' code levels."""
    (path / "model").mkdir(exist_ok=True)
    for name in MODEL:
        np.save(path / "model" / f"{name}.npy", getattr(hasher, f"{name}_"))
    d, k = counts.shape
    comp = pa.table({"component": np.repeat(np.arange(1, d + 1), k).astype(np.int32),
                     "cluster": np.tile(np.arange(k), d).astype(np.int32),
                     "centre": hasher.centres_.ravel(),
                     "refs": counts.ravel().astype(np.int64),
                     "share": (counts / max(1, n_ref)).ravel(),
                     "variance": np.repeat(hasher.explained_variance_, k)})
    pq.write_table(comp, path / "components.parquet")


def write_meta(path: Path, hasher: CoarseHasher, n_ref: int, layout: dict[str, Any],
               extra: dict[str, Any]) -> dict[str, Any]:
    """``index.json``: the format's own keys, then what the writer adds (``extra`` cannot override them)."""
    own = {"kind": KIND, "complete": True, "format": INDEX_FORMAT, "d": int(hasher.d_), "k": int(hasher.k),
           "n_ref": int(n_ref), "dim": int(hasher.n_features_in_), "occupied": int(layout["occupied"]["count"]),
           "bins": int(hasher.bins), "layout": layout}
    meta = {**own, **{key: value for key, value in extra.items() if key not in own}}
    (path / "index.json").write_text(json.dumps(meta, indent=1, default=str))
    return meta


def write_arrays(path: Path, hasher: CoarseHasher, ref_hash: np.ndarray, lists: InvertedLists,
                 extra: dict[str, Any]) -> dict[str, Any]:
    """Write an index held in memory into the directory ``path`` (which must exist and be empty).

    The files are those :func:`write_lists` writes for the same references.
    """
    d, k, n_ref = hasher.d_, hasher.k, len(ref_hash)
    writer = _Writer(path, n_ref, d, k)
    writer.codes(0, ref_hash)
    offsets = lists.starts.decode()
    writer.lists(lists.occupied.decode(), np.diff(offsets), lists.ids_range(0, lists.n_ids))
    write_model(path, hasher, level_counts(ref_hash, d, k), n_ref)
    return write_meta(path, hasher, n_ref, writer.close(), extra)


def upgrade(old: Path, out: Path, quiet: bool = False) -> dict[str, Any]:
    """Convert a format-2 index directory ``old`` into format 3 in ``out`` (existing, empty),
    without refitting: the same addresses, lists and single bests, streamed in bounded memory.

    Returns the new ``index.json``; its storage accounting is the caller's to refresh.
    """
    meta = json.loads((old / "index.json").read_text())
    d, k, n_ref = int(meta["d"]), int(meta["k"]), int(meta["n_ref"])
    try:
        arrays = {name: np.load(old / f"{name}.npy", mmap_mode="r")
                  for name in ("ref_hash", "ids", "addresses", "offsets", "best")}
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"{old}: a format-2 index file is missing or damaged ({str(exc).splitlines()[0][:200]}); "
                         "re-run vprscale index") from None
    writer = _Writer(out, n_ref, d, k)
    chunk = 1 << 24
    progress = None if quiet else ChunkProgress("upgrade: codes", -(-n_ref // chunk))
    for a in range(0, n_ref, chunk):
        writer.codes(a, arrays["ref_hash"][a : a + chunk])
        if progress:
            progress.update(1)
    occupied = len(arrays["addresses"])
    progress = None if quiet else ChunkProgress("upgrade: lists", -(-occupied // UPGRADE_LISTS))
    for a in range(0, occupied, UPGRADE_LISTS):
        b = min(occupied, a + UPGRADE_LISTS)
        offsets = np.asarray(arrays["offsets"][a : b + 1], np.int64)
        sizes = np.diff(offsets)
        writer.lists(arrays["addresses"][a:b], sizes,
                     _best_first_run(arrays["ids"][offsets[0] : offsets[-1]], sizes, arrays["best"][a:b]))
        if progress:
            progress.update(1)
    layout = writer.close()
    (out / "model").mkdir(exist_ok=True)
    for name in MODEL:
        shutil.copy2(old / "model" / f"{name}.npy", out / "model" / f"{name}.npy")
    shutil.copy2(old / "components.parquet", out / "components.parquet")
    meta.update({"format": INDEX_FORMAT, "layout": layout, "occupied": int(layout["occupied"]["count"]),
                 "upgraded_from": 2})
    (out / "index.json").write_text(json.dumps(meta, indent=1, default=str))
    return meta


def read_lists(path: str | Path) -> tuple[np.ndarray, InvertedLists, dict[str, Any]]:
    """``(codes, lists, meta)`` of an index directory, memory-mapped (a query touches only the pages
    it reads): what a tool that reads no model needs (``vprscale occupancy``), without importing the
    estimator."""
    path = Path(path)
    meta = load_index_meta(path)
    layout = meta["layout"]
    try:
        files = {name: np.load(path / file, mmap_mode="r") for name, file in ENGINE_FILES.items()}
        lists = InvertedLists(structure_from_words(files["occupied"], layout["occupied"]),
                              EliasFano.from_words(files["starts"], layout["starts"]), files["ids"],
                              int(layout["id_bits"]), int(layout["longest"]))
    except (OSError, ValueError, EOFError, KeyError) as exc:  # a missing or truncated file (no manifest)
        raise InputError(f"{path}: an index file is missing or damaged ({str(exc).splitlines()[0][:200]}); "
                         "re-run vprscale index") from None
    n_ref = int(meta["n_ref"])
    if len(files["codes"]) != code_words(n_ref, int(meta["d"]), int(meta["k"])) or \
            len(files["ids"]) != packed_words(n_ref, lists.id_bits):
        raise InputError(f"{path}: codes.npy or ids.npy does not hold {n_ref:,} places; re-run vprscale index")
    return files["codes"], lists, meta


def read_arrays(path: str | Path) -> tuple[CoarseHasher, np.ndarray, InvertedLists, dict[str, Any]]:
    """``(hasher, codes, lists, meta)`` of an index directory: the model read, the codes and the
    lists memory-mapped."""
    from vprscale.method.coarsehash import CoarseHasher

    codes, lists, meta = read_lists(path)
    path = Path(path)
    try:
        model = {name: np.load(path / "model" / f"{name}.npy") for name in MODEL}
    except (OSError, ValueError, EOFError) as exc:  # a missing or truncated file (no manifest)
        raise InputError(f"{path}: an index file is missing or damaged ({str(exc).splitlines()[0][:200]}); "
                         "re-run vprscale index") from None
    hasher = CoarseHasher.from_fitted(int(meta["k"]), int(meta.get("bins", 1 << 14)), int(meta["n_ref"]), **model)
    return hasher, codes, lists, meta
