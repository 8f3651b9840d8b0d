"""The compact store layout: only what the index and the evaluation read (``docs/dataset.md``).

A full store costs 1.15 KB per place (a reference row and two query rows of 96 float32),
while the index needs a few bytes. At 100M places and beyond the build therefore keeps:

- per reference: its CoarseHash address (``ref_hash``, 4 bytes while d ≤ 32), its
  quantisation error (``ref_err``, float32: the single best of an address is the least of
  these, ties to the smaller id) and its first principal component (``base_x1``, float32:
  the map of the d = 1 baseline), 12 bytes in all;
- the fitted CoarseHash model (``transforms/coarsehash``), fitted on moments the build
  derives (:meth:`~vprscale.dataset.merge.MergeTransform.ref_moments`) and histograms of a pass
  over the k-means sample (:func:`~vprscale.method.coarsehash.sample_spans`: every reference up
  to 33.4M, beyond an evenly spread sample of at least 16.8M);
- the query rows inside the windows the protocol evaluates (:mod:`vprscale.protocol`),
  for both noise levels, with their frame numbers, truth and part.

Every reference row is computed exactly as the full layout writes it, chunk by chunk in
the same absolute blocks, and hashed by the same kernels; so an index of a compact store
has the same addresses, lists and matches as an index of the full store of the same data.
"""

from __future__ import annotations

from typing import Any

import dask
import numpy as np
import zarr

from vprscale.core.blocks import BLOCK, chunk_bounds
from vprscale.core.passes import reduce_pass
from vprscale.core.progress import Timings, compute
from vprscale.core.publish import Output
from vprscale.dataset.layout import NOISE_LEVELS, ChunkWriter, codecs, grid, gt_of
from vprscale.dataset.store import MODEL, load_model
from vprscale.method.coarsehash import CoarseHasher, hash_descriptors, project, sample_spans
from vprscale.method.lists import address_dtype
from vprscale.protocol import query_centres, window_frames


class _Histograms:
    def __init__(self, writer: ChunkWriter, hasher: CoarseHasher) -> None:
        self.writer, self.hasher = writer, hasher

    def __call__(self, a: int, b: int) -> tuple:
        return self.hasher.column_histogram(self.writer.ref_rows(a, b))


def _merge_histograms(state: tuple | None, r: tuple) -> tuple:
    if state is None:
        return r
    return (state[0] + r[0], np.stack([np.minimum(state[1][0], r[1][0]), np.maximum(state[1][1], r[1][1])]),
            np.concatenate([state[2], r[2]]), np.concatenate([state[3], r[3]]))


class _HashWriter:
    """Hashing-pass task: hash a chunk of reference rows and write its per-place arrays."""

    def __init__(self, store: str, writer: ChunkWriter, hasher: CoarseHasher) -> None:
        self.store, self.writer, self.hasher = store, writer, hasher
        self.dtype = address_dtype(hasher.d_, hasher.k)

    def __call__(self, a: int, b: int) -> None:
        """Rows ``[a, b)`` (a chunk, or a shard of chunks written whole), computed a chunk at a time."""
        hs, step = self.hasher, self.writer.recipe.chunk_rows
        h, err, base = np.empty(b - a, self.dtype), np.empty(b - a, np.float32), np.empty(b - a, np.float32)
        for s, e in chunk_bounds(b - a, step):
            x = self.writer.ref_rows(a + s, a + e)
            # the baseline's map (the first component) comes out of the hashing's own projection
            _, addresses, errors, _ = hash_descriptors(x, hs.mean_, hs.components_, hs.centres_, base[s:e])
            h[s:e], err[s:e] = addresses, errors  # cast as the arrays store them
        group = zarr.open_group(self.store, mode="r+")
        group["ref_hash"][a:b] = h
        group["ref_err"][a:b] = err
        group["base_x1"][a:b] = base


def baseline_map(x: np.ndarray, mean: np.ndarray, components: np.ndarray) -> np.ndarray:
    """The d = 1 baseline's value of rows: their first principal component, float32.

    The first component of the reference PCA is the baseline's PCA (d = 1) of the same
    moments; projected row by row in a fixed order (:func:`~vprscale.method.coarsehash.project`),
    so a row's value does not depend on how many rows share the call.
    """
    return project(x, mean, components[:1])[:, 0].astype(np.float32)


