"""The index directory format: the one module that writes and reads it.

An index directory (format 4, docs/outputs.md) holds plain Parquet tables that any reader
opens (the DuckDB CLI, Polars, pandas, Spark), beside the fitted model:

- ``index.json``: kind, format, parameters (``d``, ``k``, ``bins``, ``n_ref``, ``dim``,
  ``occupied``), the tables' layout (``layout``) and whatever the writer adds (the store it
  came from, storage, timings);
- ``model/{mean,components,centres,explained_variance}.npy``: the fitted CoarseHasher;
- ``codes.parquet`` (``ref_id``, ``hash``): every place's address, in place order (P1);
- ``lists.parquet`` (``hash``, ``ref_id``, ``best``): the inverted lists, one row per place,
  sorted by address and then id; ``best`` marks each list's single best (least quantisation
  error, ties to the smaller id);
- ``buckets.parquet`` (``hash``, ``size``, ``offset``): one row per occupied address, its
  list's length and first row in ``lists.parquet``;
- ``components.parquet``: per component and cluster: centre, reference count and share.

Sorted integers are delta-coded (``DELTA_BINARY_PACKED``: an address repeated down a list
costs nothing, ids ascending in a long list a few bits), the codes zstd-compressed, all in
fixed row groups, so the whole directory sits within a few per cent of the information floor
(d + ⌈log2 N⌉ bits a place) and is the same bytes however the rows arrived.

Three writers produce the same files through :class:`_Tables`: :func:`write_lists` streams a
job's references through the partitioned sort of :mod:`vprscale.method.lists` (bounded
memory at any scale), :func:`write_arrays` writes lists held in memory (``Index.save``) and
:func:`upgrade` converts a format-2 or format-3 directory without refitting. :func:`read_lists`
gives the query engine its arrays, decoded from the tables by :mod:`vprscale.method.engine`
(in memory, or once into a local cache that later loads memory-map). Publishing (hidden work
copy, lock, atomic rename) is the caller's. ``index.json`` is read by
:mod:`vprscale.method.indexmeta`, which imports nothing heavy, so that tools that only check
an index (``vprscale sql``, ``verify``) start fast.
"""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from vprscale.core.errors import InputError
from vprscale.core.mapped import allocated_memmap
from vprscale.core.progress import ChunkProgress
from vprscale.method.engine import EngineWriter, code_bits, engine_arrays, open_engine
from vprscale.method.indexmeta import INDEX_FORMAT, KIND, load_index_meta
from vprscale.method.invlists import InvertedLists, ascending_with_best, best_first
from vprscale.method.kernels import decode_codes
from vprscale.method.lists import (
    PART_ROWS,
    PREFIX_BITS,
    Reader,
    address_dtype,
    inverted_lists,
    prefix_cuts,
    scatter,
)
from vprscale.method.succinct import width

if TYPE_CHECKING:  # the estimator (and scikit-learn) is imported only to read a model: see read_arrays
    from vprscale.method.coarsehash import CoarseHasher

MODEL = ("mean", "components", "centres", "explained_variance")
MODEL_FILES = {"P2": ["centres.npy"], "P3": ["components.npy", "explained_variance.npy"], "P4": ["mean.npy"]}
TABLES = ("codes.parquet", "lists.parquet", "buckets.parquet")
PLACE_GROUP = 1 << 17  # rows of a row group in the per-place tables: a look-up by hash decodes one (bench lookup)
BUCKET_GROUP = 1 << 16  # look-ups prune to one row group; fewer groups keep DuckDB's planning cheap
DECODE_ROWS = 1 << 22  # rows decoded together into the engine's arrays
UPGRADE_LISTS = 1 << 22  # lists converted together by upgrade
ZSTD = {"compression": "zstd", "compression_level": 9}


