"""``vprscale encode``: a store's references encoded by FAISS methods, once, resumably, beside the store.

An evaluation that compares FAISS codes (``eval --compare``) needs every reference encoded.
At 100M and 1B places that is one or two passes over references a compact store has to
recompute from its sources (:mod:`vprscale.dataset.references`), far longer than the
evaluation itself, so it is a job of its own, like a build:

1. the training sample: the same evenly spaced references an evaluation trains on
   (:func:`~vprscale.compared.faisscodes.training_rows`), drawn in one streamed pass for all
   the methods (chunks that hold none are not read); every method trained on it, each on one
   thread (their trained indexes must not depend on ``--workers``), and saved;
2. one pass over the references for all the methods, chunk by chunk (Dask tasks,
   ``--workers`` at a time): each chunk read (a compact store's recomputed) once, each
   method's codes written in place into its code array, and the IVF methods of one coarse
   quantiser (the same trained centroids: the same k-means on the same sample) assigning
   the rows to their lists once between them, the most costly step of an IVF code (4,096
   distances a row); a checkpoint after every group of chunks
   (:func:`~vprscale.core.passes.reduce_pass`), so a killed run resumes where it stopped;
3. each method's directory published whole (:mod:`vprscale.core.publish`).

Every task encodes its rows in fixed blocks on one FAISS thread, exactly as an evaluation
encodes them in process: the same bytes for any ``--workers``, local or distributed.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
import uuid
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from vprscale.compared.encoding import (
    describe,
    encoding_dir,
    read_trained,
    write_graph,
    write_searched,
    write_trained,
)
from vprscale.compared.faisscodes import ENCODE_ROWS, FaissCodes, training_rows
from vprscale.compared.pooled import is_pooled
from vprscale.core import deadline
from vprscale.core.cluster import cluster_peak_rss, dask_client
from vprscale.core.errors import InputError
from vprscale.core.localcopy import cache_folder, upload
from vprscale.core.manifest import NAME as MANIFEST
from vprscale.core.manifest import read_record
from vprscale.core.objects import Remote, cache_root, location
from vprscale.core.passes import reduce_pass
from vprscale.core.progress import ChunkProgress, Timings
from vprscale.core.provenance import provenance
from vprscale.core.publish import PartialOutput, check_writable, exclusive
from vprscale.dataset.references import reference_reader
from vprscale.dataset.store import ATTR, open_complete_group, store_identity

log = logging.getLogger(__name__)

ENCODE_GROUP = 16  # chunks encoded between checkpoints (more with more workers)
SAMPLE_GROUP = 64  # chunks read between checkpoints of the training sample (each rewrites the rows kept so far)


class _EncodeChunk:
    """Pass task: encode the references ``[a, b)`` with every method of the pass and write each
    one's codes in place: the rows are read (a compact store's recomputed) once for them all,
    and methods of one coarse quantiser (:attr:`FaissCodes.coarse_key`) share its assignment."""

    def __init__(self, read: Any, outs: list[str], factories: list[str], dim: int) -> None:
        self.read, self.outs, self.factories, self.dim = read, outs, factories, dim
        self._codes: list[tuple[FaissCodes, bytes | None]] | None = None

    def __call__(self, a: int, b: int) -> None:
        if self._codes is None:  # read once per process (threads share them: encoding is read-only)
            trained = [read_trained(Path(o), f, self.dim) for o, f in zip(self.outs, self.factories, strict=True)]
            self._codes = [(method, method.coarse_key) for method in trained]
        rows = self.read(a, b)
        lists: dict[bytes, np.ndarray] = {}
        for out, (method, key) in zip(self.outs, self._codes, strict=True):
            if key is not None and key not in lists:
                lists[key] = method.assign_rows(rows, a)
            codes = method.encode_rows(rows, a, lists.get(key))
            stored = np.load(Path(out) / "codes.npy", mmap_mode="r+")
            stored[a:b] = codes
            stored.flush()
            del stored


class _Pick:
    """Pass task: the rows of ``wanted`` (ascending) among the references ``[a, b)``."""

    def __init__(self, read: Any, wanted: np.ndarray) -> None:
        self.read, self.wanted = read, wanted

    def __call__(self, a: int, b: int) -> np.ndarray:
        rows = self.wanted[(self.wanted >= a) & (self.wanted < b)]
        return self.read(a, b)[rows - a] if len(rows) else np.zeros((0, 0), np.float32)


def _sample(work: Path, read: Any, bounds: list[tuple[int, int]], rows: np.ndarray, quiet: bool) -> np.ndarray:
    """The references at ``rows`` (ascending), streamed: a group of chunks at a time, only the
    chunks that hold some, keeping only those rows (resumable like every pass)."""
    starts = np.array([a for a, _ in bounds])
    holding = [bounds[c] for c in np.unique(np.searchsorted(starts, rows, side="right") - 1)]
    parts = reduce_pass(work, "training sample", holding, _Pick(read, rows), lambda s, r: [*s, r], [],
                        group=SAMPLE_GROUP, quiet=quiet)
    return np.concatenate([p for p in parts if p.size])


def encode_store(store: str | Path | Remote, factories: list[str], deep1b: str | None = None, fas: str | None = None,
                 workers: int = 2, scheduler: str | None = None, force: bool = False,
                 quiet: bool = False) -> dict[str, Any]:
    """Encode the references of ``store`` with each FAISS ``factory``; a summary per method."""
    if not factories:
        raise InputError("encode: give at least one --compare FACTORY")
    if len(set(factories)) != len(factories):
        raise InputError(f"--compare: {next(f for f in factories if factories.count(f) > 1)} given twice")
    for f in factories:
        if is_pooled(f):
            raise InputError(f"--compare {f}: a pooled sequence descriptor is encoded by vprscale eval, one "
                             "encoding per L; vprscale encode stores frame codes only")
    store = store if isinstance(store, Remote) else location(store)
    group = open_complete_group(store)
    meta = group.attrs[ATTR]
    dim, identity = int(meta["recipe"]["dim"]), store_identity(group)
    methods = {f: FaissCodes(f, dim, k=1) for f in factories}  # a bad factory string: refused before any work
    n_ref = int(meta["layout"].get("n_ref") or group["ref"].shape[0])
    for f, m in methods.items():
        if m.ivf is not None and m.ivf.nlist > n_ref:
            raise InputError(f"--compare {f}: {m.ivf.nlist:,} inverted lists for {n_ref:,} references")
    check_writable(encoding_dir(store, factories[0]).parent)
    if isinstance(store, Remote):  # FAISS writes files: an encoding there is made in the cache, then uploaded
        check_writable(cache_root())
    timings = Timings(quiet)
    summary: dict[str, Any] = {"store": str(store), "n_ref": n_ref, "dim": dim, "methods": {}}
    t0 = time.perf_counter()
    with dask_client(scheduler, workers) as client, ExitStack() as locks:
        read, bounds = reference_reader(store, group, deep1b, fas)  # refits a compact store's transforms as its build
        jobs = []
        for f in factories:
            target = encoding_dir(store, f)
            remote = target if isinstance(target, Remote) else None
            out = cache_folder(remote) if remote else target
            locks.enter_context(exclusive(out))
            partial_out = PartialOutput(out, {"encode": f, "store_identity": identity})
            if partial_out.recover() and not quiet:
                log.info(f"{out}: finished publishing the encoding a killed run had completed")
            if _encoded(target, identity) and not force:
                summary["methods"][f] = {"out": str(target), "skipped": True}
                continue
            partial_out.open()
            jobs.append(_Job(f, methods[f], partial_out, remote))
        if jobs:
            _train(jobs, read, bounds, timings, quiet)
            _encode(jobs, read, bounds, dim, workers, timings, quiet)
        for job in jobs:
            summary["methods"][job.factory] = _finish(job, n_ref, dim, identity, workers, timings, quiet)
            if job.remote:
                upload(job.partial_out.final, job.remote)
                summary["methods"][job.factory]["out"] = str(job.remote)
        summary["peak_rss_bytes"] = cluster_peak_rss(client)
    summary["wall_s"] = time.perf_counter() - t0
    return summary


def _encoded(out: Path | Remote, identity: str) -> bool:
    """Whether ``out`` holds a published encoding of this store (on object storage: with its manifest)."""
    if not (out / "encoding.json").is_file() or (isinstance(out, Remote) and not (out / MANIFEST).is_file()):
        return False
    return read_record(out / "encoding.json").get("store_identity") == identity


@dataclass
class _Job:
    """One method's encoding in the making."""

    factory: str
    method: FaissCodes
    partial_out: PartialOutput
    remote: Remote | None
    started: float = field(default_factory=time.perf_counter)

    def __post_init__(self) -> None:
        self.work.mkdir(exist_ok=True)  # checkpoints and the on-disk lists' shards

    @property
    def work(self) -> Path:
        return self.partial_out.path / ".work"

    @property
    def array_id(self) -> str:
        """A name drawn when this method's code array was made (one made before names were drawn
        gets one now): the same array keeps it across resumed runs, a new one never shares it."""
        path = self.work / "codes.id"
        if not path.is_file():
            path.write_text(uuid.uuid4().hex)
        return path.read_text()