def _queries_of_block(writer: ChunkWriter, a: int, frames: np.ndarray) -> list[np.ndarray]:
    """The query rows of ``frames`` (all in the absolute block starting at ``a``), per noise level."""
    e = min(a + BLOCK, writer.layout.n_query)
    qs = writer.query_rows(writer.deep_rows(a, e), a, e)
    return [q[frames - a] for q in qs]


def write_compact(group: zarr.Group, writer: ChunkWriter, partial: Output, timings: Timings,
                  ref_moments: np.ndarray, lengths: tuple[int, ...], quiet: bool) -> dict[str, Any]:
    """The k-means pass (over the sample) and the hashing pass of a compact build, and the
    evaluated query windows; the layout's attributes."""
    lay, recipe = writer.layout, writer.recipe
    work = partial.work
    bounds = [(a + s, a + e) for a, b in sample_spans(lay.n_ref) for s, e in chunk_bounds(b - a, recipe.chunk_rows)]
    hasher = CoarseHasher(k=2).fit_pca(ref_moments)
    if not partial.done("model"):
        sampled = sum(b - a for a, b in bounds)
        with timings.stage(f"CoarseHash model (d = {hasher.d_}): histograms of {sampled:,} references"):
            hist = reduce_pass(work, "histograms", bounds, _Histograms(writer, hasher), _merge_histograms, None,
                               quiet=quiet)
            hasher.fit_centres([hist])
        model = group.create_group("transforms/coarsehash", overwrite=True)
        for name in MODEL:
            model.create_array(name, data=np.asarray(getattr(hasher, f"{name}_"), np.float64))
        model.attrs.update({"d": hasher.d_, "k": hasher.k, "bins": hasher.bins})
        for name, dtype in (("ref_hash", address_dtype(hasher.d_, hasher.k)), ("ref_err", "f4"), ("base_x1", "f4")):
            group.create_array(name, shape=(lay.n_ref,), **grid(recipe, (lay.n_ref,)), dtype=dtype, overwrite=True,
                               compressors=None)
        partial.mark("model")
    else:
        hasher = load_model(group)
    with timings.stage("hash every reference (addresses, errors, baseline map)"):
        reduce_pass(work, "hash references", chunk_bounds(lay.n_ref, recipe.shard_rows),
                    _HashWriter(str(partial.path), writer, hasher),
                    lambda s, _: s, None, quiet=quiet)
    z = recipe.query_stride
    if not partial.done("queries"):
        with timings.stage("query rows of the evaluated windows"):
            def gt_at(t: np.ndarray) -> np.ndarray:
                return gt_of(lay, writer.fas_gt, t)

            centres = [query_centres(gt_at, lay.n_query, lay.n_deep, z, L).t for L in lengths]
            frames = window_frames(centres, list(lengths))
            blocks = np.unique(frames // BLOCK)
            shared = dask.delayed(writer, pure=True)  # hashed once, not once per block
            parts = [dask.delayed(_queries_of_block)(shared, int(b) * BLOCK,
                                                     frames[(frames >= b * BLOCK) & (frames < (b + 1) * BLOCK)])
                     for b in blocks]
            rows = compute(*parts, desc="query windows")
            chunk = (1 << 16, recipe.dim)
            for i, name in enumerate(NOISE_LEVELS):
                group.create_array(name, data=np.concatenate([r[i] for r in rows]), chunks=chunk, overwrite=True,
                                   **codecs("descriptors"))
            for name, data in (("query_frames", frames), ("gt", gt_at(frames)),
                               ("query_part", (frames >= lay.n_deep).astype(np.uint8))):
                group.create_array(name, data=data, chunks=(1 << 16,), overwrite=True, **codecs("labels"))
        partial.mark("queries")
    return {"n_ref": lay.n_ref, "n_query": lay.n_query, "eval_lengths": list(lengths), "z": z,
            "coarsehash": {"d": hasher.d_, "k": hasher.k}}
