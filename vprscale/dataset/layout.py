"""The full store layout (docs/dataset.md): the row counts, the ground truth of step 8, the
arrays' codecs, and the task that writes every array of a chunk of rows.

The compact layout (:mod:`vprscale.dataset.compact`) computes its rows with the same
:class:`ChunkWriter`, so both layouts hold the same values.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import zarr

from vprscale.core.zarrio import write_rows
from vprscale.dataset.homogenise import window_mean
from vprscale.dataset.merge import noisy_rows, project_centred
from vprscale.dataset.recipe import Recipe
from vprscale.dataset.sources.base import RowSource, check_finite
from vprscale.protocol import FAS

NOISE_LEVELS = {"query_qm1": 1.0, "query_qm2": 2.0}  # query arrays and their noise scale s (QM1, QM2)


def codecs(kind: str) -> dict[str, Any]:
    """Compression of the stored arrays.

    Descriptors are stored raw: PCA-projected float32 rows barely compress (bit-shuffled
    lz4: 0.87 of the size, zstd: 0.88) and every index or evaluation pass reads them again
    (a 10M pass: 3.2 s raw, 5.8 s with lz4). Integer arrays compress a hundredfold.
    """
    if kind == "descriptors":
        return {"compressors": None}
    return {"compressors": [zarr.codecs.BloscCodec(cname="lz4", clevel=5, shuffle="bitshuffle")]}


def grid(recipe: Recipe, shape: tuple[int, ...]) -> dict[str, Any]:
    """The chunk shape of a per-row array (``chunk_rows`` whole rows), and with a sharded recipe its
    shard shape (``shard_chunks`` chunks: one object on object storage, written whole by one task).
    Zarr records both in the array's metadata; every reader takes either form."""
    chunks = (recipe.chunk_rows, *shape[1:])
    if recipe.shard_chunks == 1:
        return {"chunks": chunks}
    return {"chunks": chunks, "shards": (recipe.shard_rows, *shape[1:])}


@dataclass
class Layout:
    """Row counts of the dataset."""

    n_deep: int
    n_fas_ref: int
    n_fas_query: int

    @property
    def n_ref(self) -> int:
        return self.n_deep + self.n_fas_ref

    @property
    def n_query(self) -> int:
        return self.n_deep + self.n_fas_query


def dataset_gt(layout: Layout, fas_gt: np.ndarray, start: int, stop: int) -> np.ndarray:
    """Ground truth of query rows ``[start, stop)`` (docs/dataset.md, step 8); −1 means none."""
    return gt_of(layout, fas_gt, np.arange(start, stop, dtype=np.int64))


def gt_of(layout: Layout, fas_gt: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Ground truth of query rows ``u``; −1 means none."""
    u = np.asarray(u, np.int64)
    gt = u.copy()
    fas = u >= layout.n_deep
    j = fas_gt[u[fas] - layout.n_deep]
    gt[fas] = np.where(j < layout.n_fas_ref, layout.n_deep + j, -1)
    return gt


@dataclass
class ChunkWriter:
    """Everything one pass-2 task needs: small matrices and the source reader, no data."""

    store: str
    source: RowSource
    recipe: Recipe
    layout: Layout
    mean: np.ndarray
    matrix: np.ndarray
    noise_mean: np.ndarray
    noise_std: np.ndarray
    fas_gt: np.ndarray
    fas_ref: np.ndarray  # the kept FAS rows, projected
    fas_query: np.ndarray

    def deep_rows(self, a: int, b: int) -> np.ndarray:
        """Deep1B reference rows ``[a, min(b, n_deep))``: homogenised, projected, rescaled."""
        d_hi = min(b, self.layout.n_deep)
        if a >= d_hi:
            return np.empty((0, self.recipe.dim), np.float32)
        centred = window_mean(self.source, self.recipe.deep1b_rows_read, a, d_hi, self.recipe.window, self.mean)
        rows = project_centred(centred, a, self.matrix)
        # Finite inputs can still overflow float32 once averaged and projected (values near 3e38).
        check_finite(rows, a, f"{self.source.name} (rows {max(0, a - self.recipe.window // 2):,}–"
                              f"{min(self.recipe.deep1b_rows_read, d_hi + self.recipe.window // 2) - 1:,} "
                              "homogenised and projected overflow float32; dataset row)")
        return rows

    def _fas(self, rows: np.ndarray, a: int, b: int, n_total: int) -> np.ndarray:
        """The FAS rows (of ``rows``, which follow the Deep1B part) inside dataset rows ``[a, b)``."""
        n_deep = self.layout.n_deep
        return rows[max(0, a - n_deep) : max(0, min(b, n_total) - n_deep)]

    def ref_rows(self, a: int, b: int, deep: np.ndarray | None = None) -> np.ndarray:
        """Reference rows ``[a, b)`` exactly as the full layout stores them (``deep``: their Deep1B
        part, when already computed)."""
        deep = self.deep_rows(a, b) if deep is None else deep
        fas = self._fas(self.fas_ref, a, b, self.layout.n_ref)
        return np.concatenate([deep, fas]) if len(fas) else deep

    def query_rows(self, deep: np.ndarray, a: int, b: int) -> list[np.ndarray]:
        """Query rows ``[a, b)`` of each noise level, given the Deep1B reference rows from ``a``."""
        fas = self._fas(self.fas_query, a, b, self.layout.n_query)
        return [np.concatenate([q, fas]) for q in noisy_rows(deep, a, self.recipe.seed, self.noise_mean,
                                                             self.noise_std, tuple(NOISE_LEVELS.values()))]

    def __call__(self, a: int, b: int) -> None:
        lay = self.layout
        deep = self.deep_rows(a, b)
        group = zarr.open_group(self.store, mode="r+")
        if a < lay.n_ref:
            write_rows(group["ref"], a, self.ref_rows(a, b, deep))
            group["ref_part"][a : min(b, lay.n_ref)] = self._parts(a, min(b, lay.n_ref))
        if a < lay.n_query:
            q_hi = min(b, lay.n_query)
            for name, q in zip(NOISE_LEVELS, self.query_rows(deep, a, b), strict=True):
                write_rows(group[name], a, q)
            group["gt"][a:q_hi] = dataset_gt(lay, self.fas_gt, a, q_hi)
            group["query_part"][a:q_hi] = self._parts(a, q_hi)

    def _parts(self, a: int, b: int) -> np.ndarray:
        return np.where(np.arange(a, b) >= self.layout.n_deep, FAS, 0).astype(np.uint8)


def consolidate(store: str) -> None:
    """Record every array's and group's metadata in the store's root ``zarr.json`` (zarr's
    consolidated metadata), the last write before the store is published: a reader then opens it
    without listing its folder, and plain zarr no longer warns, on every listing, that it does not
    know the store's ``build.json`` and ``manifest.json``. (zarr says consolidated metadata is not
    yet in the v3 specification; readers without it list the folder, as before.)"""
    with warnings.catch_warnings():  # what zarr says here is about the files of ours it lists (build.json,
        warnings.simplefilter("ignore")  # the publishing's bookkeeping) and the specification: nothing to act on
        zarr.consolidate_metadata(store)
