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
Labels = str | dict[str, str] | None  # a label file every query set shares, one per set by name, or none


@dataclass
class OwnRequest:
    """What ``vprscale build --ref`` was asked for."""

    ref: str
    queries: dict[str, str]  # noise name → file
    gt: Labels  # None: each query row's nearest reference by position, within gt_radius_m
    out: Path
    part: Labels = None
    name: str | None = None  # the store's (and results' scale column's) name; default: the ref file's stem
    ref_pos: str | None = None  # positions in metres of the references and of the query rows (both or neither)
    query_pos: Labels = None
    ref_seq: str | None = None  # many sequences: each row's sequence and frame number (both or neither)
    query_seq: Labels = None
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


@dataclass
class SetLabels:
    """One query set's labels: each row's truth (−1: none) and part, and optionally its position
    and its (sequence, frame number)."""

    gt: np.ndarray
    part: np.ndarray
    pos: np.ndarray | None = None
    seq: tuple[np.ndarray, np.ndarray] | None = None


def for_set(value: Labels, name: str | None) -> str | None:
    """The file a label flag gives query set ``name``: its own, or the one every set shares."""
    return value.get(name) if isinstance(value, dict) else value


def shared_labels(req: OwnRequest) -> bool:
    """Whether every query set takes the same label files (query sets row for row, the layout of
    one set of labels), rather than each its own (query sets of any lengths)."""
    return not any(isinstance(v, dict) for v in (req.gt, req.part, req.query_pos, req.query_seq))


def check_inputs(req: OwnRequest) -> tuple[RowSource, dict[str, RowSource]]:
    """Open and check the descriptor files before anything is written: one line naming the file and what is wrong."""
    if not req.queries:
        raise InputError("--query: give at least one query set, NAME=PATH")
    if req.stride < 1:
        raise InputError(f"--stride {req.stride}: must be at least 1")
    for flag, value in (("--gt", req.gt), ("--part", req.part), ("--query-pos", req.query_pos),
                        ("--query-seq", req.query_seq)):
        unknown = [n for n in value if n not in req.queries] if isinstance(value, dict) else []
        if unknown:
            raise InputError(f"{flag} {unknown[0]}=…: no query set {unknown[0]} (--query NAME=PATH names them)")
    ref = open_rows(req.ref)
    queries = {name: open_rows(path) for name, path in req.queries.items()}
    n_query = None
    for q in queries.values():
        if q.dim != ref.dim:
            raise InputError(f"{q.name}: query rows have {q.dim} dimensions, the references {ref.dim}")
        if shared_labels(req) and n_query is not None and q.n_rows != n_query:
            raise InputError(f"{q.name}: {q.n_rows:,} rows, but the other query sets have {n_query:,}: query sets "
                             "sharing one --gt are the same traverse row for row; give each its own, --gt NAME=PATH")
        n_query = q.n_rows
    return ref, queries


