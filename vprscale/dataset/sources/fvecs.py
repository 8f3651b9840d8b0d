"""TEXMEX vector records (a little-endian int32 ``d``, then ``d`` values: float32 in fvecs, uint8
in bvecs, int32 in ivecs) read from parts laid end to end: local files and chunk directories
(:mod:`~vprscale.dataset.sources.deep1b`) and objects read by byte ranges
(:mod:`~vprscale.dataset.sources.remote`) share this, and its checks."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from vprscale.core.errors import InputError

VALUES = {".fvecs": np.dtype("<f4"), ".bvecs": np.dtype("u1"), ".ivecs": np.dtype("<i4")}  # by file suffix


def vecs_type(name: str) -> tuple[str, np.dtype]:
    """The form (``fvecs``, ``bvecs``, ``ivecs``) and value type of a file or object by its name;
    a name without one of those suffixes (Deep1B's chunks, ``base_00``) is fvecs."""
    suffix = next((s for s in VALUES if name.endswith(s)), ".fvecs")
    return suffix[1:], VALUES[suffix]


def record_bytes(dim: int, values: np.dtype) -> int:
    return 4 + dim * values.itemsize


def read_vecs(starts: np.ndarray, dim: int, values: np.dtype, start: int, stop: int,
              records: Callable[[int, int, int], np.ndarray], name: Callable[[int], str]) -> np.ndarray:
    """Rows ``[start, stop)`` as float32 of vector parts laid end to end (``starts``: each part's first
    row, then the total); ``records(i, lo, hi)`` gives records ``lo … hi − 1`` of part ``i`` as
    uint8 rows of :func:`record_bytes` (a file's pages, a range fetched), every record's dimension
    checked."""
    out = np.empty((stop - start, dim), dtype=np.float32)
    size = record_bytes(dim, values)
    first = int(np.searchsorted(starts, start, side="right")) - 1
    for i in range(first, len(starts) - 1):
        f_lo, f_hi = int(starts[i]), int(starts[i + 1])
        if f_lo >= stop:
            break
        lo, hi = max(start, f_lo) - f_lo, min(stop, f_hi) - f_lo
        if hi <= lo:
            continue
        rec = records(i, lo, hi)
        dims = np.ascontiguousarray(rec[:, :4]).view("<i4")[:, 0]
        bad = np.flatnonzero(dims != dim)
        if bad.size:
            raise InputError(f"{name(i)}: offset {(lo + int(bad[0])) * size}: record dimension "
                             f"{int(dims[bad[0]])}, expected {dim}")
        out[f_lo + lo - start : f_lo + hi - start] = np.ascontiguousarray(rec[:, 4:]).view(values)
        del rec
    return out
