"""Writers of the real layouts (fvecs, fbin, FAS npz), streamed chunk by chunk.

They exist so that the readers are tested on files in the real layouts and so that a user
can stage synthetic data on disk exactly as the real sets would sit there.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np

from vprscale.dataset.sources.base import RowSource
from vprscale.dataset.sources.fas import Traverse

_CHUNK = 1 << 16


def _atomic_target(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return path.with_name(f".{path.name}.partial")


def write_fvecs(source: RowSource, path: str | os.PathLike, rows_per_file: int | None = None) -> list[Path]:
    """Write ``source`` as fvecs: one file, or ``path/base_NN`` files of ``rows_per_file``."""
    path = Path(path)
    if rows_per_file is None:
        spans, names = [(0, source.n_rows)], [path]
    else:
        spans = [(a, min(source.n_rows, a + rows_per_file)) for a in range(0, source.n_rows, rows_per_file)]
        names = [path / f"base_{i:02d}" for i in range(len(spans))]
    for (a, b), name in zip(spans, names, strict=True):
        tmp = _atomic_target(name)
        with open(tmp, "wb") as fh:
            for lo in range(a, b, _CHUNK):
                x = source.read(lo, min(b, lo + _CHUNK))
                rec = np.empty((len(x), source.dim + 1), dtype="<f4")
                rec[:, 0] = np.array(source.dim, "<i4").view("<f4")
                rec[:, 1:] = x
                fh.write(rec.tobytes())
        tmp.replace(name)
    return names


def write_fbin(source: RowSource, path: str | os.PathLike) -> Path:
    """Write ``source`` as a big-ann-benchmarks ``.fbin``."""
    path = Path(path)
    tmp = _atomic_target(path)
    with open(tmp, "wb") as fh:
        fh.write(np.array([source.n_rows, source.dim], dtype="<u4").tobytes())
        for _, x in source.iter_chunks(_CHUNK):
            fh.write(x.astype("<f4").tobytes())
    tmp.replace(path)
    return path


def _write_member(zf: zipfile.ZipFile, name: str, shape: tuple, dtype: np.dtype, chunks) -> None:
    with zf.open(f"{name}.npy", "w", force_zip64=True) as fh:
        header = {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": False,
                  "shape": shape}
        np.lib.format.write_array_header_2_0(fh, header)
        for part in chunks:
            fh.write(np.ascontiguousarray(part, dtype=dtype).tobytes())


def write_fas_npz(traverse: Traverse, path: str | os.PathLike) -> Path:
    """Write a traverse pair as the FAS100K ``.npz`` (uncompressed members, like np.savez)."""
    path = Path(path)
    tmp = _atomic_target(path)
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, src in (("arr_0", traverse.ref), ("arr_1", traverse.query)):
            _write_member(zf, name, (src.n_rows, src.dim), np.dtype("<f4"),
                          (x for _, x in src.iter_chunks(8192)))
        for name, arr in (("arr_2", traverse.gt), ("arr_3", traverse.ref_pos),
                          ("arr_4", traverse.query_pos), ("arr_5", np.zeros(0)), ("arr_6", np.zeros(0))):
            _write_member(zf, name, arr.shape, arr.dtype, [arr])
    tmp.replace(path)
    return path
