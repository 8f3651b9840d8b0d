"""fvecs records (a little-endian int32 ``d``, then ``d`` float32) read from parts laid end to end:
the local chunk files of Deep1B (:mod:`~vprscale.dataset.sources.deep1b`) and its objects read by
byte ranges (:mod:`~vprscale.dataset.sources.remote`) share this, and its checks."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from vprscale.core.errors import InputError


def read_fvecs(starts: np.ndarray, dim: int, start: int, stop: int, records: Callable[[int, int, int], np.ndarray],
               name: Callable[[int], str]) -> np.ndarray:
    """Rows ``[start, stop)`` of fvecs parts laid end to end (``starts``: each part's first row, then
    the total); ``records(i, lo, hi)`` gives records ``lo … hi − 1`` of part ``i`` as int32 rows of
    ``d + 1`` (a file's pages, a range fetched), every record's dimension checked."""
    out = np.empty((stop - start, dim), dtype=np.float32)
    first = int(np.searchsorted(starts, start, side="right")) - 1
    for i in range(first, len(starts) - 1):
        f_lo, f_hi = int(starts[i]), int(starts[i + 1])
        if f_lo >= stop:
            break
        lo, hi = max(start, f_lo) - f_lo, min(stop, f_hi) - f_lo
        if hi <= lo:
            continue
        rec = records(i, lo, hi)
        bad = np.flatnonzero(rec[:, 0] != dim)
        if bad.size:
            raise InputError(f"{name(i)}: offset {(lo + int(bad[0])) * 4 * (dim + 1)}: record dimension "
                             f"{int(rec[bad[0], 0])}, expected {dim}")
        out[f_lo + lo - start : f_lo + hi - start] = rec[:, 1:].view("<f4")
        del rec
    return out
