"""``vprscale localise``: stream a traverse's frames through the online matcher.

The method applied to a user's own traverse: query descriptors are read in order, a block
of rows at a time, from a store array (``STORE.zarr/query_qm1``), an ``.npy`` file, an
fvecs file or directory, or an ``.fbin``; each frame is pushed into an
:class:`~vprscale.method.online.OnlineMatcher`; one row per frame (``frame``, the ``centre`` whose
window it completes, ``match``, ``n_r``; empty until L frames) goes to a Parquet file,
written beside its destination and renamed into place when whole.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
import zarr

from vprscale.core.errors import InputError
from vprscale.core.progress import ChunkProgress
from vprscale.core.publish import check_file_output, publish_file
from vprscale.dataset.store import open_complete_group, read_sequences, store_identity
from vprscale.method.index import Index
from vprscale.method.indexfile import load_index_meta
from vprscale.method.online import OnlineMatcher
from vprscale.protocol import centre_lag, window_mask

log = logging.getLogger(__name__)

READ_ROWS = 4096


def _blocks(path: Path) -> tuple[int, int, Iterator[np.ndarray]]:
    """``(rows, width, blocks of rows)`` of a query source."""
    if (path / "zarr.json").is_file():
        if (path.parent / "zarr.json").is_file():  # an array of a store: read only once the store checks out
            arr = open_complete_group(path.parent).get(path.name)
            if not isinstance(arr, zarr.Array):
                raise InputError(f"{path}: not an array of the store {path.parent}")
        else:
            try:
                arr = zarr.open_array(path, mode="r")
            except Exception as exc:  # noqa: BLE001 - zarr's errors for a group or a damaged array vary
                raise InputError(f"{path}: not a readable Zarr array ({exc})") from None
            _check_written(arr, path)
        if arr.ndim != 2:
            raise InputError(f"{path}: a {arr.ndim}-D array, not rows of descriptors")
        return arr.shape[0], arr.shape[1], (arr[a : a + READ_ROWS] for a in range(0, arr.shape[0], READ_ROWS))
    if path.suffix == ".npy":
        try:
            arr = np.load(path, mmap_mode="r")
        except (ValueError, OSError) as exc:
            raise InputError(f"{path}: not a readable .npy array ({exc})") from None
        if arr.ndim != 2 or arr.dtype.kind != "f":
            raise InputError(f"{path}: holds {arr.dtype} of shape {arr.shape}, not rows of float descriptors")
        return arr.shape[0], arr.shape[1], (np.asarray(arr[a : a + READ_ROWS]) for a in range(0, len(arr), READ_ROWS))
    from vprscale.dataset.sources.rows import open_rows

    src = open_rows(path)
    return src.n_rows, src.dim, (src.read(a, min(src.n_rows, a + READ_ROWS)) for a in range(0, src.n_rows, READ_ROWS))


def _check_written(arr: zarr.Array, path: Path) -> None:
    """Refuse an array that declares more rows than its written chunks hold: Zarr reads an
    unwritten chunk as its fill value, which are no frames (and 10^11 declared rows would be
    matched for days). The chunk (or shard) files are counted as they are listed, so the check
    costs what the array holds, not what it declares."""
    grid = getattr(arr, "shards", None) or arr.chunks
    objects = math.prod(-(-s // c) for s, c in zip(arr.shape, grid, strict=True))
    written = sum(len(files) for _, _, files in os.walk(path / "c"))
    if written < objects:
        raise InputError(f"{path}: declares {arr.shape[0]:,} rows in {objects:,} chunks, of which {written:,} are "
                         "written: the others are no frames")


OUT_FORMATS = {".parquet": "parquet", ".pq": "parquet", ".csv": "csv"}


class MatchWriter:
    """One row per frame as Parquet or CSV, a block of frames at a time (memory stays a block's,
    whatever the traverse's length): ``frame``, ``centre``, ``match``, ``n_r`` and ``score`` (the
    matched window's, in δ_max units as the batch reports it; lower is more confident). The first
    L − 1 frames complete no window: their columns are null (empty in CSV), and pandas reads the
    Parquet file's integer columns as nullable integers (``Int64``), not floats with NaN."""

    def __init__(self, where: Any, fmt: str) -> None:
        self.where, self.fmt, self.writer = where, fmt, None

    def write(self, table: pa.Table) -> None:
        if self.fmt == "parquet":  # through pandas' nullable integers, whose metadata the file keeps
            frame = table.to_pandas(types_mapper={pa.int64(): pd.Int64Dtype()}.get)
            table = pa.Table.from_pandas(frame, preserve_index=False)
            if self.writer is None:
                self.writer = pq.ParquetWriter(self.where, table.schema)
        elif self.writer is None:
            self.writer = pacsv.CSVWriter(self.where, table.schema)
        self.writer.write_table(table)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


def localise(index: str | Path, queries: str | Path, L: int, mode: str = "paper", out: str | Path | None = None,
             quiet: bool = False, top: int | None = None, force: bool = False,
             store: str | Path | None = None) -> dict[str, Any]:
    """Localise every frame of ``queries``; returns a summary, and writes the rows to ``out`` (a
    ``.parquet`` or ``.csv`` file, whole or not at all, an existing one replaced only with
    ``force`` and kept beside; ``"-"``: CSV on standard output) when given, with each window's
    ``top`` best candidates as columns ``top_1 …`` when asked for. With the index's ``store``, a
    map of many sequences: no window that crosses a sequence's end or a gap is ever answered."""
    meta = load_index_meta(index)
    valid = None
    if store is not None:
        group = open_complete_group(store)
        if store_identity(group) != (meta.get("store") or {}).get("identity"):
            raise InputError(f"--store {store}: not the store {index} was built from")
        valid = window_mask(read_sequences(group, "ref"), L)
    path = Path(queries)
    if not path.exists():
        raise InputError(f"{path}: no such query file or array")
    rows, width, blocks = _blocks(path)
    if width != meta["dim"]:
        raise InputError(f"{path}: frames of {width} features; the index hashes frames of {meta['dim']}")
    to_stdout = out == "-"
    if out is not None and not to_stdout:
        out = Path(out)
        check_file_output(out, force)
        if out.suffix.lower() not in OUT_FORMATS:
            raise InputError(f"--out {out}: name a .parquet or .csv file (the suffix says the format)")
        if not out.parent.is_dir():
            raise InputError(f"--out {out}: the folder {out.parent} does not exist")
        if not os.access(out.parent, os.W_OK | os.X_OK):
            raise InputError(f"--out {out}: the folder {out.parent} is not writable")
    if isinstance(L, int) and L > rows:
        raise InputError(f"--L {L}: longer than the {rows:,} frames of {path}")
    try:
        matcher = OnlineMatcher(Index.load(index), L, mode, n_best=top or 1, valid=valid)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    # the kernels compiled (a first run: numba's) before the matching is timed, on frames of no consequence
    OnlineMatcher(matcher.index, L, mode, n_best=top or 1).push_many(np.zeros((L + 1, width), np.float32),
                                                                     return_score=True, return_top=bool(top))
    lag = centre_lag(L)
    progress = None if quiet else ChunkProgress("localise", (rows + READ_ROWS - 1) // READ_ROWS)
    tmp = None if out is None or to_stdout else out.with_name(f".{out.name}.partial")
    if to_stdout:
        sys.stdout.flush()
    writer = None if out is None else MatchWriter(sys.stdout.buffer if to_stdout else tmp,
                                                  "csv" if to_stdout else OUT_FORMATS[out.suffix.lower()])
    secs, u = 0.0, 0  # the matcher's time, not the reading's or the writing's
    try:
        for block in blocks:
            bad = np.flatnonzero(~np.isfinite(block).all(axis=1))
            if len(bad):  # a NaN frame would hash to an arbitrary address and be matched
                raise InputError(f"{path}: frame {u + int(bad[0]):,} holds NaN or Inf")
            t1 = time.perf_counter()
            match, n_r, score, *best = matcher.push_many(block, return_score=True, return_top=bool(top))  # one call
            secs += time.perf_counter() - t1
            if writer is not None:
                frames = np.arange(u, u + len(block))
                done = match >= 0
                columns = {"frame": frames, "centre": pa.array(np.where(done, frames - lag, 0), mask=~done),
                           "match": pa.array(match, mask=~done), "n_r": pa.array(n_r, mask=~done),
                           "score": pa.array(score, mask=~done)}
                for j in range(top or 0):
                    columns[f"top_{j + 1}"] = pa.array(best[0][:, j], mask=best[0][:, j] < 0)
                writer.write(pa.table(columns))
            u += len(block)
            if progress:
                progress.update(1)
        if writer is not None:
            writer.close()
    except BaseException:
        if tmp is not None:
            tmp.unlink(missing_ok=True)  # never a partial file left to look like matches
        raise
    if tmp is not None:
        publish_file(tmp, out)
    if not quiet:
        log.info(f"localised {rows:,} frames: {secs:.1f} s of matching ({secs / max(1, rows) * 1e6:.1f} µs a frame)")
    return {"frames": rows, "L": L, "mode": mode, "seconds": secs, "us_per_frame": secs / max(1, rows) * 1e6,
            "out": str(out) if out else None, "state_bytes": matcher.state_bytes}
