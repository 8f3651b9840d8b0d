"""A store's reference rows as a Dask array, whatever its layout (``docs/dataset.md``).

A full store holds them (``ref``). A compact store keeps a few bytes per place instead
(:mod:`vprscale.dataset.compact`), so a method that must read the references themselves —
FAISS encoding them for the compact-code comparison — gets them recomputed from the store's
sources, chunk by chunk in the same absolute blocks and by the same code as the build: the
same bits the full layout of the same data stores. Nothing but one chunk at a time is ever
held; reading them costs what a build's hashing pass costs (about 2 minutes at 100M, 18 at
1B on 2 cores).
"""

from __future__ import annotations

import json
from pathlib import Path

import dask
import dask.array as da
import numpy as np
import zarr

from vprscale.core.blocks import chunk_bounds
from vprscale.core.errors import InputError
from vprscale.core.objects import Remote, zarr_url
from vprscale.core.zarrio import rows_of
from vprscale.dataset.build import open_sources
from vprscale.dataset.layout import ChunkWriter, Layout
from vprscale.dataset.merge import MergeTransform
from vprscale.dataset.recipe import Recipe
from vprscale.dataset.store import ATTR

_CHECKED = ("deep1b_mean", "deep1b_scale")  # fitted transforms that must come out equal from the sources


class StoredRows:
    """Reference rows ``[a, b)`` of a full store, read from its ``ref`` (opened in the task)."""

    def __init__(self, store: Path | Remote) -> None:
        self.store = zarr_url(store)

    def __call__(self, a: int, b: int) -> np.ndarray:
        return np.asarray(zarr.open_group(self.store, mode="r")["ref"][a:b], np.float32)


class RecomputedRows:
    """Reference rows ``[a, b)`` of a compact store, computed from its sources as the build did."""

    def __init__(self, writer: ChunkWriter) -> None:
        self.writer = writer

    def __call__(self, a: int, b: int) -> np.ndarray:
        return np.asarray(self.writer.ref_rows(a, b), np.float32)


def reference_reader(store: Path, group: zarr.Group, deep1b: str | None = None,
                     fas: str | None = None) -> tuple[StoredRows | RecomputedRows, list[tuple[int, int]]]:
    """A task that gives the reference rows ``[a, b)`` of ``store``, and the chunks to ask it for.

    ``deep1b`` and ``fas`` name the source files a compact store was built from; a store
    built from the synthetic generator needs neither.
    """
    meta = group.attrs[ATTR]
    lay = meta["layout"]
    if lay["kind"] != "compact":
        return StoredRows(store), chunk_bounds(int(group["ref"].shape[0]), int(group["ref"].chunks[0]))
    recipe = Recipe.from_dict({k: v for k, v in meta["recipe"].items() if k != "layout"}, str(store))
    sources = meta["sources"]
    for flag, given, fingerprint in (("--deep1b", deep1b, sources["deep1b"]), ("--fas", fas, sources["fas"])):
        synthetic = str(fingerprint.get("format", fingerprint.get("ref", {}).get("format", ""))).startswith("synthetic")
        if given is None and not synthetic:
            raise InputError(f"{flag}: {store} is a compact store built from files; give the file it was built from "
                             "(its reference rows are recomputed from the sources)")
    fas_dim = int(sources["fas"].get("ref", {}).get("dim", 4096))
    deep, traverse = open_sources(recipe, deep1b, fas, fas_dim)
    for name, src, want in (("--deep1b", deep, sources["deep1b"]), ("--fas", traverse, sources["fas"])):
        if _plain(src.fingerprint()) != _plain(want):
            raise InputError(f"{name}: {src.name} is not the source {store} was built from (its fingerprint differs)")
    layout = Layout(int(lay["n_deep1b"]), int(lay["n_fas_ref"]), int(lay["n_fas_query"]))
    t = group["transforms"]
    merge = MergeTransform(recipe.dim, layout.n_fas_ref, layout.n_fas_query, recipe.seed,
                           bool(meta.get("rescale", True))).fit(t["deep1b_moments"][:], traverse)
    refit = {"deep1b_mean": merge.deep_pca_.mean_, "deep1b_scale": merge.scale_}
    for name in _CHECKED:
        if not np.array_equal(np.asarray(refit[name], np.float64), t[name][:]):
            raise InputError(f"{store}: its sources no longer give its transforms ({name} differs); "
                             "rebuild the store")
    writer = ChunkWriter(zarr_url(store), deep, recipe, layout, t["deep1b_mean"][:],
                         t["deep1b_components"][:].T * t["deep1b_scale"][:], t["noise_mean"][:], t["noise_std"][:],
                         traverse.gt, merge.fas_ref_, merge.fas_query_)
    return RecomputedRows(writer), chunk_bounds(layout.n_ref, recipe.chunk_rows)


def reference_rows(store: Path, group: zarr.Group, deep1b: str | None = None, fas: str | None = None) -> da.Array:
    """The reference rows of ``store`` as a Dask array (its ``ref``, or recomputed for a compact store)."""
    if group.attrs[ATTR]["layout"]["kind"] != "compact":
        return rows_of(group["ref"])
    read, bounds = reference_reader(store, group, deep1b, fas)
    shared = dask.delayed(read, pure=True)  # hashed once, not once per chunk
    dim = int(group.attrs[ATTR]["recipe"]["dim"])
    chunks = [da.from_delayed(shared(a, b), shape=(b - a, dim), dtype=np.float32) for a, b in bounds]
    return da.concatenate(chunks, axis=0)


def _plain(fingerprint: object) -> object:
    """A fingerprint as the store's JSON attributes hold it (tuples as lists, numbers as JSON numbers)."""
    return json.loads(json.dumps(fingerprint, default=str))
