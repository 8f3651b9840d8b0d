"""A dataset of an HDF5 file (``file.hdf5:train``): the ann-benchmarks and VIBE layout (``train``,
``test``, ``neighbors``), read through h5py's hyperslabs, the file opened inside each read; a
file at a URL (``https://…/file.hdf5:train``, ``s3://…``) is read by byte ranges, as h5py asks
for them. h5py is an optional dependency (``pip install "vprscale[hdf5]"``)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.errors import InputError
from vprscale.core.objects import is_url, public
from vprscale.dataset.sources.base import RowSource
from vprscale.dataset.sources.fingerprint import file_fingerprint
from vprscale.dataset.sources.remote import remote_file, remote_fingerprint

SUFFIXES = (".hdf5", ".h5")


def _h5py():
    try:
        import h5py
    except ImportError:
        raise InputError("reading HDF5 needs h5py: pip install \"vprscale[hdf5]\"") from None
    return h5py


def _within(f: Any, key: str, name: str) -> None:
    """Every link on the way to ``key`` stays in the file: an external link would read another
    file (any the user can read) as if it were this one's."""
    h5py, node = _h5py(), f
    for part in [p for p in key.split("/") if p]:
        if not isinstance(node, h5py.Group) or part not in node:
            return  # not there: the caller says what the file holds
        link = node.get(part, getlink=True)
        if isinstance(link, h5py.ExternalLink):
            raise InputError(f"{name}: {part!r} is an external link (to {link.filename}:{link.path}); vprscale reads "
                             "only what the named file holds: give that file itself")
        node = node[part]


def _stored_within(dataset: Any, name: str) -> None:
    """The dataset's bytes are in the file: not external storage (raw files named in the HDF5
    header, any path on the reading machine) and not a virtual dataset (mapped from other files)."""
    if dataset.is_virtual:
        raise InputError(f"{name}: a virtual dataset (its rows are mapped from other files); vprscale reads only "
                         "what the named file holds: copy the rows into a plain dataset (h5py: f2[k] = f1[k][:])")
    if dataset.id.get_create_plist().get_external_count():
        raise InputError(f"{name}: stored in external raw files named by the HDF5 file; vprscale reads only what the "
                         "named file holds: copy the rows into a plain dataset (h5py: f2[k] = f1[k][:])")


def _datasets(f: Any) -> list[str]:
    """The datasets at the top of an open file (hard links only: what the file itself holds)."""
    h5py = _h5py()
    return sorted(k for k in f if isinstance(f.get(k, getlink=True), h5py.HardLink) and isinstance(f[k], h5py.Dataset))


def _checked(f: Any, key: str | None, name: str, what: str) -> tuple[str, tuple, np.dtype]:
    """``(key, shape, dtype)`` of the dataset ``key`` of the open file ``f`` (shown as ``name``),
    held in the file itself; ``key`` None: the file's one 2-D dataset, as a Parquet file's one
    list column is taken (an ann-benchmarks file holds several: they are named)."""
    h5py = _h5py()
    if key is None:
        found = [k for k in _datasets(f) if len(f[k].shape) == 2]
        if len(found) != 1:
            raise InputError(f"{name}: name the dataset of {what} ({name}:DATASET); 2-D datasets: "
                             f"{', '.join(found) or 'none'}")
        key = found[0]
    _within(f, key, f"{name}:{key}")
    if key not in f or not isinstance(f[key], h5py.Dataset):
        raise InputError(f"{name}:{key}: no dataset {key!r} in the file (it holds {', '.join(_datasets(f))})")
    _stored_within(f[key], f"{name}:{key}")
    return key, f[key].shape, f[key].dtype


def _open_file(path: Path | None, url: str | None) -> Any:
    return _h5py().File(remote_file(url) if url else path, "r")


def _located(path: str | os.PathLike) -> tuple[Path | None, str | None, str]:
    """``(local path, url, shown)`` of an HDF5 file named by path or URL (a local one must exist)."""
    url = str(path) if is_url(str(path)) else None
    local = None if url else Path(path).absolute()  # tasks may run elsewhere
    if local is not None and not local.is_file():
        raise InputError(f"{local}: no such file")
    return local, url, public(url) if url else str(local)


class Hdf5Source(RowSource):
    """The 2-D dataset ``key`` of the HDF5 file at ``path`` (a local path or a URL); ``key`` None:
    the file's one 2-D dataset."""

    def __init__(self, path: str | os.PathLike, key: str | None) -> None:
        self.path, self.url, where = _located(path)
        try:
            with self._open() as f:
                self.key, shape, dtype = _checked(f, key, where, "descriptors")
        except OSError as exc:
            raise InputError(f"{where}: not a readable HDF5 file ({str(exc).splitlines()[0][:160]})") from None
        self.name = f"{where}:{self.key}"
        if len(shape) != 2 or dtype.kind not in "fiu" or shape[1] == 0:
            raise InputError(f"{self.name}: a 2-D dataset of descriptor rows expected, not {len(shape)}-D {dtype} "
                             f"{shape}")
        self.n_rows, self.dim = int(shape[0]), int(shape[1])
        self._file = remote_fingerprint(self.url) if self.url else file_fingerprint(self.path)

    def _open(self) -> Any:
        return _open_file(self.path, self.url)

    def _read(self, start: int, stop: int) -> np.ndarray:
        with self._open() as f:
            return np.asarray(f[self.key][start:stop], np.float32)

    def fingerprint(self) -> dict[str, Any]:
        return {"format": "hdf5", "dataset": self.key, "rows": self.n_rows, "dim": self.dim,
                "files": [self._file]}


def read_ids(path: str | os.PathLike, key: str) -> np.ndarray:
    """The integer dataset ``key`` of an HDF5 file, read whole: ground truth as ann-benchmarks keeps
    it (``neighbors``, n × k, nearest first) or one id a row (n)."""
    local, url, where = _located(path)
    try:
        with _open_file(local, url) as f:
            key, shape, dtype = _checked(f, key, where, "ids")
            if len(shape) not in (1, 2) or dtype.kind not in "iu" or (len(shape) == 2 and shape[1] == 0):
                raise InputError(f"{where}:{key}: an integer dataset of ids (n, or n × k nearest first) expected, "
                                 f"not {len(shape)}-D {dtype} {shape}")
            return np.asarray(f[key][()])
    except OSError as exc:
        raise InputError(f"{where}: not a readable HDF5 file ({str(exc).splitlines()[0][:160]})") from None
