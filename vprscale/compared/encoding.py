"""A FAISS method's stored encoding of a store's references: the one on-disk format of the
compact-code comparison (written by ``vprscale encode``, read by ``vprscale eval --compare``).

An encoding lives beside its store, ``<store>.faiss/<method>/`` (``data/paper/1B.faiss/
IVF4096_PQ3/`` for ``data/paper/1B.zarr``), because it depends on the store's references
only, not on a CoarseHash index:

- ``trained.faiss``: the trained, empty FAISS index (``faiss.write_index``);
- ``codes.npy``: every reference's standalone FAISS code (``sa_code_size`` bytes: for IVF
  the list number, then the code), in id order: from them the inverted lists
  (``add_sa_codes``), the window scores' codes, list numbers and distance terms are all
  rebuilt in one sequential read, so nothing else is stored;
- ``encoding.json``: the factory, the store's identity, the number of references and the
  training rows, with the provenance of the run.

The codes of a stored encoding are the bytes an evaluation encoding in its own process
writes (the same training rows, the same blocks), so an evaluation answers the same either way.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import faiss
import numpy as np

from vprscale.compared.faisscodes import FaissCodes
from vprscale.core.errors import InputError

ENCODING_FORMAT = 1
LOAD_ROWS = 1 << 20  # codes added to the FAISS index at a time when an encoding is loaded


def encodings_dir(store: Path) -> Path:
    """Where the encodings of ``store`` live: ``<store without .zarr>.faiss`` beside it."""
    return store.with_name(f"{store.name.removesuffix('.zarr')}.faiss")


def encoding_dir(store: Path, factory: str) -> Path:
    """The directory of one FAISS method's encoding of ``store`` (its factory string, file-safe)."""
    return encodings_dir(store) / re.sub(r"[^A-Za-z0-9]+", "_", factory).strip("_")


def write_trained(codes: FaissCodes, out: Path, n_ref: int) -> None:
    """The trained (still empty) index, and an empty code array for ``n_ref`` references."""
    faiss.write_index(codes.index, str(out / "trained.faiss"))
    np.lib.format.open_memmap(out / "codes.npy", mode="w+", dtype=np.uint8, shape=(n_ref, codes.index.sa_code_size()))


def read_trained(out: Path, factory: str, dim: int) -> FaissCodes:
    """A FaissCodes on the trained index stored in ``out`` (single-threaded: a task of a pass)."""
    codes = FaissCodes(factory, dim, k=1)
    codes.bind(faiss.read_index(str(out / "trained.faiss")))
    return codes


def describe(factory: str, identity: str, n_ref: int, train_rows: int, record: dict[str, Any]) -> dict[str, Any]:
    """The contents of ``encoding.json``."""
    return {"format": ENCODING_FORMAT, "factory": factory, "store_identity": identity, "n_ref": n_ref,
            "training_rows": train_rows, "provenance": record}


def stored_encoding(store: Path, factory: str, identity: str) -> Path | None:
    """The published encoding of ``factory`` for this store, if there is one; a stale one is refused."""
    out = encoding_dir(store, factory)
    meta_file = out / "encoding.json"
    if not meta_file.is_file():
        return None
    meta = json.loads(meta_file.read_text())
    if meta.get("format") != ENCODING_FORMAT or meta.get("factory") != factory:
        raise InputError(f"{out}: not an encoding of {factory} in this version's format; re-run vprscale encode "
                         "with --force")
    if meta.get("store_identity") != identity:
        raise InputError(f"{out}: encodes another store than {store} (rebuilt since?); re-run vprscale encode "
                         "with --force")
    return out


def load_encoding(out: Path, codes: FaissCodes) -> None:
    """Give ``codes`` (a method not yet trained) the stored trained index and every reference's code."""
    codes.bind(faiss.read_index(str(out / "trained.faiss")))
    stored = np.load(out / "codes.npy", mmap_mode="r")
    codes.start(len(stored))
    for i in range(0, len(stored), LOAD_ROWS):
        codes.add_codes(np.ascontiguousarray(stored[i : i + LOAD_ROWS]))
    codes.finish()
