"""The manifest of a published output: every file it holds, with its size and a CRC32C.

A store, an index or an evaluation is published with ``manifest.json`` beside its files
(:class:`~vprscale.core.publish.PartialOutput` writes it as the last step before sealing).
Opening an output checks that every listed file is there with its size (a ``stat`` per
file) and the checksums of its smallest files up to ``CHEAP_BYTES`` (the whole output below
that size: a 20K store or index, a 1B index's model and directory arrays), so a deleted,
truncated, permuted or overwritten file is an error naming it, never zeros or a wrong answer;
``vprscale verify`` checks every checksum (CRC32C runs at several GB/s, so a full check costs
about one read of the output). Outputs written before manifests existed have
none and are opened as before; one whose own metadata says it was written since (a reader
passes ``remake``) is refused without its manifest, which would otherwise turn every check
off. A listed file or folder that is a symbolic link is refused: nothing is read from outside
a published output through it. An output on object storage (a :class:`~vprscale.core.objects.Remote`
root) is listed once instead of a ``stat`` per file, and is never opened without its manifest:
written last, it is what makes such an output complete.
"""

from __future__ import annotations

import json
import re
import stat
from pathlib import Path
from typing import Any

import google_crc32c

from vprscale.core.errors import InputError
from vprscale.core.objects import BOOKKEEPING, Remote

Root = Path | Remote  # a local output directory, or an output's prefix on object storage

NAME = "manifest.json"
FORMAT = 1
READ_BYTES = 1 << 24


def crc32c_of(path: Path | Remote) -> str:
    """The CRC32C of a file's bytes, read in blocks (as manifests record it)."""
    crc = google_crc32c.Checksum()
    with path.open("rb") if isinstance(path, Remote) else open(path, "rb") as fh:
        while block := fh.read(READ_BYTES):
            crc.update(block)
    return crc.hexdigest().decode()


def _files(root: Path) -> list[Path]:
    """Every regular file of the output, except the manifest and publishing's own bookkeeping."""
    skip = {NAME, ".job.json"}
    return sorted(p for p in root.rglob("*") if p.is_file() and p.name not in skip
                  and not any(part in (".done", ".work") for part in p.relative_to(root).parts))


def _remote_files(root: Remote) -> dict[str, int]:
    """Every object of an output on object storage but the manifest and the job's bookkeeping, with its size."""
    return {rel: size for rel, size in root.files().items()
            if rel != NAME and not any(rel == b or rel.startswith(b) for b in BOOKKEEPING)}


def write_manifest(root: Root) -> dict[str, Any]:
    """List every file under ``root`` with its size and CRC32C in ``root/manifest.json``."""
    if isinstance(root, Remote):
        files = {rel: {"bytes": size, "crc32c": crc32c_of(root / rel)}
                 for rel, size in sorted(_remote_files(root).items())}
        manifest = {"format": FORMAT, "files": files}
        (root / NAME).write_text(json.dumps(manifest, indent=0, sort_keys=True))
        return manifest
    files = {p.relative_to(root).as_posix(): {"bytes": p.stat().st_size, "crc32c": crc32c_of(p)} for p in _files(root)}
    manifest = {"format": FORMAT, "files": files}
    tmp = root / f".{NAME}.tmp"
    tmp.write_text(json.dumps(manifest, indent=0, sort_keys=True))
    tmp.replace(root / NAME)
    return manifest


def read_manifest(root: Root) -> dict[str, Any] | None:
    """The manifest of ``root`` (None for an output written before manifests existed)."""
    path = root / NAME if isinstance(root, Remote) else Path(root) / NAME
    if not path.is_file():
        return None
    try:
        manifest = json.loads(path.read_text())
        files = manifest["files"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path}: unreadable manifest ({exc}); the output is damaged, rebuild it") from None
    if not isinstance(files, dict):
        raise InputError(f"{path}: unreadable manifest (no file list); the output is damaged, rebuild it")
    for rel, entry in files.items():
        if rel.startswith("/") or ".." in rel.split("/") or not isinstance(entry, dict) or not {
                "bytes", "crc32c"} <= entry.keys():
            raise InputError(f"{path}: lists {rel!r}, not a file of the output; the output is damaged, rebuild it")
    return manifest


def remake(record: Any, usual: str, published: bool = False) -> str | None:
    """How to re-create an output whose metadata ``record`` (``build.json``, ``index.json``,
    ``eval.json``, ``encoding.json``) carries a provenance record, or that its format says was
    ``published`` with a manifest: every vprscale that writes either publishes a manifest too, so
    such an output without its manifest is refused, saying this: the command line its provenance
    records (a command's), else ``usual``. None for an output older than both (opened as before)."""
    provenance = record.get("provenance") if isinstance(record, dict) else None
    if not isinstance(provenance, dict) and not published:
        return None
    command = provenance.get("command") if isinstance(provenance, dict) else None
    return f"{command} --force" if isinstance(command, str) and command.startswith("vprscale ") else usual