class _TableWriter:
    """One Parquet table written a run of rows at a time, in row groups of ``group`` rows.

    Whole row groups are written as they fill, so the file is the same bytes however the
    runs were cut (partitions, upgrade chunks, an index held in memory).
    """

    def __init__(self, path: Path, schema: pa.Schema, group: int, **options: Any) -> None:
        self.writer = pq.ParquetWriter(path, schema, **ZSTD, **options)
        self.schema, self.group = schema, group
        self.pending: list[list[np.ndarray]] = [[] for _ in schema.names]
        self.held = 0

    def write(self, *columns: np.ndarray) -> None:
        for held, x in zip(self.pending, columns, strict=True):
            held.append(x)
        self.held += len(columns[0])
        if self.held >= self.group:
            self._flush(self.held // self.group * self.group)

    def _flush(self, n: int) -> None:
        joined = [np.concatenate(held) if len(held) > 1 else held[0] for held in self.pending]
        self.writer.write_table(pa.table([pa.array(x[:n], f.type) for x, f in zip(joined, self.schema, strict=True)],
                                         schema=self.schema), row_group_size=self.group)
        self.pending = [[x[n:]] for x in joined]
        self.held -= n

    def close(self) -> None:
        if self.held:
            self._flush(self.held)
        self.writer.close()


class _Tables:
    """``codes.parquet``, ``lists.parquet`` and ``buckets.parquet`` of one directory, written in order.

    :meth:`codes` takes places' addresses run by run (from place 0 on), :meth:`lists` runs of
    lists in address order, each list's ids with its single best first (the engine's order,
    which every writer holds); :meth:`close` returns the layout that ``index.json`` records.
    """

    def __init__(self, out: Path, n_ref: int, d: int, k: int, check: TableCheck | None = None) -> None:
        self.n_ref, self.d, self.k, self.check = n_ref, d, k, check  # check: what an untrusted source passes
        self.id_type = pa.uint32() if n_ref <= 1 << 32 else pa.uint64()
        delta = "DELTA_BINARY_PACKED"
        self.codes_table = _TableWriter(out / "codes.parquet",
                                        pa.schema([("ref_id", self.id_type), ("hash", pa.uint64())]), PLACE_GROUP,
                                        use_dictionary=False, column_encoding={"ref_id": delta, "hash": "PLAIN"},
                                        write_page_index=True)
        self.lists_table = _TableWriter(out / "lists.parquet",
                                        pa.schema([("hash", pa.uint64()), ("ref_id", self.id_type),
                                                   ("best", pa.bool_())]), PLACE_GROUP,
                                        use_dictionary=False,
                                        column_encoding={"hash": delta, "ref_id": delta, "best": "PLAIN"},
                                        write_page_index=True)
        self.buckets_table = _TableWriter(out / "buckets.parquet",
                                          pa.schema([("hash", pa.uint64()), ("size", pa.uint32()),
                                                     ("offset", pa.uint64())]), BUCKET_GROUP,
                                          use_dictionary=["size"], column_encoding={"hash": delta, "offset": delta},
                                          write_page_index=True)
        self.n_codes = self.n_ids = self.n_lists = self.longest = 0

    def codes(self, a: int, h: np.ndarray) -> None:
        """The addresses of the next places, ``a … a + len(h) − 1``."""
        if a != self.n_codes:
            raise ValueError(f"codes of places from {a:,}: the next place is {self.n_codes:,}")
        if self.check:
            self.check.codes(np.asarray(h, np.uint64))
        self.codes_table.write(np.arange(a, a + len(h), dtype=np.uint64), np.asarray(h, np.uint64))
        self.n_codes += len(h)

    def lists(self, addresses: np.ndarray, sizes: np.ndarray, ids: np.ndarray) -> None:
        """The next run of occupied addresses (ascending), their lists' sizes and ids (best first)."""
        sizes = np.asarray(sizes, np.int64)
        starts = np.r_[0, np.cumsum(sizes)].astype(np.int64)
        order = np.array(ids, np.int64)
        best = ascending_with_best(order, starts)
        addresses = np.asarray(addresses, np.uint64)
        if self.check:
            self.check.lists(addresses, sizes, order)
        self.lists_table.write(np.repeat(addresses, sizes), order.view(np.uint64), best)  # ids ≥ 0: no copy
        self.buckets_table.write(addresses, sizes.astype(np.uint32), (self.n_ids + starts[:-1]).astype(np.uint64))
        self.n_ids += len(order)
        self.n_lists += len(addresses)
        self.longest = max(self.longest, int(np.max(sizes, initial=0)))

    def close(self) -> dict[str, Any]:
        for table in (self.codes_table, self.lists_table, self.buckets_table):
            table.close()
        return {"tables": list(TABLES), "code_bits": code_bits(self.d, self.k),
                "id_bits": width(max(0, self.n_ref - 1)), "longest": self.longest,
                "occupied": {"count": self.n_lists}, "rows_per_group": {"places": PLACE_GROUP,
                                                                        "buckets": BUCKET_GROUP}}


class TableCheck:
    """The checks an index's tables pass as they are decoded, against the ``n_ref``, ``d`` and ``k``
    of its ``index.json``: what costs nothing beside the decoding, which visits every code and id
    anyway. A forged or damaged table (a code of more than d digits, an id out of range or twice,
    lists out of order) is one error naming it, before a kernel indexes anything by it."""

    def __init__(self, n_ref: int, d: int, k: int) -> None:
        self.n_ref, self.top = n_ref, k**d - 1  # the largest address, as a Python int (2^64 − 1 at most)
        self.n_codes = self.n_ids = 0
        self.last = -1  # the last occupied address seen
        self.seen = np.zeros(n_ref, bool)

    def codes(self, h: np.ndarray) -> None:
        self.n_codes += len(h)
        if self.n_codes > self.n_ref:
            raise ValueError(f"codes.parquet holds more than index.json's {self.n_ref:,} places")
        if len(h) and int(h.max()) > self.top:
            raise ValueError(f"codes.parquet holds an address above K^d − 1 = {self.top:,}")

    def lists(self, addresses: np.ndarray, sizes: np.ndarray, ids: np.ndarray) -> None:
        """A run of lists (addresses ascending, sizes, ids ascending within each list)."""
        if not len(addresses):
            return
        if int(addresses[0]) <= self.last or (len(addresses) > 1 and (addresses[1:] <= addresses[:-1]).any()):
            raise ValueError("buckets.parquet's addresses are not strictly ascending")
        if int(addresses[-1]) > self.top:
            raise ValueError(f"buckets.parquet holds an address above K^d − 1 = {self.top:,}")
        if (sizes < 1).any():
            raise ValueError("buckets.parquet holds an empty list")
        if len(ids) and (int(ids.min()) < 0 or int(ids.max()) >= self.n_ref):
            raise ValueError(f"lists.parquet holds a ref_id outside 0 … {self.n_ref - 1:,}")
        step = np.diff(ids)
        step[np.cumsum(sizes)[:-1] - 1] = 1  # a list's first id may be below the last list's last
        if (step <= 0).any():
            raise ValueError("lists.parquet's ids are not strictly ascending within a list")
        self.seen[ids] = True
        self.last = int(addresses[-1])
        self.n_ids += len(ids)

    def close(self) -> None:
        """Every place has its code and sits in one list: n_ref ids below n_ref, all seen, are each once."""
        if self.n_codes != self.n_ref or self.n_ids != self.n_ref or not self.seen.all():
            raise ValueError(f"the index's tables hold {self.n_codes:,} codes and {self.n_ids:,} ids "
                             f"({int(self.seen.sum()):,} distinct), not index.json's {self.n_ref:,} of each")


def fill_from_tables(path: Path) -> Callable[[EngineWriter], None]:
    """What decodes the tables of the index ``path`` into an :class:`EngineWriter`: its codes,
    then its lists (each list's best moved to its front, the engine's order), streamed and
    checked (:class:`TableCheck`) on the way."""

    def fill(writer: EngineWriter) -> None:
        check = TableCheck(writer.n_ref, writer.d, writer.k)
        a = 0
        for batch in pq.ParquetFile(path / "codes.parquet").iter_batches(DECODE_ROWS, columns=["hash"]):
            h = batch.column(0).to_numpy()
            check.codes(h)
            writer.codes(a, h)
            a += len(h)
        ids = pq.ParquetFile(path / "lists.parquet").iter_batches(DECODE_ROWS, columns=["ref_id", "best"])
        held_ids, held_best = np.zeros(0, np.int64), np.zeros(0, bool)
        for batch in pq.ParquetFile(path / "buckets.parquet").iter_batches(DECODE_ROWS, columns=["hash", "size"]):
            addresses, sizes = (batch.column(i).to_numpy() for i in (0, 1))
            need = int(sizes.sum(dtype=np.int64))
            while len(held_ids) < need:
                more = next(ids, None)
                if more is None:
                    raise ValueError("lists.parquet holds fewer rows than buckets.parquet's sizes")
                held_ids = np.concatenate([held_ids, more.column(0).to_numpy().astype(np.int64)])
                held_best = np.concatenate([held_best, more.column(1).to_numpy(zero_copy_only=False)])
            starts = np.r_[0, np.cumsum(sizes, dtype=np.int64)]
            order, best = held_ids[:need], held_best[:need]
            check.lists(addresses, sizes.astype(np.int64), order)
            if len(sizes) and not (np.add.reduceat(best.astype(np.int64), starts[:-1]) == 1).all():
                raise ValueError("lists.parquet's best column does not mark one single best a list")
            best_first(order, starts, order[best])
            writer.lists(addresses, sizes, order)
            held_ids, held_best = held_ids[need:], held_best[need:]
        if next(ids, None) is not None or len(held_ids):
            raise ValueError("lists.parquet holds more rows than buckets.parquet's sizes")
        check.close()

    return fill


def _best_first_run(order: np.ndarray, sizes: np.ndarray, best: np.ndarray) -> np.ndarray:
    """``order`` (ids ascending per list) with each list's single best moved to its front (a best
    that is not in its list is an error: the kernel would search past the list for it)."""
    order, starts = np.array(order, np.int64), np.r_[0, np.cumsum(sizes)].astype(np.int64)
    best = np.asarray(best, np.int64)
    if len(best) and not (np.add.reduceat(order == np.repeat(best, sizes), starts[:-1]) == 1).all():
        raise ValueError("a list's single best is not one of its ids")
    best_first(order, starts, best)
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
    writer = _Tables(out, n_ref, d, k)
    # every place's address once more, for the partitioned sort to read back; removed at the end
    ref_hash = allocated_memmap(out / ".ref_hash.tmp", addr_t, (n_ref,))
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
    writer = _Tables(path, n_ref, d, k)
    writer.codes(0, ref_hash)
    offsets = lists.starts.decode()
    writer.lists(lists.occupied.decode(), np.diff(offsets), lists.ids_range(0, lists.n_ids))
    write_model(path, hasher, level_counts(ref_hash, d, k), n_ref)
    return write_meta(path, hasher, n_ref, writer.close(), extra)


def upgrade(old: Path, out: Path, quiet: bool = False) -> dict[str, Any]:
    """Convert a format-2 or format-3 index directory ``old`` into the current format in ``out``
    (existing, empty), without refitting: the same addresses, lists and single bests, streamed
    in bounded memory.

    Returns the new ``index.json``; its storage accounting is the caller's to refresh.
    """
    meta = json.loads((old / "index.json").read_text())
    d, k, n_ref, fmt = int(meta["d"]), int(meta["k"]), int(meta["n_ref"]), int(meta["format"])
    try:
        source = _format_2(old) if fmt == 2 else _format_3(old, meta["layout"], n_ref, d, k)
    except (OSError, ValueError, EOFError, KeyError) as exc:
        raise InputError(f"{old}: a format-{fmt} index file is missing or damaged "
                         f"({str(exc).splitlines()[0][:200]}); re-run vprscale index") from None
    codes, occupied, lists = source
    check = TableCheck(n_ref, d, k)
    writer = _Tables(out, n_ref, d, k, check)
    chunk = 1 << 24
    try:
        progress = None if quiet else ChunkProgress("upgrade: codes", -(-n_ref // chunk))
        for a in range(0, n_ref, chunk):
            writer.codes(a, codes(a, min(n_ref, a + chunk)))
            if progress:
                progress.update(1)
        progress = None if quiet else ChunkProgress("upgrade: lists", -(-occupied // UPGRADE_LISTS))
        for a in range(0, occupied, UPGRADE_LISTS):
            writer.lists(*lists(a, min(occupied, a + UPGRADE_LISTS)))
            if progress:
                progress.update(1)
        check.close()
    except (ValueError, IndexError) as exc:
        raise InputError(f"{old}: the format-{fmt} index's arrays do not agree with its index.json "
                         f"({str(exc).splitlines()[0][:200]}); re-run vprscale index") from None
    layout = writer.close()
    (out / "model").mkdir(exist_ok=True)
    for name in MODEL:
        shutil.copy2(old / "model" / f"{name}.npy", out / "model" / f"{name}.npy")
    shutil.copy2(old / "components.parquet", out / "components.parquet")
    meta.update({"format": INDEX_FORMAT, "layout": layout, "occupied": int(layout["occupied"]["count"]),
                 "upgraded_from": fmt})
    (out / "index.json").write_text(json.dumps(meta, indent=1, default=str))
    return meta


Lists = Callable[[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]]


def _format_2(old: Path) -> tuple[Reader, int, Lists]:
    """Format 2's places' addresses, its number of lists and its lists ``a … b − 1`` as
    ``(addresses, sizes, ids best first)``: plain arrays, bests apart."""
    arrays = {name: np.load(old / f"{name}.npy", mmap_mode="r")
              for name in ("ref_hash", "ids", "addresses", "offsets", "best")}

    def lists(a: int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        offsets = np.asarray(arrays["offsets"][a : b + 1], np.int64)
        sizes = np.diff(offsets)
        return (arrays["addresses"][a:b], sizes,
                _best_first_run(arrays["ids"][offsets[0] : offsets[-1]], sizes, arrays["best"][a:b]))

    return lambda a, b: arrays["ref_hash"][a:b], len(arrays["addresses"]), lists


def _format_3(old: Path, layout: dict[str, Any], n_ref: int, d: int, k: int) -> tuple[Reader, int, Lists]:
    """Format 3's, from its succinct files (the engine's own form, :mod:`vprscale.method.engine`)."""
    codes, inverted = open_engine(old, layout, n_ref, d, k)
    bits = code_bits(d, k)

    def lists(a: int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        offsets = inverted.starts.decode(a, b + 1)
        return inverted.occupied.decode(a, b), np.diff(offsets), inverted.ids_range(offsets[0], offsets[-1])

    return (lambda a, b: decode_codes(codes, bits, d, k, np.int64(a), np.int64(b)), inverted.n_lists, lists)


def read_lists(path: str | Path) -> tuple[np.ndarray, InvertedLists, dict[str, Any]]:
    """``(codes, lists, meta)`` of an index directory, as the query engine holds them (decoded
    from the tables, :mod:`vprscale.method.engine`): what a tool that reads no model needs
    (``vprscale occupancy``), without importing the estimator."""
    path = Path(path)
    meta = load_index_meta(path)
    _model(path, meta, mmap="r")
    try:
        codes, lists = engine_arrays(path, int(meta["n_ref"]), int(meta["d"]), int(meta["k"]), fill_from_tables(path))
    except (OSError, ValueError, EOFError, KeyError, pa.ArrowException) as exc:  # a damaged table
        raise InputError(f"{path}: an index table cannot be read ({str(exc).splitlines()[0][:200]}); "
                         "re-run vprscale index") from None
    return codes, lists, meta


def read_arrays(path: str | Path) -> tuple[CoarseHasher, np.ndarray, InvertedLists, dict[str, Any]]:
    """``(hasher, codes, lists, meta)`` of an index directory: the model read, the codes and the
    lists memory-mapped."""
    codes, lists, meta = read_lists(path)
    return read_model(Path(path), meta), codes, lists, meta


def _model(path: Path, meta: dict[str, Any], mmap: str | None = None) -> dict[str, np.ndarray]:
    """The model's arrays (``mmap="r"``: mapped, only their headers read), of the shapes that
    ``index.json``'s ``d``, ``k`` and ``dim`` give them, else an error naming the file."""
    try:
        model = {name: np.load(path / "model" / f"{name}.npy", mmap_mode=mmap) for name in MODEL}
    except (OSError, ValueError, EOFError) as exc:  # a missing or truncated file (no manifest)
        raise InputError(f"{path}: an index file is missing or damaged ({str(exc).splitlines()[0][:200]}); "
                         "re-run vprscale index") from None
    d, k = int(meta["d"]), int(meta["k"])
    dim = int(meta["dim"]) if meta.get("dim") is not None else model["mean"].shape[-1]  # older: the model says
    want = {"mean": (dim,), "components": (d, dim), "centres": (d, k), "explained_variance": (d,)}
    for name, shape in want.items():
        if model[name].shape != shape or model[name].dtype.kind != "f":
            raise InputError(f"{path}: model/{name}.npy is {model[name].dtype} {model[name].shape}, where index.json "
                             f"(d = {d}, k = {k}, dim = {dim}) says float {shape}; re-run vprscale index")
    return model


def read_model(path: Path, meta: dict[str, Any]) -> CoarseHasher:
    """The fitted CoarseHasher of the index directory ``path`` (whose ``index.json`` is ``meta``)."""
    from vprscale.method.coarsehash import CoarseHasher

    model = _model(path, meta)
    return CoarseHasher.from_fitted(int(meta["k"]), int(meta.get("bins", 1 << 14)), int(meta["n_ref"]), **model)
