"""Rows of a source written into a store in another order, out of core.

A dataset's own layout fixes the order of its rows (MSLS's: city by city, each side in its
``seq_info.csv`` order), while descriptors come in whatever order a network wrote them. Reading
each store chunk's rows where they lie would read the whole source once per chunk; instead the
source is read once, in order, and each row is appended to a bucket file of the chunk it goes
to; then each chunk is assembled from its bucket and written whole. Memory holds one block of
rows and one chunk; the disk holds one more copy of the rows, in the work folder, while it runs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import zarr

from vprscale.core.progress import ChunkProgress
from vprscale.dataset.sources.base import RowSource

READ_ROWS = 1 << 16  # source rows read at a time (at most)


def in_order(src_rows: np.ndarray) -> bool:
    """Whether the rows asked for are one run of the source, in order (copied as they are)."""
    return len(src_rows) == 0 or bool((np.diff(src_rows) == 1).all())


def reorder_into(source: RowSource, src_rows: np.ndarray, array: zarr.Array, work: Path,
                 progress: bool = True) -> None:
    """Write ``source``'s rows ``src_rows[i]`` as row ``i`` of ``array`` (one row each, no repeats)."""
    n, chunk = len(src_rows), int(array.chunks[0])
    if in_order(src_rows):
        first = int(src_rows[0]) if n else 0
        bar = ChunkProgress(f"copy {array.basename}", -(-n // chunk)) if progress else None
        for a in range(0, n, chunk):
            array[a : a + chunk] = source.read(first + a, first + min(n, a + chunk))
            if bar:
                bar.update(1)
        return
    work.mkdir(parents=True, exist_ok=True)
    for f in work.glob("bucket-*"):  # a killed run's buckets: started again
        f.unlink()
    dest = np.full(source.n_rows, -1, np.int64)
    dest[src_rows] = np.arange(n, dtype=np.int64)
    bar = ChunkProgress(f"sort {array.basename} rows into chunks", -(-source.n_rows // READ_ROWS)) if progress else None
    for a in range(0, source.n_rows, READ_ROWS):
        b = min(source.n_rows, a + READ_ROWS)
        to = dest[a:b]
        held = np.flatnonzero(to >= 0)
        if len(held):
            rows, to = source.read(a, b)[held], to[held]
            bucket = to // chunk
            order = np.argsort(bucket, kind="stable")
            rows, to, bucket = rows[order], to[order], bucket[order]
            edges = np.flatnonzero(np.diff(bucket)) + 1
            for lo, hi in zip(np.r_[0, edges], np.r_[edges, len(bucket)], strict=True):
                j = int(bucket[lo])
                with open(work / f"bucket-{j}.rows", "ab") as fh:
                    fh.write(rows[lo:hi].tobytes())
                with open(work / f"bucket-{j}.to", "ab") as fh:
                    fh.write(to[lo:hi].tobytes())
        if bar:
            bar.update(1)
    bar = ChunkProgress(f"write {array.basename} chunks", -(-n // chunk)) if progress else None
    for j, a in enumerate(range(0, n, chunk)):
        rows = np.fromfile(work / f"bucket-{j}.rows", np.float32).reshape(-1, source.dim)
        to = np.fromfile(work / f"bucket-{j}.to", np.int64)
        out = np.empty((min(n, a + chunk) - a, source.dim), np.float32)
        out[to - a] = rows
        array[a : a + len(out)] = out
        (work / f"bucket-{j}.rows").unlink()
        (work / f"bucket-{j}.to").unlink()
        if bar:
            bar.update(1)