def read_record(path: Path | Remote) -> dict[str, Any]:
    """An output's metadata file (``build.json``, ``index.json``, ``zarr.json`` …) as a dict: {}
    where it is missing or not a JSON object (the manifest check then says what is wrong)."""
    try:
        record = json.loads(path.read_text() if isinstance(path, Remote) else Path(path).read_text())
    except (OSError, ValueError, InputError):
        return {}
    return record if isinstance(record, dict) else {}


def made_since_manifests(version: Any) -> bool:
    """Whether a vprscale version (as recorded in an output) publishes manifests (0.3 and later)."""
    numbers = [int(x) for x in re.findall(r"\d+", str(version))[:2]]
    return len(numbers) == 2 and tuple(numbers) >= (0, 3)


CHEAP_BYTES = 1 << 30  # checksummed on every open: reading this much costs well under a second from the page cache


def check_manifest(root: Root, full: bool = False, only: str | None = None, budget: int = CHEAP_BYTES,
                   remake: str | None = None) -> int:
    """Check the files ``root``'s manifest lists (those under ``only``, if given): present with their
    size, none a symbolic link or inside one, and their checksum, smallest files first while their
    bytes stay within ``budget`` (all of them with ``full``). Returns the number checked; an error
    names the first bad file. ``remake`` (the command that re-creates the output) says the output
    was published with a manifest, so its absence is an error rather than an older output."""
    if isinstance(root, Remote):
        return _check_remote(root, full, only, budget)
    root = Path(root)
    manifest = read_manifest(root)
    if manifest is None:
        if remake is not None:
            raise InputError(f"{root}: no {NAME}, though it was written by a vprscale that publishes one (deleted?): "
                             f"its files cannot be checked; re-create it: {remake}")
        return 0
    checked, summed, folders = 0, 0, set()
    for rel, entry in sorted(manifest["files"].items(), key=lambda item: (item[1]["bytes"], item[0])):
        if only is not None and not rel.startswith(only):
            continue
        path = root / rel
        _no_link_within(root, path.parent, folders)
        try:
            info = path.lstat()
        except FileNotFoundError:
            raise InputError(f"{path}: missing from a complete output (its manifest lists it); "
                             "the output is damaged, rebuild it") from None
        if stat.S_ISLNK(info.st_mode):
            raise InputError(f"{path}: a symbolic link where its manifest lists a file; vprscale reads nothing "
                             "from outside a published output: the output is damaged, rebuild it")
        if info.st_size != entry["bytes"]:
            raise InputError(f"{path}: {info.st_size:,} bytes, its manifest says {entry['bytes']:,}; "
                             "the output is damaged, rebuild it")
        summed += info.st_size
        if (full or summed <= budget) and crc32c_of(path) != entry["crc32c"]:
            raise InputError(f"{path}: its content changed since it was published (checksum differs); "
                             "the output is damaged, rebuild it")
        checked += 1
    return checked


def remote_manifest(root: Remote) -> dict[str, Any]:
    """The manifest of an output on object storage; none, no output (written last: without it the
    output was never completed)."""
    manifest = read_manifest(root)
    if manifest is None:
        raise InputError(f"{root}: no {NAME}: on object storage an output is complete only once its manifest is "
                         "written (its job did not finish, or this is not a vprscale output)")
    return manifest


def _check_remote(root: Remote, full: bool, only: str | None, budget: int) -> int:
    """:func:`check_manifest` of an output on object storage: sizes from one listing."""
    manifest = remote_manifest(root)
    sizes = root.files()
    checked, summed = 0, 0
    for rel, entry in sorted(manifest["files"].items(), key=lambda item: (item[1]["bytes"], item[0])):
        if only is not None and not rel.startswith(only):
            continue
        if rel not in sizes:
            raise InputError(f"{root / rel}: missing from a complete output (its manifest lists it); "
                             "the output is damaged, rebuild it")
        if sizes[rel] != entry["bytes"]:
            raise InputError(f"{root / rel}: {sizes[rel]:,} bytes, its manifest says {entry['bytes']:,}; "
                             "the output is damaged, rebuild it")
        summed += sizes[rel]
        if (full or summed <= budget) and crc32c_of(root / rel) != entry["crc32c"]:
            raise InputError(f"{root / rel}: its content changed since it was published (checksum differs); "
                             "the output is damaged, rebuild it")
        checked += 1
    return checked


def _no_link_within(root: Path, folder: Path, seen: set[Path]) -> None:
    """Refuse a symbolic link among the folders from ``root`` (exclusive) down to ``folder``; each
    folder is looked at once per check (a store lists tens of thousands of chunks in a few folders)."""
    while folder != root and folder not in seen:
        if folder.is_symlink():
            raise InputError(f"{folder}: a symbolic link inside a published output; vprscale reads nothing from "
                             "outside an output through one: the output is damaged, rebuild it")
        seen.add(folder)
        folder = folder.parent


def listed(root: Root, prefix: str) -> set[str] | None:
    """Names under ``prefix`` the manifest lists (None without a manifest)."""
    manifest = read_manifest(root)
    if manifest is None:
        return None
    return {rel[len(prefix):] for rel in manifest["files"] if rel.startswith(prefix)}
