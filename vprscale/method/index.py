"""``vprscale index``: fit CoarseHash on a dataset store and write the index directory.

Directory layout (all written into a hidden partial copy and published when whole):

- ``index.json``: parameters, provenance of the store, storage accounting, timings;
- ``model/{mean,components,centres,explained_variance}.npy``: the fitted hasher;
- the inverted lists (:mod:`vprscale.method.lists`): ``ref_hash.npy``, ``ids.npy``,
  ``addresses.npy``, ``offsets.npy``, ``best.npy`` (memory-mapped by the engine) and
  ``lists.parquet`` / ``buckets.parquet`` (for SQL);
- ``components.parquet``: per component and cluster: centre, reference count and share.

A full store is fitted here (PCA on the moments its build derived, histograms and
hashing in two passes over ``ref``); a compact store was hashed by its build, and its
index only sorts the lists.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from pathlib import Path
from typing import Any

import dask
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import zarr

import vprscale
from vprscale.dataset.blocks import chunk_bounds
from vprscale.dataset.compact import load_model
from vprscale.dataset.rawchunks import rows_of
from vprscale.dataset.store import ATTR, PartialOutput, check_writable, exclusive, open_complete_group
from vprscale.errors import InputError
from vprscale.evaluation.storage import file_bytes, storage_table
from vprscale.jobs.cluster import cluster_peak_rss, dask_client
from vprscale.jobs.progress import Timings, run_tasks
from vprscale.method.coarsehash import CoarseHasher, hash_descriptors
from vprscale.method.lists import write_lists

INDEX_FORMAT = 2  # 2: lists as .npy files beside the Parquet copies
MODEL_FILES = {"P2": ["centres.npy"], "P3": ["components.npy", "explained_variance.npy"], "P4": ["mean.npy"]}


def store_identity(store: Path) -> str:
    """A digest of a store's provenance: an index records it, an evaluation checks it."""
    meta = open_complete_group(store).attrs[ATTR]
    core = {k: meta.get(k) for k in ("recipe", "sources", "layout", "seed", "rescale")}
    return hashlib.sha256(json.dumps(core, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _hash_chunk(x: np.ndarray, mean: np.ndarray, comp: np.ndarray,
                centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    _, h, err, _ = hash_descriptors(x, mean, comp, centres)
    return h, err.astype(np.float32)  # errors are compared in float32, as a compact store keeps them


def default_index_dir(store: Path, d: int, k: int) -> Path:
    return store.parent / f"{store.name.removesuffix('.zarr')}-d{d}-k{k}.index"


def store_layout(group: zarr.Group) -> dict[str, Any]:
    """The layout attributes of a store (``kind`` is ``full`` for stores built before layouts had a name)."""
    return {"kind": "full", **group.attrs[ATTR].get("layout", {})}


def ref_moments(group: zarr.Group) -> np.ndarray | None:
    """The reference moments a build derived (``None`` for stores built before they were kept)."""
    t = group.get("transforms")
    return t["ref_moments"][:] if t is not None and "ref_moments" in t else None


def build_index(store: str | Path, d: int | None = None, k: int = 2, out: str | Path | None = None,
                scheduler: str | None = None, workers: int = 2, quiet: bool = False,
                force: bool = False) -> dict[str, Any]:
    """Fit (or, for a compact store, load) CoarseHash, hash every reference, and write the index directory.

    An existing index is replaced only when the new one is whole; if evaluations sit in its
    ``eval/`` folder, only with ``force``, and they are then kept beside the new index in
    ``<index>.previous-eval/`` (they belong to the old one).
    """
    store = Path(store)
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
    final = Path(out) if out else default_index_dir(store, d_eff, k)
    check_writable(final.parent)
    identity = store_identity(store)
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
            _write_model(partial.path, hasher, lists["level_counts"], n_ref)
        peak = cluster_peak_rss(client)
        disk = {"P1": file_bytes(partial.path / "ref_hash.npy"),
                **{p: file_bytes(*(partial.path / "model" / f for f in fs)) for p, fs in MODEL_FILES.items()}}
        list_bytes = file_bytes(*(partial.path / f"{n}.npy" for n in ("ids", "addresses", "offsets", "best")))
        built = store / "build.json"
        meta = {
            "kind": "coarsehash-index", "complete": True, "format": INDEX_FORMAT, "d": d_eff, "k": k,
            "n_ref": int(n_ref), "dim": int(dim), "occupied": int(lists["occupied"]), "bins": hasher.bins,
            "store": {"path": str(store.resolve()), "identity": identity, "layout": layout["kind"],
                      "scale": group.attrs[ATTR]["recipe"]["scale"], "rescale": group.attrs[ATTR].get("rescale", True),
                      "built": json.loads(built.read_text()) if built.is_file() else {}},
            "storage": storage_table(int(n_ref), d_eff, k, int(dim), disk),
            "lists": {"bytes": list_bytes, "bytes_per_place": list_bytes / max(1, n_ref),
                      "partitions": lists["partitions"]},
            "timings_s": timings.stages, "wall_s": time.perf_counter() - t0, "peak_rss_bytes": peak,
            "versions": {"vprscale": vprscale.__version__},
        }
        (partial.path / "index.json").write_text(json.dumps(meta, indent=1))
        if (final / "eval").is_dir():  # only with force (checked above): the old evaluations are kept beside
            kept = final.with_name(f"{final.name}.previous-eval")
            if kept.exists():
                shutil.rmtree(kept)
            (final / "eval").rename(kept)
        partial.publish()
    return {"index": str(final), **meta}


def _write_model(path: Path, hasher: CoarseHasher, counts: np.ndarray, n_ref: int) -> None:
    (path / "model").mkdir(exist_ok=True)
    for name in ("mean", "components", "centres", "explained_variance"):
        np.save(path / "model" / f"{name}.npy", getattr(hasher, f"{name}_"))
    d, k = counts.shape
    comp = pa.table({"component": np.repeat(np.arange(1, d + 1), k).astype(np.int32),
                     "cluster": np.tile(np.arange(k), d).astype(np.int32),
                     "centre": hasher.centres_.ravel(),
                     "refs": counts.ravel().astype(np.int64),
                     "share": (counts / n_ref).ravel(),
                     "variance": np.repeat(hasher.explained_variance_, k)})
    pq.write_table(comp, path / "components.parquet")


def load_index_meta(index: str | Path) -> dict[str, Any]:
    """``index.json`` of a complete index, or an error naming the directory."""
    p = Path(index)
    meta_file = p / "index.json"
    if not meta_file.is_file():
        raise InputError(f"{p}: not a vprscale index (no index.json)")
    try:
        meta = json.loads(meta_file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{meta_file}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict) or not meta.get("complete") or meta.get("kind") != "coarsehash-index":
        raise InputError(f"{p}: the index is incomplete or of another kind")
    if meta.get("format", 1) < INDEX_FORMAT:
        raise InputError(f"{p}: an index of an older vprscale (no memory-mapped lists); re-run vprscale index")
    return meta
