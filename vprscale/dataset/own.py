"""``vprscale build --ref REF --query NAME=QUERY … --gt GT``: your own descriptors as a store
(docs/bring-your-own.md).

Writes the full layout of docs/dataset.md that ``index``, ``eval --noise NAME``, ``report``
and the SQL console read: ``ref``, one ``query_<NAME>`` per query set (rows aligned with
each other: the same traverse seen in different conditions), ``gt`` (the reference row of
each query row, −1 for none) and the parts. Rows stream chunk by chunk, one task per
chunk, checked for NaN and Inf, into a hidden work copy that is published whole; a killed
build resumes where it stopped.

Query rows may come in two parts (``--part``: 0 for every row of the first, then 1),
reported as the ``deep1b`` and ``fas`` parts of the protocol; without it every row is part 0.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import dask
import numpy as np
import zarr

from vprscale.core.blocks import BLOCK, chunk_bounds
from vprscale.core.cluster import cluster_peak_rss, dask_client
from vprscale.core.errors import InputError
from vprscale.core.progress import Timings, run_tasks
from vprscale.core.provenance import provenance
from vprscale.core.publish import PartialOutput, check_writable, exclusive
from vprscale.dataset.layout import codecs, consolidate
from vprscale.dataset.shuffle import reorder_into
from vprscale.dataset.sources.base import RowSource
from vprscale.dataset.sources.rows import open_rows, read_labels, read_positions, read_sequences
from vprscale.dataset.store import ATTR

log = logging.getLogger(__name__)

CHUNK_ROWS = 16 * BLOCK  # rows per Zarr chunk and per task, at most
CHUNK_BYTES = 32 << 20  # bytes of one chunk (and of what one task holds), at most, unless one row is larger
MAX_ROW_BYTES = 1 << 30  # a single descriptor this large is no descriptor
NAME = re.compile(r"[a-z][a-z0-9_]{0,30}")


@dataclass
class OwnRequest:
    """What ``vprscale build --ref`` was asked for."""

    ref: str
    queries: dict[str, str]  # noise name → file
    gt: str | None  # None: each query row's nearest reference by position, within gt_radius_m
    out: Path
    part: str | None = None
    name: str | None = None  # the store's (and results' scale column's) name; default: the ref file's stem
    ref_pos: str | None = None  # positions in metres of the references and of the query rows (both or neither)
    query_pos: str | None = None
    ref_seq: str | None = None  # many sequences: each row's sequence and frame number (both or neither)
    query_seq: str | None = None
    stride: int = 1  # the evaluation's default query stride z
    gt_radius_m: float = 25.0  # without --gt: how far a query row's nearest reference may be to be its truth
    force: bool = False
    workers: int = 2
    scheduler: str | None = None
    quiet: bool = False


def parse_query(text: str) -> tuple[str, str]:
    """``NAME=PATH`` of ``--query``, the name checked (it names an array and the noise column)."""
    name, sep, path = text.partition("=")
    if not sep or not path:
        raise InputError(f"--query {text}: give NAME=PATH, e.g. --query night=night.npy")
    if not NAME.fullmatch(name):
        raise InputError(f"--query {text}: the name must be lower-case letters, digits and _, starting with a letter")
    return name, path


def _digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16]


def check_inputs(req: OwnRequest) -> tuple[RowSource, dict[str, RowSource], np.ndarray, np.ndarray]:
    """Open and check every input before anything is written: one line naming the file and what is wrong."""
    if not req.queries:
        raise InputError("--query: give at least one query set, NAME=PATH")
    if req.stride < 1:
        raise InputError(f"--stride {req.stride}: must be at least 1")
    ref = open_rows(req.ref)
    queries = {name: open_rows(path) for name, path in req.queries.items()}
    n_query = None
    for q in queries.values():
        if q.dim != ref.dim:
            raise InputError(f"{q.name}: query rows have {q.dim} dimensions, the references {ref.dim}")
        if n_query is not None and q.n_rows != n_query:
            raise InputError(f"{q.name}: {q.n_rows:,} rows, but the other query sets have {n_query:,}: query sets "
                             "are the same traverse in other conditions, row for row")
        n_query = q.n_rows
    if req.gt is None and (req.ref_pos is None or req.query_pos is None):
        raise InputError("--gt missing: give each query row's reference row, or --ref-pos and --query-pos to take "
                         "the nearest reference by position")
    gt = np.full(n_query, -1, np.int64) if req.gt is None else read_labels(req.gt, n_query, "ground truth")
    bad = np.flatnonzero((gt < -1) | (gt >= ref.n_rows))
    if len(bad):
        raise InputError(f"{req.gt}: row {bad[0]:,} holds {gt[bad[0]]}, not a reference row (0 … {ref.n_rows - 1:,}) "
                         "or −1 (no truth)")
    if req.gt is not None and not (gt >= 0).any():
        raise InputError(f"{req.gt}: no query row has a truth (all −1): nothing could be evaluated")
    part = np.zeros(n_query, np.int64) if req.part is None else read_labels(req.part, n_query, "part")
    if not np.isin(part, (0, 1)).all() or (np.diff(part) < 0).any():
        raise InputError(f"{req.part}: parts must be 0 for the first query rows, then 1 for the rest")
    return ref, queries, gt, part


def check_positions(req: OwnRequest, n_ref: int, n_query: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The references' and query rows' positions (``--ref-pos``, ``--query-pos``), read and checked;
    None without them. Both or neither: a radius in metres needs both ends."""
    if (req.ref_pos is None) != (req.query_pos is None):
        raise InputError(f"--{'query' if req.query_pos is None else 'ref'}-pos missing: positions in metres need "
                         "both the references' (--ref-pos) and the query rows' (--query-pos)")
    if req.ref_pos is None:
        return None
    ref_pos = read_positions(req.ref_pos, n_ref, "reference positions")
    query_pos = read_positions(req.query_pos, n_query, "query positions")
    if ref_pos.shape[1] != query_pos.shape[1]:
        raise InputError(f"{req.query_pos}: {query_pos.shape[1]} coordinates a row, the reference positions have "
                         f"{ref_pos.shape[1]}")
    return ref_pos, query_pos