def _train(jobs: list[_Job], read: Any, bounds: list[tuple[int, int]], timings: Timings, quiet: bool) -> None:
    """Train every method not yet trained, on one streamed sample of the training references
    (every method trains on the same rows), and save each trained index."""
    untrained = [j for j in jobs if not j.partial_out.done("trained")]
    if not untrained:
        return
    n_ref = bounds[-1][1]
    rows = training_rows(n_ref)
    with timings.stage(f"training sample: {len(rows):,} evenly spaced references"):
        sample = _sample(untrained[0].work, read, bounds, rows, quiet)  # checkpointed with the first to train
    for job in untrained:
        with timings.stage(f"{job.factory}: train"):
            with threadpool_limits(limits=1, user_api="blas"):  # one thread: the same trained index for any workers
                job.method.train(sample)
            write_trained(job.method, job.partial_out.path, n_ref)
            (job.work / "codes.id").unlink(missing_ok=True)  # a new code array: a new name
        job.partial_out.mark("trained")


def _encode(jobs: list[_Job], read: Any, bounds: list[tuple[int, int]], dim: int, workers: int, timings: Timings,
            quiet: bool) -> None:
    """Encode every reference with every method not yet encoded, in one resumable pass."""
    pending = [j for j in jobs if not j.partial_out.done("encoded")]
    if not pending:
        return
    names = [j.factory for j in pending]
    task = _EncodeChunk(read, [str(j.partial_out.path) for j in pending], names, dim)
    # The checkpoint names its methods' code arrays (each named when made, at training): a run with
    # another set of methods, or with one of them started afresh since, starts the pass over.
    arrays = " ".join(f"{j.factory}@{j.array_id}" for j in pending)
    with timings.stage(f"encode {bounds[-1][1]:,} references: {', '.join(names)}"):
        reduce_pass(pending[0].work, f"encode {' + '.join(names)}", bounds, task, lambda s, _: s, None,
                    group=max(ENCODE_GROUP, 2 * workers), quiet=quiet,
                    checkpoint=f"encode-{hashlib.sha256(arrays.encode()).hexdigest()[:16]}")
    for job in pending:
        job.partial_out.mark("encoded")


