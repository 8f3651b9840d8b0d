"""``vprscale build``: stream the sources through docs/dataset.md into ``<out>/<scale>.zarr``.

Two passes over Deep1B. Pass 1 accumulates the moments of the homogenised rows for the
exact PCA, while the FAS PCAs and the noise model are fitted; the fitted transforms are
saved in the store. Pass 2 writes every output chunk in one task: homogenise, project,
rescale, draw the query noise, and write the same row range of ``ref``, ``query_qm1``,
``query_qm2``, ``gt`` and the part labels. Each Zarr chunk is written whole by exactly one
task, so tasks never race and a resumed build simply rewrites unfinished chunks.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import dask
import numpy as np
import zarr
from threadpoolctl import threadpool_limits

import vprscale
from vprscale.core.blocks import BLOCK, chunk_bounds
from vprscale.core.cluster import cluster_peak_rss, dask_client
from vprscale.core.errors import InputError
from vprscale.core.manifest import NAME as MANIFEST
from vprscale.core.objects import Remote, location, zarr_url
from vprscale.core.passes import reduce_pass, run_groups
from vprscale.core.progress import Timings
from vprscale.core.provenance import provenance
from vprscale.core.publish import Output, check_writable, exclusive, output_for
from vprscale.core.throughput import throughput
from vprscale.dataset import compact
from vprscale.dataset.corpora import Corpus, check_corpus
from vprscale.dataset.homogenise import window_mean
from vprscale.dataset.layout import NOISE_LEVELS, ChunkWriter, Layout, codecs, consolidate, grid
from vprscale.dataset.merge import MergeTransform, noisy_rows, project_rows
from vprscale.dataset.recipe import MAX_CHUNK_ROWS, Recipe, load_recipe
from vprscale.dataset.sources.base import RowSource
from vprscale.dataset.sources.fas import Traverse, open_fas
from vprscale.dataset.sources.rows import open_rows
from vprscale.dataset.sources.synthetic import FasParams, SyntheticDeep1B, SyntheticFAS
from vprscale.dataset.store import ATTR
from vprscale.method.coarsehash import hash_descriptors, sample_spans
from vprscale.method.lists import address_dtype
from vprscale.method.pca import block_moments
from vprscale.protocol import EVAL_LENGTHS, MIN_FAS

log = logging.getLogger(__name__)

MAX_MAGNITUDE = 1e18  # homogenised values beyond this overflow float32 once squared or projected
WRITE_BYTES_PER_S = 400e6  # the page cache's write-back on this kind of machine, measured
FIXED_S = 3.0  # start-up (imports, compiled kernels from numba's cache), fitting and publishing, measured here
PARALLEL_EFFICIENCY = 0.8  # two tasks share memory bandwidth and the chunk reads


@dataclass
class BuildRequest:
    """What the user asked for (the CLI's arguments)."""

    scale: str
    out: str | Path  # a local directory or a URL (s3://bucket/prefix)
    deep1b: str | None = None  # the large corpus's file or URL (Deep1B's, or another's: ``corpus``)
    corpus: Corpus | None = None  # the corpus it names, whose published width the file must have
    fas: str | None = None
    workers: int = 2
    scheduler: str | None = None
    dry_run: bool = False
    force: bool = False
    fas_dim: int = 4096
    rescale: bool = True
    quiet: bool = False
    layout: str | None = None  # "full" or "compact"; default: the recipe's
    shard_chunks: int | None = None  # chunks per zarr shard; default: the recipe's (1: unsharded)


def open_sources(recipe: Recipe, deep1b: str | None, fas: str | None,
                 fas_dim: int, corpus: Corpus | None = None) -> tuple[RowSource, Traverse]:
    """The real files when given, else the synthetic generator; validated against the recipe
    (and against the corpus ``deep1b`` is said to be)."""
    deep = open_rows(deep1b) if deep1b else SyntheticDeep1B(recipe.deep1b_rows_read, recipe.seed)
    check_corpus(corpus, deep.name, deep.dim)
    if deep.dim < recipe.dim:  # the corpus's PCA keeps the recipe's D components: it needs as many
        raise InputError(f"{deep.name}: descriptors have {deep.dim} dimensions, fewer than the recipe's {recipe.dim}")
    if deep.n_rows < recipe.deep1b_rows_read:
        raise InputError(f"--scale {recipe.scale}: needs {recipe.deep1b_rows_read:,} Deep1B rows but "
                         f"{deep.name} holds {deep.n_rows:,}")
    traverse = open_fas(fas) if fas else SyntheticFAS(recipe.seed, FasParams(dim=fas_dim)).traverse()
    for which, src in (("ref", traverse.ref), ("query", traverse.query)):
        want = recipe.fas_rows(which, src.n_rows)
        if want > src.n_rows:
            raise InputError(f"--scale {recipe.scale}: needs {want:,} FAS {which} rows but "
                             f"{src.name} holds {src.n_rows:,}")
    if traverse.ref.dim < recipe.dim:
        raise InputError(f"{traverse.ref.name}: {traverse.ref.dim} dimensions, fewer than {recipe.dim}")
    for src in (traverse.ref, traverse.query):  # all zeros (or one row repeated) would build a store of zeros
        head = src.read(0, min(src.n_rows, 4096))
        if len(head) > 1 and not np.ptp(head, axis=0).any():
            raise InputError(f"{src.name}: its first {len(head):,} descriptors are all equal (every value "
                             f"{head[0, 0]:g}…): blank or damaged data")
    return deep, traverse


def _versions() -> dict[str, str]:
    return {"vprscale": vprscale.__version__, "numpy": np.__version__, "dask": dask.__version__,
            "zarr": zarr.__version__, "python": sys.version.split()[0]}


def _per_row(fn, rows: int) -> float:
    """Seconds per row of ``fn()`` over ``rows`` rows, best of two warm runs."""
    fn()
    best = math.inf
    for _ in range(2):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best / rows


def plan(recipe: Recipe, deep: RowSource, traverse: Traverse, out: Path | Remote, workers: int, layout: str,
         measure: bool = True) -> dict[str, Any]:
    """What a build reads, writes and needs, with a time estimate from measured per-row costs.

    Each stage of the passes (homogenising, moments, projection, noise, hashing) is timed
    on one block of rows on one thread, as a task runs it, and the passes are added up:
    full = 2 homogenisations, moments, projection, noise and the writes of three float32
    rows; compact = 2 homogenisations (and a third of the k-means sample's rows), moments,
    2 projections (and the sample's), the histograms of the sample and the hashing. The FAS
    part is a few randomized-PCA passes over 4096-d rows.
    """
    lay = Layout(recipe.deep1b_rows_kept, recipe.fas_rows("ref", traverse.ref.n_rows),
                 recipe.fas_rows("query", traverse.query.n_rows))
    d = recipe.dim
    d_hash = max(1, math.ceil(math.log2(lay.n_ref)))
    if layout == "full":
        write = 4 * d * (lay.n_ref + 2 * lay.n_query) + 9 * lay.n_query + lay.n_ref
    else:
        held = 120 * (lay.n_query // recipe.query_stride + 2 * MIN_FAS)  # windows of L ≤ 100, 1.2 safety
        write = (address_dtype(d_hash, 2).itemsize + 8) * lay.n_ref + held * (8 * d + 9)
    free = math.inf if isinstance(out, Remote) else shutil.disk_usage(
        out if out.exists() else out.parent if out.parent.exists() else Path.cwd()).free
    if not measure:
        return {"bytes_written_max": write, "disk_free": free}
    rows = min(BLOCK, recipe.deep1b_rows_kept)
    with threadpool_limits(limits=1, user_api="blas"):
        def homogenise() -> np.ndarray:
            return window_mean(deep, recipe.deep1b_rows_read, 0, rows, recipe.window)

        cost = {"homogenise": _per_row(homogenise, rows)}
        h = homogenise()
        cost["moments"] = _per_row(lambda: block_moments(h, 0), rows)
        matrix = np.eye(d)
        cost["project"] = _per_row(lambda: project_rows(h, np.zeros(d), matrix), rows)
        cost["noise"] = _per_row(lambda: noisy_rows(h, 0, recipe.seed, np.zeros(d), np.ones(d), (1.0, 2.0)), rows)
        comp = np.linalg.qr(np.random.default_rng(0).standard_normal((d, d)))[0][:d_hash]
        centres = np.tile([-0.1, 0.1], (d_hash, 1))
        cost["hash"] = _per_row(lambda: hash_descriptors(h, np.zeros(d), comp, centres), rows)
        fas_sample = min(2048, traverse.ref.n_rows)
        x = traverse.ref.read(0, fas_sample)
        # a FAS pass reads (or, synthetic, draws) every row and multiplies it by the sketch
        fas_per_row = (_per_row(lambda: traverse.ref.read(0, fas_sample), fas_sample)
                       + _per_row(lambda: x.T @ (x @ np.ones((x.shape[1], 128), np.float32)), fas_sample))
    c = cost
    sampled = sum(b - a for a, b in sample_spans(lay.n_ref)) / lay.n_ref  # the k-means pass's share of the rows
    if layout == "full":
        per_deep = 2 * c["homogenise"] + c["moments"] + c["project"] + c["noise"] + 12 * d / WRITE_BYTES_PER_S
    else:
        per_deep = ((2 + sampled) * c["homogenise"] + c["moments"] + (1 + sampled) * (c["project"] + c["hash"])
                    + c["project"] + 12 / WRITE_BYTES_PER_S)
    fas_passes = 3 if lay.n_fas_ref == traverse.ref.n_rows else 6  # randomized PCA passes
    parallel = max(1, min(workers, os.cpu_count() or 1)) * PARALLEL_EFFICIENCY
    est = FIXED_S + (per_deep * recipe.deep1b_rows_kept + fas_per_row * (traverse.ref.n_rows * fas_passes
                                                                           + traverse.query.n_rows * 2)) / parallel
    passes = 2 if layout == "full" else 2 + sampled
    read = 4 * (recipe.deep1b_rows_read + 40) * (deep.dim + 1) * passes + 4 * traverse.ref.dim * (
        traverse.ref.n_rows * fas_passes + traverse.query.n_rows * 3)
    chunk_mem = (recipe.shard_rows if layout == "full" else recipe.chunk_rows) * d * (8 + 8 + 4 * 6)
    fas_mem = 4 * traverse.ref.dim * (8192 * 3 + 128 * 4) + 8 * traverse.ref.dim * 128 * 3
    hist_mem = 8 * d_hash * (1 << 14) * 24 if layout == "compact" else 0  # per-chunk histograms of a group
    return {"scale": recipe.scale, "layout": layout, "ref_rows": lay.n_ref, "query_rows": lay.n_query,
            "deep1b_rows_read": recipe.deep1b_rows_read, "fas_ref_rows": lay.n_fas_ref,
            "fas_query_rows": lay.n_fas_query, "bytes_read": read, "bytes_written_max": write,
            "disk_free": free, "memory_estimate": workers * chunk_mem + fas_mem + hist_mem + 300 * 2**20,
            "seconds_estimate": est, "per_row_s": cost, "deep1b": deep.name, "fas": traverse.ref.name}


def _gib(x: float) -> str:
    return f"{x / 2**30:.2f} GiB"


def print_plan(p: dict[str, Any], out: Path | Remote) -> None:
    print(f"build {p['scale']} ({p['layout']} layout) → {out}")
    for kind in ("ref", "query"):
        rows, fas = p[f"{kind}_rows"], p[f"fas_{kind}_rows"]
        print(f"  {kind + ' rows':<11} {rows:>15,}   (Deep1B {rows - fas:,} + FAS {fas:,})")
    print(f"  reads       {_gib(p['bytes_read']):>15}   from {p['deep1b']} and {p['fas']}")
    print(f"  writes      {_gib(p['bytes_written_max']):>15}   at most (before compression)")
    free = "object storage" if math.isinf(p["disk_free"]) else _gib(p["disk_free"])
    print(f"  disk free   {free:>15}")
    print(f"  memory      {_gib(p['memory_estimate']):>15}   peak, estimated")
    print(f"  time        {p['seconds_estimate']:>13.0f} s   estimated from measured throughput")


def build(req: BuildRequest) -> dict[str, Any]:
    """Run (or plan) a build; returns the summary that the CLI prints."""
    recipe = load_recipe(req.scale)
    if req.shard_chunks is not None:
        if req.shard_chunks < 1 or recipe.chunk_rows * req.shard_chunks > MAX_CHUNK_ROWS:
            raise InputError(f"--shard-chunks {req.shard_chunks}: must be from 1 to "
                             f"{MAX_CHUNK_ROWS // recipe.chunk_rows} (shards of at most {MAX_CHUNK_ROWS:,} rows)")
        recipe = dataclasses.replace(recipe, shard_chunks=req.shard_chunks)
    deep, traverse = open_sources(recipe, req.deep1b, req.fas, req.fas_dim, req.corpus)
    out = location(req.out)
    if isinstance(out, Path):
        out = out.absolute()  # workers of a distributed cluster do not share our working directory
    if isinstance(out, Path) and out.exists() and not out.is_dir():
        raise InputError(f"--out {req.out}: is a file, not a directory")
    final = out / f"{recipe.scale}{'' if req.rescale else '-norescale'}.zarr"
    p = plan(recipe, deep, traverse, out, req.workers, req.layout or recipe.layout, measure=req.dry_run)
    if req.dry_run:
        print_plan(p, final)
    if p["bytes_written_max"] > p["disk_free"]:
        raise InputError(f"--out {out}: the build writes up to {_gib(p['bytes_written_max'])} "
                         f"but only {_gib(p['disk_free'])} is free")
    if req.dry_run:
        return {"dry_run": True, **p}
    check_writable(out)
    with exclusive(final):
        if output_for(final, {}).recover() and not req.quiet:
            log.info(f"{final}: finished publishing the build a killed run had completed")
        if isinstance(final, Path) and final.exists() and not (final / "zarr.json").is_file():
            raise InputError(f"--out {out}: {final} exists and is not a dataset store; not replaced")
        if (final / "zarr.json").exists() and not req.force:
            meta = zarr.open_group(zarr_url(final), mode="r").attrs.get(ATTR, {})
            if meta.get("complete") and (isinstance(final, Path) or (final / MANIFEST).exists()):
                wanted = _identity(recipe, deep, traverse, req)
                differ = [k for k in wanted if json.loads(json.dumps(wanted[k], default=str)) != meta.get(k)]
                if differ:
                    raise InputError(f"--out {out}: {final} is a complete store of other {' and '.join(differ)}; "
                                     "--force replaces it (or give another --out)")
                log.info(f"{final} is complete; use --force to rebuild it")
                return {"skipped": True, "store": str(final)}
        return _build(recipe, deep, traverse, final, req)


def _identity(recipe: Recipe, deep: RowSource, traverse: Traverse, req: BuildRequest) -> dict[str, Any]:
    """What defines a store's data: the recipe (with its layout), the rescaling and the sources."""
    return {"recipe": {**recipe.as_dict(), "layout": req.layout or recipe.layout}, "rescale": req.rescale,
            "sources": {"deep1b": deep.fingerprint(), "fas": traverse.fingerprint()}}


class DeepMoments:
    """Pass-1 task: per-block moments of the homogenised Deep1B rows of a chunk."""

    def __init__(self, source: RowSource, recipe: Recipe) -> None:
        self.source, self.recipe = source, recipe

    def __call__(self, a: int, b: int) -> np.ndarray:
        h = window_mean(self.source, self.recipe.deep1b_rows_read, a, b, self.recipe.window)
        low, high = h.min(axis=0), h.max(axis=0)  # two column passes tell both checks (rows only when one fails)
        if max(-low.min(), high.max()) > MAX_MAGNITUDE:
            i, half = a + int(np.flatnonzero(np.abs(h).max(axis=1) > MAX_MAGNITUDE)[0]), self.recipe.window // 2
            raise InputError(f"{self.source.name}: rows {max(0, i - half):,}–{i + half - 1:,} average to values beyond "
                             f"±{MAX_MAGNITUDE:.0e} (dataset row {i:,}); their squares overflow the float32 recipe")
        if len(h) > self.recipe.window and np.array_equal(low, high):
            raise InputError(f"{self.source.name}: dataset rows {a:,}–{b - 1:,} are all equal after homogenising "
                             f"(every value {h[0, 0]:g}…): a blank or damaged block of descriptors")
        return block_moments(h, a)


def _add_blocks(acc: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    for m in blocks:  # block by block, in order: the same bits for any chunking
        acc += m
    return acc


def _check_moments(moments: np.ndarray, source: RowSource) -> None:
    if not np.isfinite(moments).all():
        raise InputError(f"{source.name}: the homogenised rows' second moments overflow float64 "
                         "(values too large for the recipe's PCA)")


def _build(recipe: Recipe, deep: RowSource, traverse: Traverse, final: Path | Remote,
           req: BuildRequest) -> dict[str, Any]:
    t_start = time.perf_counter()
    timings = Timings(req.quiet)
    lay = Layout(recipe.deep1b_rows_kept, recipe.fas_rows("ref", traverse.ref.n_rows),
                 recipe.fas_rows("query", traverse.query.n_rows))
    layout = req.layout or recipe.layout
    provenance_key = _identity(recipe, deep, traverse, req)
    partial = output_for(final, provenance_key)
    resumed = partial.open()
    if resumed and not req.quiet:
        log.info(f"resuming the unfinished build in {partial.path}")
    store = str(partial.path)
    work = partial.work
    d = recipe.dim
    with dask_client(req.scheduler, req.workers) as client:
        if not (partial.done("fit") and (work / "fas_query.npy").is_file()):  # a new client refits
            group = zarr.open_group(store, mode="a", zarr_format=3)
            with timings.stage("fit transforms (Deep1B exact PCA, FAS PCA, noise model)"):
                moments = reduce_pass(work, "Deep1B moments", chunk_bounds(lay.n_deep, recipe.chunk_rows),
                                      DeepMoments(deep, recipe), _add_blocks, np.zeros((deep.dim + 1, deep.dim + 1)),
                                      quiet=req.quiet)
                _check_moments(moments, deep)
                merge = MergeTransform(d, lay.n_fas_ref, lay.n_fas_query, recipe.seed, req.rescale).fit(moments,
                                                                                                       traverse)
            _save_transforms(group, merge, work)
            partial.mark("fit")
        group = zarr.open_group(store, mode="r+")
        t = group["transforms"]
        fas_ref, fas_query = np.load(work / "fas_ref.npy"), np.load(work / "fas_query.npy")
        writer = ChunkWriter(store, deep, recipe, lay, t["deep1b_mean"][:],
                             t["deep1b_components"][:].T * t["deep1b_scale"][:],
                             t["noise_mean"][:], t["noise_std"][:], traverse.gt, fas_ref, fas_query)
        if layout == "full":
            _write_full(group, writer, partial, timings)
            extra: dict[str, Any] = {}
        else:
            extra = compact.write_compact(group, writer, partial, timings, t["ref_moments"][:], EVAL_LENGTHS,
                                          req.quiet)
        peak = cluster_peak_rss(client)
    elapsed = time.perf_counter() - t_start
    input_rows = (recipe.deep1b_rows_read, traverse.ref.n_rows + traverse.query.n_rows)  # the corpus, FAS100K
    summary = {"store": str(final), "scale": recipe.scale, "layout": layout, "ref_rows": lay.n_ref,
               "query_rows": lay.n_query, "query_sets": len(NOISE_LEVELS), "resumed": resumed,
               "stages_s": timings.stages,
               "wall_s": elapsed, "peak_rss_bytes": peak, "workers": req.workers, "input_rows": sum(input_rows),
               "input_bytes": 4 * (input_rows[0] * deep.dim + input_rows[1] * traverse.ref.dim),
               "provenance": provenance(inputs={k: provenance_key[k] for k in ("recipe", "sources")})}
    group = zarr.open_group(store, mode="r+")
    _write_positions(group, traverse, lay)
    group.attrs[ATTR] = {**provenance_key, "complete": True, "versions": _versions(), "seed": recipe.seed,
                         "layout": {"kind": layout, "n_deep1b": lay.n_deep, "n_fas_ref": lay.n_fas_ref,
                                    "n_fas_query": lay.n_fas_query, **extra}}
    partial.write_text("build.json", json.dumps({k: v for k, v in summary.items() if k != "store"},
                                                indent=1, default=str))
    consolidate(store)
    partial.publish()
    summary["bytes_on_disk"] = (sum(final.files().values()) if isinstance(final, Remote)
                                else sum(f.stat().st_size for f in final.rglob("*") if f.is_file()))
    return summary


def _write_positions(group: zarr.Group, traverse: Traverse, lay: Layout) -> None:
    """Where the FAS part's frames were taken (FAS100K's ``arr_3`` and ``arr_4``, in metres), for
    ``eval --radius-m`` on that part: ``fas_ref_pos`` of its kept references (dataset rows
    ``n_deep1b …``), ``fas_query_pos`` of its query rows (likewise); the Deep1B part has none."""
    for name, pos, n in (("fas_ref_pos", traverse.ref_pos, lay.n_fas_ref),
                         ("fas_query_pos", traverse.query_pos, lay.n_fas_query)):
        data = np.asarray(pos[:n], np.float64).reshape(n, -1)
        group.create_array(name, shape=data.shape, chunks=(max(1, n), data.shape[1]), dtype="f8", overwrite=True,
                           **codecs("labels"))
        group[name][:] = data


def _write_full(group: zarr.Group, writer: ChunkWriter, partial: Output, timings: Timings) -> None:
    """Pass 2 of the full layout: every row of every array, one chunk per task."""
    lay, recipe, d = writer.layout, writer.recipe, writer.recipe.dim
    if not partial.done("arrays"):
        for name, rows in (("ref", lay.n_ref), ("query_qm1", lay.n_query), ("query_qm2", lay.n_query)):
            group.create_array(name, shape=(rows, d), **grid(recipe, (rows, d)), dtype="f4",
                               overwrite=True, **codecs("descriptors"))
        group.create_array("gt", shape=(lay.n_query,), **grid(recipe, (lay.n_query,)), dtype="i8",
                           overwrite=True, **codecs("labels"))
        for name, rows in (("ref_part", lay.n_ref), ("query_part", lay.n_query)):
            group.create_array(name, shape=(rows,), **grid(recipe, (rows,)), dtype="u1",
                               overwrite=True, **codecs("labels"))
        partial.mark("arrays")
    tasks = [dask.delayed(_write_and_mark)(writer, a, b, partial, f"chunk-{c}")
             for c, (a, b) in enumerate(chunk_bounds(max(lay.n_ref, lay.n_query), recipe.shard_rows))
             if not partial.done(f"chunk-{c}")]
    with timings.stage(f"write {len(tasks)} chunks (homogenise, project, rescale, noise)"):
        run_groups(tasks, "write chunks")


def _write_and_mark(writer: ChunkWriter, a: int, b: int, partial: Output, unit: str) -> None:
    writer(a, b)
    partial.mark(unit)


def _save_transforms(group: zarr.Group, merge: MergeTransform, work: Path) -> None:
    t = group.create_group("transforms", overwrite=True)
    arrays = {"deep1b_mean": merge.deep_pca_.mean_, "deep1b_components": merge.deep_pca_.components_,
              "deep1b_explained_variance": merge.deep_pca_.explained_variance_,
              "deep1b_scale": merge.scale_, "fas_mean": merge.fas_pca_.mean_,
              "fas_components": merge.fas_pca_.components_,
              "noise_pca_mean": merge.noise_pca_.mean_, "noise_pca_components": merge.noise_pca_.components_,
              "noise_mean": merge.noise_mean_, "noise_std": merge.noise_std_,
              "deep1b_moments": merge.deep_moments_, "ref_moments": merge.ref_moments()}
    for name, arr in arrays.items():
        t.create_array(name, data=np.asarray(arr, dtype=np.float64))
    np.save(work / "fas_ref.npy", merge.fas_ref_)
    np.save(work / "fas_query.npy", merge.fas_query_)


def format_summary(s: dict[str, Any]) -> str:
    sets = int(s.get("query_sets", 1))  # every query set has as many rows (a traverse in other conditions)
    queries = f"{sets} query sets of {s['query_rows']:,} rows" if sets > 1 else f"{s['query_rows']:,} query rows"
    lines = [f"built {s['store']} ({s['layout']} layout): {s['ref_rows']:,} ref rows, {queries}"
             + (" (resumed)" if s.get("resumed") else "")]
    for name, secs in s["stages_s"].items():
        lines.append(f"  {secs:8.1f} s  {name}")
    lines.append(f"  {s['wall_s']:8.1f} s  total")
    lines.append(f"  peak memory {s['peak_rss_bytes'] / 2**30:.2f} GiB, {s['bytes_on_disk'] / 2**30:.2f} GiB on disk")
    if "input_rows" in s:  # a build's own run (a resumed one counts from where it resumed)
        lines.append("  read " + throughput(s["input_rows"], s["input_bytes"], s["wall_s"], s["workers"]))
    return "\n".join(lines)
