"""``vprscale index``: fit CoarseHash on a dataset store and write the index directory.

The directory's format is :mod:`vprscale.method.indexfile`'s; this job adds the store's
provenance, storage accounting and timings to its ``index.json``, and writes it into a
hidden partial copy that is published when whole.

A full store is fitted here (PCA on the moments its build derived, histograms and
hashing in two passes over ``ref``); a compact store was hashed by its build, and its
index only sorts the lists.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import dask
import numpy as np

import vprscale
from vprscale.core.blocks import chunk_bounds
from vprscale.core.cluster import cluster_peak_rss, dask_client
from vprscale.core.errors import InputError
from vprscale.core.localcopy import cache_folder, upload
from vprscale.core.manifest import NAME
from vprscale.core.objects import Remote, location, shown
from vprscale.core.progress import Timings, run_tasks
from vprscale.core.provenance import provenance
from vprscale.core.publish import PartialOutput, check_writable, exclusive, keep_beside, refuse_foreign
from vprscale.core.zarrio import rows_of
from vprscale.dataset.store import ATTR, load_model, open_complete_group, ref_moments, store_identity, store_layout
from vprscale.evaluation.storage import file_bytes, index_parts, storage_table
from vprscale.method.coarsehash import CoarseHasher, hash_descriptors
from vprscale.method.indexfile import (
    MODEL_FILES,
    load_index_meta,
    upgrade,
    write_lists,
    write_meta,
    write_model,
)

log = logging.getLogger(__name__)


def _hash_chunk(x: np.ndarray, mean: np.ndarray, comp: np.ndarray,
                centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    _, h, err, _ = hash_descriptors(x, mean, comp, centres)
    return h, err.astype(np.float32)  # errors are compared in float32, as a compact store keeps them


def default_index_dir(store: Path | Remote, d: int, k: int) -> Path | Remote:
    return store.parent / f"{store.name.removesuffix('.zarr')}-d{d}-k{k}.index"


def build_index(store: str | Path, d: int | None = None, k: int = 2, out: str | Path | None = None,
                scheduler: str | None = None, workers: int = 2, quiet: bool = False,
                force: bool = False) -> dict[str, Any]:
    """Fit (or, for a compact store, load) CoarseHash, hash every reference, and write the index directory.

    An existing index is replaced only when the new one is whole; if evaluations sit in its
    ``eval/`` folder, only with ``force``, and they are then kept beside the new index in
    ``<index>.previous-eval/`` (they belong to the old one).
    """
    store = location(store)
    group = open_complete_group(store)
    layout = store_layout(group)
    if layout["kind"] == "compact":
        hasher = load_model(group)
        n_ref, dim = int(layout["n_ref"]), hasher.components_.shape[1]
        if (d is not None and d != hasher.d_) or k != hasher.k:
            raise InputError(f"{store}: a compact store holds addresses for d = {hasher.d_}, K = {hasher.k} only "
                             f"(asked: d = {d}, K = {k}); rebuild it with --layout full for other widths")
        d_eff = hasher.d_
    else:
        n_ref, dim = group["ref"].shape
        hasher = CoarseHasher(d=d, k=k)
        d_eff = hasher._check(n_ref, dim)
    target = location(out) if out is not None else default_index_dir(store, d_eff, k)
    remote = target if isinstance(target, Remote) else None
    # an index is memory-mapped while it is written and where it is used: one for object storage is
    # made in the local cache, then uploaded (core/localcopy)
    final = cache_folder(remote) if remote else target
    if not final.resolve().name:
        raise InputError(f"--out {out}: names no directory to write the index into; give a new folder's path")
    check_writable(final.parent)
    if remote:
        check_writable(remote.parent)
        refuse_foreign(remote)  # before the work: what is there is replaced only if vprscale wrote it
        if not force and (remote / NAME).exists():
            raise InputError(f"--out {remote}: holds an index; --force replaces it")
    identity = store_identity(group)
    timings = Timings(quiet)
    t0 = time.perf_counter()
    with exclusive(final), dask_client(scheduler, workers) as client:
        partial = PartialOutput(final, {"store": identity, "d": d_eff, "k": k})
        partial.recover()
        if final.exists() and not (final / "index.json").is_file():
            raise InputError(f"--out {final}: exists and is not a vprscale index; not replaced")
        if (final / "eval").is_dir() and any((final / "eval").iterdir()) and not force:
            raise InputError(f"{final}: holds evaluations in eval/; re-indexing would orphan them "
                             "(--force keeps them beside the new index, in <index>.previous-eval/)")
        if final.exists() and not force and not remote:  # an existing output is replaced only with --force
            old = load_index_meta(final)
            same_store = (old.get("store") or {}).get("identity") == identity
            if not same_store or (old["d"], old["k"]) != (d_eff, k):
                of = "other parameters" if same_store else "another store"
                raise InputError(f"--out {final}: holds an index of {of} (d = {old['d']}, K = {old['k']}); --force "
                                 "replaces it and keeps its evaluations beside")
            log.info(f"{final} is complete (d = {d_eff}, K = {k}, this store); --force rebuilds it")
            return {"index": str(final), **old, "parts_published": index_parts(final)}
        partial.open()
        if layout["kind"] == "compact":
            chunk = group["ref_hash"].chunks[0]
            stored_h, stored_err = group["ref_hash"], group["ref_err"]

            def addresses(a: int, b: int) -> np.ndarray:
                return stored_h[a:b]

            def errors(a: int, b: int) -> np.ndarray:
                return stored_err[a:b]
        else:
            ref = rows_of(group["ref"])
            with timings.stage(f"fit CoarseHash (d = {d_eff}, K = {k}) on {n_ref:,} refs"):
                hasher.fit(ref, moments=ref_moments(group))
            parts = [dask.delayed(_hash_chunk, nout=2)(blk, hasher.mean_, hasher.components_, hasher.centres_)
                     for blk in ref.to_delayed().ravel()]
            with timings.stage("hash every reference"):
                results = run_tasks([dask.delayed(tuple)(p) for p in parts], "hash refs")
            h = np.concatenate([r[0] for r in results])
            err = np.concatenate([r[1] for r in results])
            chunk = max(1, len(h))

            def addresses(a: int, b: int) -> np.ndarray:
                return h[a:b]

            def errors(a: int, b: int) -> np.ndarray:
                return err[a:b]
        with timings.stage("sort and write the inverted lists"):
            lists = write_lists(partial.path, addresses, errors, chunk_bounds(n_ref, chunk), n_ref, d_eff, k,
                                quiet=quiet)
            write_model(partial.path, hasher, lists["level_counts"], n_ref)
        peak = cluster_peak_rss(client)
        disk = {"P1": file_bytes(partial.path / "codes.parquet"),
                **{p: file_bytes(*(partial.path / "model" / f for f in fs)) for p, fs in MODEL_FILES.items()}}
        list_bytes = file_bytes(*(partial.path / n for n in ("lists.parquet", "buckets.parquet")))
        built = store / "build.json"
        extra = {
            "store": {"path": shown(store), "identity": identity, "layout": layout["kind"],
                      "scale": group.attrs[ATTR]["recipe"]["scale"], "rescale": group.attrs[ATTR].get("rescale", True),
                      "built": json.loads(built.read_text()) if built.is_file() else {}},
            "storage": storage_table(int(n_ref), d_eff, k, int(dim), disk),
            "lists": {"bytes": list_bytes, "bytes_per_place": list_bytes / max(1, n_ref),
                      "partitions": lists["partitions"]},
            "timings_s": timings.stages, "wall_s": time.perf_counter() - t0, "peak_rss_bytes": peak,
            "versions": {"vprscale": vprscale.__version__},
            "provenance": provenance(inputs={"store": shown(store), "store_identity": identity}),
        }
        extra["parts"] = index_parts(partial.path)  # index.json and the manifest are counted where shown
        meta = write_meta(partial.path, hasher, n_ref, lists["layout"], extra)
        if (final / "eval").is_dir():  # only with force (checked above): the old evaluations are kept beside
            keep_beside(final / "eval", final.with_name(f"{final.name}.previous-eval"))
        partial.publish()
    parts = index_parts(final)  # as published: index.json and the manifest counted
    if remote:
        upload(final, remote)
    return {"index": str(remote or final), **meta, "parts_published": parts}


def upgrade_index(path: str | Path, quiet: bool = False) -> dict[str, Any]:
    """Convert a format-2 or format-3 index in place into the current format, without refitting (same lists,
    same matches); an index already current is left as it is.

    The new directory is written into a hidden work copy and published like a fresh index;
    its evaluations (``eval/``, still valid: the matches do not change) wait beside it in
    ``<index>.eval-during-upgrade`` while the directories are swapped, and a run killed
    there moves them back on its next start.
    """
    final = Path(path)
    parked = final.with_name(f"{final.name}.eval-during-upgrade")
    with exclusive(final):
        partial = PartialOutput(final, {"upgrade": str(final.resolve())})
        partial.recover()
        if parked.is_dir() and not (final / "eval").exists():
            parked.rename(final / "eval")
        meta = load_index_meta(final, upgradable=True)
        if meta["format"] not in (2, 3):
            return {**meta, "index": str(final), "converted": False}
        check_writable(final.parent)
        partial.open()
        t0 = time.perf_counter()
        meta = upgrade(final, partial.path, quiet=quiet)
        disk = {"P1": file_bytes(partial.path / "codes.parquet"),
                **{p: file_bytes(*(partial.path / "model" / f for f in fs)) for p, fs in MODEL_FILES.items()}}
        meta["storage"] = storage_table(int(meta["n_ref"]), int(meta["d"]), int(meta["k"]), int(meta["dim"]), disk)
        list_bytes = file_bytes(*(partial.path / n for n in ("lists.parquet", "buckets.parquet")))
        meta["lists"] = {**meta.get("lists", {}), "bytes": list_bytes, "bytes_per_place": list_bytes / meta["n_ref"]}
        meta["parts"] = index_parts(partial.path)
        meta["upgrade"] = {"wall_s": time.perf_counter() - t0,
                           "provenance": provenance(inputs={"index": str(final.resolve())})}
        (partial.path / "index.json").write_text(json.dumps(meta, indent=1, default=str))
        if (final / "eval").is_dir():
            (final / "eval").rename(parked)
        partial.publish()
        if parked.is_dir():
            parked.rename(final / "eval")
    return {**meta, "index": str(final), "converted": True}


def sweep_indexes(store: str | Path, widths: list[int], scheduler: str | None = None, workers: int = 2,
                  quiet: bool = False) -> list[Path]:
    """The K = 2 indexes of ``store`` at each width of a d sweep (Fig. 4a), built where missing."""
    store = Path(store)
    identity = store_identity(open_complete_group(store))
    paths = []
    for d in widths:
        path = default_index_dir(store, d, 2)
        try:
            current = load_index_meta(path)["store"]["identity"] == identity
        except InputError:
            current = False
        if not current:
            build_index(store, d=d, k=2, out=path, scheduler=scheduler, workers=workers, quiet=quiet)
        paths.append(path)
    return paths
