"""The FAS part of a build's fit, kept between builds.

Every scale from 1M up keeps all of FAS100K, so its FAS PCA (a randomized solver over 47,781
rows of 4,096 values), the noise PCA and noise model, and the projected FAS rows are the same
for every rung of the ladder and for the no-rescale ablation. They are computed once per FAS
source and kept under ``$VPRSCALE_CACHE/fas-fit/``, keyed by what they depend on: the
traverse's fingerprint (a file's size, time and sampled hash, or the generator's parameters),
the FAS rows kept, D, the seed, and the code that computes them (the bytes of the PCA and
merge modules, :func:`code_digest`), so a changed source, recipe or solver never meets a
stale entry. A hit gives the very arrays the fit would: the store's bytes are the same.
"""

from __future__ import annotations

import hashlib
import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.objects import cache_root

FORMAT = 1


def code_digest(*files: str | os.PathLike) -> str:
    """The bytes of the modules that compute the cached arrays (the caller names them)."""
    h = hashlib.sha256()
    for f in files:
        h.update(Path(f).read_bytes())
    return h.hexdigest()


def _path(key: dict[str, Any]) -> Path:
    text = json.dumps({"format": FORMAT, **key}, sort_keys=True, default=str)
    return cache_root() / "fas-fit" / f"{hashlib.sha256(text.encode()).hexdigest()[:24]}.npz"


def load(key: dict[str, Any]) -> dict[str, np.ndarray] | None:
    """The arrays saved for ``key``, or None (none saved, or an unreadable entry: fitted again)."""
    path = _path(key)
    try:
        with np.load(path, allow_pickle=False) as z:
            return {name: z[name] for name in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        return None


def save(key: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
    """Keep ``arrays`` for ``key``, whole or not at all (written beside, then renamed); a cache
    that cannot be written is skipped: the next build fits again."""
    path = _path(key)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
        tmp.replace(path)
    except OSError:
        tmp.unlink(missing_ok=True)
