"""The manifest of a published output: every file it holds, with its size and a CRC32C.

A store, an index or an evaluation is published with ``manifest.json`` beside its files
(:class:`~vprscale.core.publish.PartialOutput` writes it as the last step before sealing).
Opening an output checks that every listed file is there with its size (a ``stat`` per
file) and the checksums of its smallest files up to ``CHEAP_BYTES`` (the whole output below
that size: a 20K store or index, a 1B index's model and directory arrays), so a deleted,
truncated, permuted or overwritten file is an error naming it, never zeros or a wrong answer;
``vprscale verify`` checks every checksum (CRC32C runs at several GB/s, so a full check costs
about one read of the output). Outputs written before manifests existed have
none and are opened as before.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import google_crc32c

from vprscale.core.errors import InputError

NAME = "manifest.json"
FORMAT = 1
READ_BYTES = 1 << 24


def _crc(path: Path) -> str:
    crc = google_crc32c.Checksum()
    with open(path, "rb") as fh:
        while block := fh.read(READ_BYTES):
            crc.update(block)
    return crc.hexdigest().decode()


def _files(root: Path) -> list[Path]:
    """Every regular file of the output, except the manifest and publishing's own bookkeeping."""
    skip = {NAME, ".job.json"}
    return sorted(p for p in root.rglob("*") if p.is_file() and p.name not in skip
                  and not any(part in (".done", ".work") for part in p.relative_to(root).parts))


def write_manifest(root: Path) -> dict[str, Any]:
    """List every file under ``root`` with its size and CRC32C in ``root/manifest.json``."""
    files = {p.relative_to(root).as_posix(): {"bytes": p.stat().st_size, "crc32c": _crc(p)} for p in _files(root)}
    manifest = {"format": FORMAT, "files": files}
    tmp = root / f".{NAME}.tmp"
    tmp.write_text(json.dumps(manifest, indent=0, sort_keys=True))
    tmp.replace(root / NAME)
    return manifest


def read_manifest(root: Path) -> dict[str, Any] | None:
    """The manifest of ``root`` (None for an output written before manifests existed)."""
    path = Path(root) / NAME
    if not path.is_file():
        return None
    try:
        manifest = json.loads(path.read_text())
        files = manifest["files"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path}: unreadable manifest ({exc}); the output is damaged, rebuild it") from None
    if not isinstance(files, dict):
        raise InputError(f"{path}: unreadable manifest (no file list); the output is damaged, rebuild it")
    return manifest


CHEAP_BYTES = 1 << 30  # checksummed on every open: reading this much costs well under a second from the page cache


def check_manifest(root: Path, full: bool = False, only: str | None = None, budget: int = CHEAP_BYTES) -> int:
    """Check the files ``root``'s manifest lists (those under ``only``, if given): present with their
    size, and their checksum, smallest files first while their bytes stay within ``budget`` (all
    of them with ``full``). Returns the number checked; an error names the first bad file."""
    root = Path(root)
    manifest = read_manifest(root)
    if manifest is None:
        return 0
    checked, summed = 0, 0
    for rel, entry in sorted(manifest["files"].items(), key=lambda item: (item[1]["bytes"], item[0])):
        if only is not None and not rel.startswith(only):
            continue
        path = root / rel
        try:
            size = path.stat().st_size
        except FileNotFoundError:
            raise InputError(f"{path}: missing from a complete output (its manifest lists it); "
                             "the output is damaged, rebuild it") from None
        if size != entry["bytes"]:
            raise InputError(f"{path}: {size:,} bytes, its manifest says {entry['bytes']:,}; "
                             "the output is damaged, rebuild it")
        summed += size
        if (full or summed <= budget) and _crc(path) != entry["crc32c"]:
            raise InputError(f"{path}: its content changed since it was published (checksum differs); "
                             "the output is damaged, rebuild it")
        checked += 1
    return checked


def listed(root: Path, prefix: str) -> set[str] | None:
    """Names under ``prefix`` the manifest lists (None without a manifest)."""
    manifest = read_manifest(root)
    if manifest is None:
        return None
    return {rel[len(prefix):] for rel in manifest["files"] if rel.startswith(prefix)}
