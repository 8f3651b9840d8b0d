"""``index.json`` of an index directory (the format is :mod:`vprscale.method.indexfile`'s): its
kind, format and completeness, checked against the manifest. Kept apart, importing nothing but
the standard library and the manifest's checksums, so that a command that only opens an index's
metadata starts in a fraction of a second."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from vprscale.core.errors import InputError
from vprscale.core.manifest import check_manifest

KIND = "coarsehash-index"
INDEX_FORMAT = 3  # 3: succinct codes, ids and directory; 2: lists as plain .npy files beside Parquet copies


def load_index_meta(index: str | Path, upgradable: bool = False) -> dict[str, Any]:
    """``index.json`` of a complete index, or an error naming the directory.

    An index of an older format is refused with what to run; with ``upgradable`` a format-2
    index (which ``vprscale index --upgrade`` converts) is returned as it is.
    """
    p = Path(index)
    meta_file = p / "index.json"
    if not meta_file.is_file():
        raise InputError(f"{p}: not a vprscale index (no index.json)")
    try:
        meta = json.loads(meta_file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{meta_file}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict) or not meta.get("complete") or meta.get("kind") != KIND:
        raise InputError(f"{p}: the index is incomplete or of another kind")
    fmt = meta.get("format", 1)
    if fmt < 2:
        raise InputError(f"{p}: an index of an older vprscale (no memory-mapped lists); re-run vprscale index")
    if fmt == 2 and not upgradable:
        raise InputError(f"{p}: an index of format 2 (plain lists, 2-3x larger); convert it without refitting: "
                         f"vprscale index --upgrade {p}")
    if fmt > INDEX_FORMAT:
        raise InputError(f"{p}: index format {fmt} is newer than this vprscale reads ({INDEX_FORMAT}); "
                         "upgrade vprscale")
    check_manifest(p)
    return meta