def set_labels(req: OwnRequest, name: str, n: int, n_ref: int, ref_pos: np.ndarray | None,
               ref_seq: bool) -> SetLabels:
    """Query set ``name``'s labels (``n`` rows), read and checked."""
    gt_file, part_file = for_set(req.gt, name), for_set(req.part, name)
    pos_file, seq_file = for_set(req.query_pos, name), for_set(req.query_seq, name)
    if (ref_pos is None) != (pos_file is None):
        flag = f"--query-pos {name}=…" if isinstance(req.query_pos, dict) else "--query-pos"
        raise InputError(f"{'--ref-pos' if ref_pos is None else flag} missing: positions in metres need both the "
                         "references' (--ref-pos) and the query rows' (--query-pos)")
    if ref_seq != (seq_file is not None):
        flag = f"--query-seq {name}=…" if isinstance(req.query_seq, dict) else "--query-seq"
        raise InputError(f"{'--ref-seq' if not ref_seq else flag} missing: sequences need both the references' "
                         "(--ref-seq) and the query rows' (--query-seq)")
    pos = None
    if pos_file is not None:
        pos = read_positions(pos_file, n, "query positions")
        if ref_pos.shape[1] != pos.shape[1]:
            raise InputError(f"{pos_file}: {pos.shape[1]} coordinates a row, the reference positions have "
                             f"{ref_pos.shape[1]}")
    if gt_file is None:
        if pos is None:
            raise InputError(f"--gt missing{f' for {name}' if isinstance(req.gt, dict) else ''}: give each query "
                             "row's reference row, or --ref-pos and --query-pos to take the nearest reference by "
                             "position")
        if not req.gt_radius_m > 0:
            raise InputError(f"--gt-radius-m {req.gt_radius_m}: must be above 0 metres")
        gt = truth_from_positions(ref_pos, pos, req.gt_radius_m)
        if not (gt >= 0).any():
            raise InputError(f"--query-pos {pos_file}: no query row lies within {req.gt_radius_m:g} m of a "
                             "reference: nothing could be evaluated (check both files' coordinates, or --gt-radius-m)")
    else:
        gt = read_labels(gt_file, n, "ground truth")
        bad = np.flatnonzero((gt < -1) | (gt >= n_ref))
        if len(bad):
            raise InputError(f"{gt_file}: row {bad[0]:,} holds {gt[bad[0]]}, not a reference row "
                             f"(0 … {n_ref - 1:,}) or −1 (no truth)")
        if not (gt >= 0).any():
            raise InputError(f"{gt_file}: no query row has a truth (all −1): nothing could be evaluated")
    part = np.zeros(n, np.int64) if part_file is None else read_labels(part_file, n, "part")
    if not np.isin(part, (0, 1)).all() or (np.diff(part) < 0).any():
        raise InputError(f"{part_file}: parts must be 0 for the first query rows, then 1 for the rest")
    seq = read_sequences(seq_file, n, "query sequences") if seq_file is not None else None
    return SetLabels(gt, part, pos, seq)


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
    ref, queries = check_inputs(req)
    if (req.ref_pos is None) != (req.query_pos is None):
        raise InputError(f"--{'query' if req.query_pos is None else 'ref'}-pos missing: positions in metres need "
                         "both the references' (--ref-pos) and the query rows' (--query-pos)")
    if (req.ref_seq is None) != (req.query_seq is None):
        raise InputError(f"--{'query' if req.query_seq is None else 'ref'}-seq missing: sequences need both the "
                         "references' (--ref-seq) and the query rows' (--query-seq)")
    ref_pos = read_positions(req.ref_pos, ref.n_rows, "reference positions") if req.ref_pos is not None else None
    ref_seq = read_sequences(req.ref_seq, ref.n_rows, "reference sequences") if req.ref_seq is not None else None
    shared = shared_labels(req)
    sets: dict[str, SetLabels] = {}
    for set_name, q in queries.items():  # label files every set shares are read once
        sets[set_name] = (next(iter(sets.values())) if shared and sets else
                          set_labels(req, set_name, q.n_rows, ref.n_rows, ref_pos, ref_seq is not None))
    name = req.name or Path(req.ref).stem
    if not NAME.fullmatch(name.lower()) or name != name.lower():
        raise InputError(f"--name {name}: lower-case letters, digits and _, starting with a letter")
    out = Path(req.out).absolute()
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {req.out}: is a file, not a directory")
    check_writable(out)
    check_room(ref, queries, out)
    labels, sources = _labels(req, ref, queries, sets, ref_pos, ref_seq)
    identity = {"recipe": {"scale": name, "dim": ref.dim, "query_stride": req.stride, "own": True},
                "sources": sources, "rescale": None, "seed": None}
    first = next(iter(sets.values()))
    n_deep = int((first.part == 0).sum())
    layout = {"kind": "full", "n_deep1b": n_deep, "n_fas_ref": 0, "n_fas_query": len(first.gt) - n_deep,
              "noises": sorted(queries), **({"positions": int(ref_pos.shape[1])} if ref_pos is not None else {}),
              **({"sequences": {"ref": int(len(np.unique(ref_seq[0]))),
                                "query": int(len(np.unique(np.concatenate([s.seq[0] for s in sets.values()]))))}}
                 if ref_seq is not None else {}),
              **({"query_sets": {n: {"rows": len(lab.gt), "n_deep1b": int((lab.part == 0).sum())}
                                 for n, lab in sets.items()}} if not shared else {})}
    rows = {"ref": StoreRows(ref), **{f"query_{n}": StoreRows(q) for n, q in queries.items()}}
    return write_store(out / f"{name}.zarr", identity, rows, labels, layout, req)


def _labels(req: OwnRequest, ref: RowSource, queries: dict[str, RowSource], sets: dict[str, SetLabels],
            ref_pos: np.ndarray | None, ref_seq: tuple[np.ndarray, np.ndarray] | None
            ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """``(arrays, sources)``: the label arrays of the store and the record of what they came from.

    Query sets that share their labels (one traverse in several conditions) keep one set of them,
    ``gt``, ``query_part``, ``query_pos``, ``query_seq`` (docs/dataset.md); sets of any lengths
    keep their own, ``query_<name>_gt``, ``query_<name>_part``, …"""
    shared = shared_labels(req)
    labels: dict[str, np.ndarray] = {}
    truth: dict[str, Any] = {}
    placed: dict[str, Any] = {}
    for set_name, lab in (sets.items() if not shared else [(None, next(iter(sets.values())))]):
        prefix, tag = (f"query_{set_name}_", f"_{set_name}") if set_name else ("query_", "")
        labels |= {f"{prefix}gt" if set_name else "gt": lab.gt, f"{prefix}part": lab.part.astype(np.uint8)}
        truth |= {f"gt{tag}": _digest(lab.gt), f"part{tag}": _digest(lab.part)}
        if for_set(req.gt, set_name) is None:
            truth[f"gt_from_positions_within_m{tag}"] = req.gt_radius_m
        if lab.pos is not None:
            labels[f"{prefix}pos"] = lab.pos
            placed[f"query_pos{tag}"] = _digest(lab.pos)
        if lab.seq is not None:
            labels |= {f"{prefix}seq": lab.seq[0], f"{prefix}frame": lab.seq[1]}
            placed[f"query_seq{tag}"] = _digest(np.stack(lab.seq))
    labels["ref_part"] = np.zeros(ref.n_rows, np.uint8)
    # the record in the order earlier versions wrote it: the same store identity for the same inputs
    sources: dict[str, Any] = {"ref": ref.fingerprint(), **{f"query_{n}": q.fingerprint() for n, q in queries.items()},
                               **truth}
    if ref_pos is not None:
        labels["ref_pos"] = ref_pos
        sources |= {"ref_pos": _digest(ref_pos), **{k: v for k, v in placed.items() if k.startswith("query_pos")}}
    if ref_seq is not None:
        labels |= {"ref_seq": ref_seq[0], "ref_frame": ref_seq[1]}
        sources |= {"ref_seq": _digest(np.stack(ref_seq)),
                    **{k: v for k, v in placed.items() if k.startswith("query_seq")}}
    first = ("gt", "query_part", "ref_part", "ref_seq", "ref_frame", "query_seq", "query_frame", "ref_pos", "query_pos")
    return {**{k: labels[k] for k in first if k in labels}, **labels}, sources


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
