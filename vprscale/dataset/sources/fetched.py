"""The manifest ``vprscale fetch`` writes beside each file it fetched (``<file>.manifest.json``:
bytes, CRC32C, source, rows), and the check every reader of such a file makes first: a file cut
short or overwritten since it was fetched is refused in one line, never read as data. The
manifest's fields are written by :mod:`vprscale.dataset.fetch`."""

from __future__ import annotations

import json
from pathlib import Path

from vprscale.core.errors import InputError
from vprscale.core.manifest import CHEAP_BYTES, crc32c_of


def manifest_path(path: Path) -> Path:
    """Where ``fetch`` keeps a fetched file's manifest: beside it, ``<file>.manifest.json``."""
    return path.with_name(f"{path.name}.manifest.json")


def check_fetched(path: Path) -> None:
    """A file ``fetch`` wrote, as it wrote it: its size always and its CRC32C up to ``CHEAP_BYTES``
    against the manifest beside it; a file without one is not checked. Else one line naming it."""
    beside = manifest_path(path)
    if not beside.is_file():
        return
    try:
        manifest = json.loads(beside.read_text())
        size, crc = int(manifest["bytes"]), str(manifest["crc32c"])
    except (OSError, ValueError, KeyError, TypeError):
        raise InputError(f"{beside}: not a manifest vprscale fetch wrote (unreadable); fetch {path.name} "
                         "again") from None
    actual = path.stat().st_size
    if actual != size:
        raise InputError(f"{path}: {actual:,} bytes, the manifest it was fetched with says {size:,} (changed since "
                         "it was fetched); fetch it again")
    if actual <= CHEAP_BYTES and crc32c_of(path) != crc:
        raise InputError(f"{path}: its content changed since it was fetched (checksum differs from {beside.name}); "
                         "fetch it again")
