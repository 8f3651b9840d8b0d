"""The dataset store (Zarr v3, docs/dataset.md): opening a complete store and reading what
every job asks of it (its provenance digest, layout, reference moments, compact model).

The layouts themselves are written by :mod:`vprscale.dataset.layout` (full) and
:mod:`vprscale.dataset.compact`; this module is how everything above reads a store.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from vprscale.core.errors import InputError
from vprscale.core.manifest import check_manifest, made_since_manifests, read_record, remake
from vprscale.core.objects import Remote, location, zarr_url
from vprscale.method.coarsehash import CoarseHasher
from vprscale.protocol import Sequences

ATTR = "vprscale"
MODEL = ("mean", "components", "centres", "explained_variance", "ranges")  # a compact store's CoarseHash model


def open_complete_group(path: str | os.PathLike | Remote, kind: str = "dataset") -> zarr.Group:
    """Open a published Zarr store (a local path or a URL), refusing one that is missing or not
    marked complete."""
    p = path if isinstance(path, Remote) else location(path)
    if not (p / "zarr.json").is_file():
        if not p.exists():
            raise InputError(f"{p}: no such {'object or prefix' if isinstance(p, Remote) else 'file or directory'}")
        raise InputError(f"{p}: not a vprscale {kind} store (no zarr.json)")
    try:
        group = zarr.open_group(zarr_url(p), mode="r")
        meta = group.attrs.get(ATTR, {})
    except (ValueError, TypeError, KeyError) as exc:  # zarr's errors for a broken zarr.json
        raise InputError(f"{p / 'zarr.json'}: not readable Zarr metadata ({str(exc).splitlines()[0][:200]})") from None
    if not meta.get("complete"):
        raise InputError(f"{p}: the {kind} store is incomplete (its build did not finish)")
    check_manifest(p, remake=_remake(p, meta, kind))
    return group


def _remake(store: Path | Remote, meta: dict[str, Any], kind: str) -> str | None:
    """How to re-create a store published with a manifest (None for one built before 0.3, which
    had none): the command its ``build.json`` records. A store of your own data (no recipe
    versions recorded) is 0.3 or later by birth."""
    usual = f"vprscale build … --out {store.parent} --force (the build that made {store.name})"
    since = made_since_manifests(meta.get("versions", {}).get("vprscale", "0.3"))
    return remake(read_record(store / "build.json"), usual, since)


def store_identity(group: zarr.Group) -> str:
    """A digest of an opened store's provenance: an index records it, an evaluation checks it."""
    meta = group.attrs[ATTR]
    core = {k: meta.get(k) for k in ("recipe", "sources", "layout", "seed", "rescale")}
    return hashlib.sha256(json.dumps(core, sort_keys=True, default=str).encode()).hexdigest()[:16]


def store_layout(group: zarr.Group) -> dict[str, Any]:
    """The layout attributes of a store (``kind`` is ``full`` for stores built before layouts had a name)."""
    return {"kind": "full", **group.attrs[ATTR].get("layout", {})}


def read_sequences(group: zarr.Group, side: str) -> Sequences | None:
    """The sequences of the store's ``side`` rows (``ref`` or ``query``), from its ``<side>_seq``
    and ``<side>_frame`` arrays; None for a store of one traverse (every recipe's)."""
    if f"{side}_seq" not in group:
        return None
    return Sequences(group[f"{side}_seq"][:], group[f"{side}_frame"][:])


def ref_moments(group: zarr.Group) -> np.ndarray | None:
    """The reference moments a build derived (``None`` for stores built before they were kept)."""
    t = group.get("transforms")
    return t["ref_moments"][:] if t is not None and "ref_moments" in t else None


def load_model(group: zarr.Group) -> CoarseHasher:
    """The CoarseHash model a compact store was hashed with."""
    m = group["transforms/coarsehash"]
    return CoarseHasher.from_fitted(int(m.attrs["k"]), int(m.attrs["bins"]), int(group["ref_hash"].shape[0]),
                                    **{name: m[name][:] for name in MODEL})
