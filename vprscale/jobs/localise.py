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
from vprscale.dataset.store import open_complete_group
from vprscale.method.index import Index
from vprscale.method.indexfile import load_index_meta
from vprscale.method.online import OnlineMatcher
from vprscale.protocol import centre_lag

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
    from vprscale.dataset.sources.deep1b import open_deep1b

    src = open_deep1b(path)
    return src.n_rows, src.dim, (src.read(a, min(src.n_rows, a + READ_ROWS)) for a in range(0, src.n_rows, READ_ROWS))


OUT_FORMATS = {".parquet": "parquet", ".pq": "parquet", ".csv": "csv"}


def write_matches(table: pa.Table, where: Any, fmt: str) -> None:
    """One row per frame as Parquet or CSV: ``frame``, ``centre``, ``match``, ``n_r`` and ``score``
    (the matched window's, in δ_max units as the batch reports it; lower is more confident). The
    first L − 1 frames complete no window: their columns are null (empty in CSV), and pandas reads
    the Parquet file's integer columns as nullable integers (``Int64``), not floats with NaN."""
    if fmt == "csv":
        pacsv.write_csv(table, where)
        return
    frame = table.to_pandas(types_mapper={pa.int64(): pd.Int64Dtype()}.get)
    pq.write_table(pa.Table.from_pandas(frame, preserve_index=False), where)


def localise(index: str | Path, queries: str | Path, L: int, mode: str = "paper", out: str | Path | None = None,
             quiet: bool = False) -> dict[str, Any]:
    """Localise every frame of ``queries``; returns a summary, and writes the rows to ``out`` (a
    ``.parquet`` or ``.csv`` file, whole or not at all; ``"-"``: CSV on standard output) when given."""
    meta = load_index_meta(index)
    path = Path(queries)
    if not path.exists():
        raise InputError(f"{path}: no such query file or array")
    rows, width, blocks = _blocks(path)
    if width != meta["dim"]:
        raise InputError(f"{path}: frames of {width} features; the index hashes frames of {meta['dim']}")
    to_stdout = out == "-"
    if out is not None and not to_stdout:
        out = Path(out)
        if out.is_dir():
            raise InputError(f"--out {out}: is a directory; give a file name")
        if out.suffix.lower() not in OUT_FORMATS:
            raise InputError(f"--out {out}: name a .parquet or .csv file (the suffix says the format)")
        if not out.parent.is_dir():
            raise InputError(f"--out {out}: the folder {out.parent} does not exist")
        if not os.access(out.parent, os.W_OK | os.X_OK):
            raise InputError(f"--out {out}: the folder {out.parent} is not writable")
    if isinstance(L, int) and L > rows:
        raise InputError(f"--L {L}: longer than the {rows:,} frames of {path}")
    try:
        matcher = OnlineMatcher(Index.load(index), L, mode)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    lag = centre_lag(L)
    match = np.full(rows, -1, np.int64)
    n_r = np.zeros(rows, np.int64)
    score = np.full(rows, np.nan)
    progress = None if quiet else ChunkProgress("localise", (rows + READ_ROWS - 1) // READ_ROWS)
    t0 = time.perf_counter()
    u = 0
    for block in blocks:
        bad = np.flatnonzero(~np.isfinite(block).all(axis=1))
        if len(bad):  # a NaN frame would hash to an arbitrary address and be matched
            raise InputError(f"{path}: frame {u + int(bad[0]):,} holds NaN or Inf")
        got, got_n_r, got_score = matcher.push_many(block, return_score=True)  # frame by frame, one call a block
        done = got >= 0
        at = slice(u, u + len(block))
        match[at][done], n_r[at][done], score[at][done] = got[done], got_n_r[done], got_score[done]
        u += len(block)
        if progress:
            progress.update(1)
    secs = time.perf_counter() - t0
    frames = np.arange(rows)
    done = match >= 0
    table = pa.table({"frame": frames, "centre": pa.array(np.where(done, frames - lag, 0), mask=~done),
                      "match": pa.array(match, mask=~done), "n_r": pa.array(n_r, mask=~done),
                      "score": pa.array(score, mask=~done)})
    if to_stdout:
        sys.stdout.flush()
        write_matches(table, sys.stdout.buffer, "csv")
    elif out is not None:
        tmp = out.with_name(f".{out.name}.partial")
        write_matches(table, tmp, OUT_FORMATS[out.suffix.lower()])
        tmp.replace(out)
    if not quiet:
        log.info(f"localised {rows:,} frames in {secs:.1f} s ({secs / max(1, rows) * 1e6:.1f} µs per frame)")
    return {"frames": rows, "L": L, "mode": mode, "seconds": secs, "us_per_frame": secs / max(1, rows) * 1e6,
            "out": str(out) if out else None, "state_bytes": matcher.state_bytes}