def check_sequences(req: OwnRequest, n_ref: int, n_query: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The references' and query rows' sequences (``--ref-seq``, ``--query-seq``), read and checked;
    empty without them. Both or neither: a window is the same thing on either side."""
    if (req.ref_seq is None) != (req.query_seq is None):
        raise InputError(f"--{'query' if req.query_seq is None else 'ref'}-seq missing: sequences need both the "
                         "references' (--ref-seq) and the query rows' (--query-seq)")
    if req.ref_seq is None:
        return {}
    return {"ref": read_sequences(req.ref_seq, n_ref, "reference sequences"),
            "query": read_sequences(req.query_seq, n_query, "query sequences")}


def truth_from_positions(ref_pos: np.ndarray, query_pos: np.ndarray, radius_m: float) -> np.ndarray:
    """Each query row's nearest reference by position (ties: the smaller row), or −1 where none lies
    within ``radius_m`` metres: the truth VPR-methods-evaluation derives from UTM positions."""
    from scipy.spatial import cKDTree

    k = min(16, len(ref_pos))  # ties are broken among the 16 nearest (exact unless more lie at one distance)
    dist, idx = cKDTree(ref_pos).query(query_pos, k=k)
    dist, idx = dist.reshape(len(query_pos), k), idx.reshape(len(query_pos), k)
    nearest = np.where(dist == dist[:, :1], idx, np.iinfo(np.int64).max).min(axis=1)
    return np.where(dist[:, 0] <= radius_m, nearest, -1).astype(np.int64)


def chunk_rows(n_rows: int, row_bytes: int) -> int:
    """Rows per Zarr chunk (and task) of an array of ``n_rows`` rows of ``row_bytes``: as many as
    fit in ``CHUNK_BYTES`` (a power of two, so that every block of ``BLOCK`` rows, which FAISS
    encodes together, starts on a chunk), at most ``CHUNK_ROWS``, and at most the whole array.
    Chunks are stored uncompressed and whole, and a task holds one, so a store costs what its
    data costs: 3 rows of 50,000 dimensions take 600 KB, a million of 4,096 take 2,048-row chunks
    of 32 MiB, never 4 GB a task."""
    fit = 1 << max(0, (CHUNK_BYTES // max(1, row_bytes)).bit_length() - 1)
    return max(1, min(CHUNK_ROWS, fit, n_rows))


def check_room(ref: RowSource, queries: dict[str, RowSource], out: Path) -> None:
    """Refuse, before any work, a store that cannot be written: a row beyond ``MAX_ROW_BYTES``, or
    more bytes than the disk under ``out`` has free."""
    row_bytes = ref.dim * 4
    if row_bytes > MAX_ROW_BYTES:
        raise InputError(f"{ref.name}: rows of {ref.dim:,} dimensions ({row_bytes / 2**30:.1f} GiB each as float32); "
                         f"vprscale stores descriptors of at most {MAX_ROW_BYTES // 4:,} dimensions")
    need = row_bytes * (ref.n_rows + sum(q.n_rows for q in queries.values()))
    free = shutil.disk_usage(out).free
    if need > free:
        raise InputError(f"--out {out}: the store needs {need / 2**30:,.1f} GiB and the disk there has "
                         f"{free / 2**30:,.1f} GiB free")


def build_own(req: OwnRequest) -> dict[str, Any]:
    """Write the store ``<out>/<name>.zarr``; returns the summary the CLI prints."""
    ref, queries, gt, part = check_inputs(req)
    positions = check_positions(req, ref.n_rows, len(gt))
    sequences = check_sequences(req, ref.n_rows, len(gt))
    if req.gt is None:
        if not req.gt_radius_m > 0:
            raise InputError(f"--gt-radius-m {req.gt_radius_m}: must be above 0 metres")
        gt = truth_from_positions(*positions, req.gt_radius_m)
        if not (gt >= 0).any():
            raise InputError(f"--query-pos {req.query_pos}: no query row lies within {req.gt_radius_m:g} m of a "
                             "reference: nothing could be evaluated (check both files' coordinates, or --gt-radius-m)")
    name = req.name or Path(req.ref).stem
    if not NAME.fullmatch(name.lower()) or name != name.lower():
        raise InputError(f"--name {name}: lower-case letters, digits and _, starting with a letter")
    out = Path(req.out).absolute()
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {req.out}: is a file, not a directory")
    final = out / f"{name}.zarr"
    n_deep = int((part == 0).sum())
    identity = {"recipe": {"scale": name, "dim": ref.dim, "query_stride": req.stride, "own": True},
                "sources": {"ref": ref.fingerprint(), **{f"query_{n}": q.fingerprint() for n, q in queries.items()},
                            "gt": _digest(gt), "part": _digest(part),
                            **({"gt_from_positions_within_m": req.gt_radius_m} if req.gt is None else {}),
                            **({"ref_pos": _digest(positions[0]), "query_pos": _digest(positions[1])}
                               if positions else {}),
                            **{f"{side}_seq": _digest(np.stack(seq)) for side, seq in sequences.items()}},
                "rescale": None, "seed": None}
    check_writable(out)
    check_room(ref, queries, out)
    labels = {"gt": gt, "query_part": part.astype(np.uint8), "ref_part": np.zeros(ref.n_rows, np.uint8),
              **{f"{side}_{what}": a for side, seq in sequences.items() for what, a in zip(("seq", "frame"), seq,
                                                                                        strict=True)},
              **({"ref_pos": positions[0], "query_pos": positions[1]} if positions else {})}
    layout = {"kind": "full", "n_deep1b": n_deep, "n_fas_ref": 0, "n_fas_query": len(gt) - n_deep,
              "noises": sorted(queries), **({"positions": int(positions[0].shape[1])} if positions else {}),
              **({"sequences": {side: int(len(np.unique(seq))) for side, (seq, _) in sequences.items()}}
                 if sequences else {})}
    rows = {"ref": StoreRows(ref), **{f"query_{n}": StoreRows(q) for n, q in queries.items()}}
    return write_store(final, identity, rows, labels, layout, req)


@dataclass
class StoreRows:
    """One descriptor array of a store: its source, and the source row of each store row (None:
    every row, in order, copied a chunk per task; else reordered out of core, :mod:`.shuffle`)."""

    source: RowSource
    order: np.ndarray | None = None

    @property
    def n_rows(self) -> int:
        return self.source.n_rows if self.order is None else len(self.order)


def write_store(final: Path, identity: dict[str, Any], rows: dict[str, StoreRows], labels: dict[str, np.ndarray],
                layout: dict[str, Any], req: Any) -> dict[str, Any]:
    """Write the store ``final`` (full layout: descriptor arrays ``rows``, label arrays ``labels``
    as their dtypes, ``layout``) into a hidden work copy and publish it whole; returns the summary
    the CLI prints. ``req`` gives ``force``, ``quiet``, ``workers`` and ``scheduler``."""
    out = final.parent
    check_writable(out)
    t0 = time.perf_counter()
    dim = next(iter(rows.values())).source.dim
    with exclusive(final):
        PartialOutput(final, {}).recover()
        if final.exists() and not (final / "zarr.json").is_file():
            raise InputError(f"--out {out}: {final} exists and is not a dataset store; not replaced")
        if (final / "zarr.json").exists() and not req.force:
            raise InputError(f"--out {out}: {final} already holds a store; --force replaces it (or give another "
                             "--name or --out)")
        partial = PartialOutput(final, json.loads(json.dumps(identity, default=str)))
        resumed = partial.open()
        timings = Timings(req.quiet)
        group = zarr.open_group(str(partial.path), mode="a", zarr_format=3)
        if not partial.done("arrays"):
            for array, r in rows.items():
                group.create_array(array, shape=(r.n_rows, dim), chunks=(chunk_rows(r.n_rows, 4 * dim), dim),
                                   dtype="f4", overwrite=True, **codecs("descriptors"))
            for array, data in labels.items():
                width = int(np.prod(data.shape[1:], dtype=np.int64))
                group.create_array(array, shape=data.shape,
                                   chunks=(chunk_rows(len(data), 8 * width), *data.shape[1:]),
                                   dtype=data.dtype, overwrite=True, **codecs("labels"))
                group[array][:] = data
            partial.mark("arrays")
        for array, r in rows.items():  # a source in another order: read once, in order, into chunk buckets
            if r.order is not None and not partial.done(array):
                with timings.stage(f"reorder {array}"):
                    reorder_into(r.source, r.order, group[array], partial.path / f".{array}-buckets", not req.quiet)
                shutil.rmtree(partial.path / f".{array}-buckets", ignore_errors=True)
                partial.mark(array)
        tasks = [dask.delayed(_copy_chunk)(str(partial.path), array, r.source, a, b, partial, f"{array}-{c}")
                 for array, r in rows.items() if r.order is None
                 for c, (a, b) in enumerate(chunk_bounds(r.n_rows, chunk_rows(r.n_rows, 4 * dim)))
                 if not partial.done(f"{array}-{c}")]
        with dask_client(req.scheduler, req.workers) as client:
            if tasks:
                with timings.stage(f"copy {len(tasks)} chunks"):
                    run_tasks(tasks, "copy chunks")
            peak = cluster_peak_rss(client)
        queries = [a for a in rows if a.startswith("query_")]
        summary = {"store": str(final), "scale": identity["recipe"]["scale"], "layout": "full",
                   "ref_rows": rows["ref"].n_rows, "query_rows": rows[queries[0]].n_rows, "query_sets": len(queries),
                   "resumed": resumed, "stages_s": timings.stages,
                   "wall_s": time.perf_counter() - t0, "peak_rss_bytes": peak,
                   "provenance": provenance(inputs={"sources": identity["sources"]})}
        group.attrs[ATTR] = {**json.loads(json.dumps(identity, default=str)), "complete": True, "layout": layout}
        (partial.path / "build.json").write_text(json.dumps({k: v for k, v in summary.items() if k != "store"},
                                                            indent=1, default=str))
        consolidate(str(partial.path))
        partial.publish()
    if resumed and not req.quiet:
        log.info(f"resumed the unfinished build of {final}")
    summary["bytes_on_disk"] = sum(f.stat().st_size for f in final.rglob("*") if f.is_file())
    return summary


def _copy_chunk(store: str, array: str, source: RowSource, a: int, b: int, partial: PartialOutput,
                unit: str) -> None:
    """One chunk of one array, read (and checked for NaN and Inf) and written whole."""
    zarr.open_array(f"{store}/{array}", mode="r+")[a:b] = source.read(a, b)
    partial.mark(unit)
