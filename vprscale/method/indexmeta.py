"""``index.json`` of an index directory (the format is :mod:`vprscale.method.indexfile`'s): its
kind, format and completeness, checked against the manifest. Kept apart, importing nothing but
the standard library and the manifest's checksums, so that a command that only opens an index's
metadata starts in a fraction of a second."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from vprscale.core.errors import InputError
from vprscale.core.manifest import check_manifest, remake

KIND = "coarsehash-index"
INDEX_FORMAT = 4  # 4: Parquet tables; 3: succinct codes, ids and directory as .npy; 2: plain .npy lists


def load_index_meta(index: str | Path, upgradable: bool = False, full: bool = False) -> dict[str, Any]:
    """``index.json`` of a complete index, or an error naming the directory.

    An index of an older format is refused with what to run; with ``upgradable`` a format-2 or
    format-3 index (which ``vprscale index --upgrade`` converts) is returned as it is. ``full`` checks every
    checksum of the manifest (``vprscale verify``), not only the cheap ones.
    """
    p = Path(index)
    meta = read_index_meta(p)
    fmt = meta.get("format", 1)
    if fmt < 2:
        raise InputError(f"{p}: an index of an older vprscale (no memory-mapped lists); re-run vprscale index")
    if fmt in (2, 3) and not upgradable:
        held = "plain lists, 2-3x larger" if fmt == 2 else "lists in vprscale's own files, not Parquet tables"
        raise InputError(f"{p}: an index of format {fmt} ({held}); convert it without refitting: "
                         f"vprscale index --upgrade {p}")
    if fmt > INDEX_FORMAT:
        raise InputError(f"{p}: index format {fmt} is newer than this vprscale reads ({INDEX_FORMAT}); "
                         "upgrade vprscale")
    return checked(p, meta, full)


def read_index_meta(p: Path) -> dict[str, Any]:
    """``index.json`` of a complete index of any format, not yet checked against the manifest."""
    meta_file = p / "index.json"
    if not meta_file.is_file():
        raise InputError(f"{p}: not a vprscale index (no index.json)")
    try:
        meta = json.loads(meta_file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{meta_file}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict) or not meta.get("complete") or meta.get("kind") != KIND:
        raise InputError(f"{p}: the index is incomplete or of another kind")
    _parameters(meta_file, meta)
    return meta


def _parameters(meta_file: Path, meta: dict[str, Any]) -> None:
    """``d``, ``k``, ``n_ref`` and ``dim`` (where given) as the engine can hold them (every later check of the
    tables and the model is against these): integers, K ≥ 2, K^d addresses in 64 bits."""
    for key, low in (("d", 1), ("k", 2), ("n_ref", 1), ("dim", 1)):
        value = meta.get(key)
        if key == "dim" and value is None:  # an index of a vprscale before 0.4 does not say: its model does
            continue
        if type(value) is not int or value < low:
            raise InputError(f"{meta_file}: {key} is {value!r}, not an integer of at least {low}")
    if meta["k"] ** meta["d"] > 1 << 64:
        raise InputError(f"{meta_file}: k^d = {meta['k']}^{meta['d']} addresses do not fit 64 bits")
    if meta["n_ref"] > 1 << 40:
        raise InputError(f"{meta_file}: n_ref {meta['n_ref']:,} is beyond any index vprscale writes")


def checked(p: Path, meta: dict[str, Any], full: bool = False) -> dict[str, Any]:
    """``meta`` once the index checks out against its manifest. Every index of format 3 was
    published with one: without it, it has lost its checks and is refused (an older one, which
    may predate manifests, is read as it is)."""
    fmt = meta.get("format", 1)
    store = meta.get("store", {}).get("path", "STORE") if isinstance(meta.get("store"), dict) else "STORE"
    check_manifest(p, full=full, remake=remake(meta if fmt >= 3 else None, f"vprscale index {store} --out {p} --force",
                                               published=fmt >= 3))
    return meta