def _finish(job: _Job, n_ref: int, dim: int, identity: str, workers: int, timings: Timings,
            quiet: bool) -> dict[str, Any]:
    """A method's lists and records (or its graph) from its codes, its record, published; its summary."""
    factory, method, partial_out = job.factory, job.method, job.partial_out
    # each step below is one unit (a graph's link: most of an hour at 10M): under a budget
    # (vprscale run --budget) none starts once the budget is spent; the codes are kept
    if method.records_on_disk or (method.graph and not partial_out.done("graph")):
        deadline.check(0.0, f"{factory}: every reference encoded, its {'graph' if method.graph else 'lists'} "
                       "not written yet")
    if method.records_on_disk:
        with timings.stage(f"{factory}: inverted lists on disk and window records"):
            write_searched(partial_out.path, factory, dim, partial_out.done, partial_out.mark)
    elif method.graph and not partial_out.done("graph"):
        with timings.stage(f"{factory}: link the graph"):
            bar = None if quiet else ChunkProgress(f"link {factory}", -(-n_ref // ENCODE_ROWS), unit="blocks")
            write_graph(partial_out.path, factory, dim, bar.update if bar else None)
        partial_out.mark("graph")
    record = provenance(inputs={"store_identity": identity, "factory": factory}, workers=workers)
    (partial_out.path / "encoding.json").write_text(json.dumps(
        describe(factory, identity, n_ref, len(training_rows(n_ref)), record), indent=1))
    partial_out.publish()
    return {"out": str(partial_out.final), "wall_s": time.perf_counter() - job.started,
            "code_bytes": int(method.code_bytes)}
