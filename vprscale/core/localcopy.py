"""Outputs that must be local to be used (an index is memory-mapped), kept on object storage.

An index named by URL is fetched once into the cache (``$VPRSCALE_CACHE/outputs/…``) and
checked, every object's size and CRC32C, against the manifest it was published with; later
runs use the copy for as long as the remote manifest is unchanged, so a re-published index is
fetched again, never read stale. An index written to a URL is made in that same cache folder
(its files are memory-mapped while they are written), then uploaded, its manifest last: the
output is complete on the storage only once everything it lists is there.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from pathlib import Path

from vprscale.core.manifest import NAME, check_manifest, read_manifest, remote_manifest
from vprscale.core.objects import Remote, cache_root, storage_errors
from vprscale.core.publish import clear_remote_output, keep_remote_beside

log = logging.getLogger(__name__)


def cache_folder(remote: Remote, fresh: bool = False) -> Path:
    """The local folder that holds ``remote``'s copy (named by its URL's digest, then its name);
    ``fresh``: emptied first, for an output about to be made there (an earlier copy is not it)."""
    folder = cache_root() / "outputs" / hashlib.sha256(remote.url.encode()).hexdigest()[:16] / remote.name
    if fresh:
        shutil.rmtree(folder, ignore_errors=True)
    return folder


def local_copy(remote: Remote) -> Path:
    """A verified local copy of a published output on object storage (fetched if missing or stale)."""
    manifest = remote_manifest(remote)
    target = cache_folder(remote)
    if read_manifest(target) == manifest:
        check_manifest(target)
        return target
    partial = target.with_name(f".{target.name}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    log.info(f"fetching {remote} ({sum(e['bytes'] for e in manifest['files'].values()) / 2**20:,.1f} MiB) "
             f"into the cache, {target}")
    with storage_errors(remote.url):
        for rel in manifest["files"]:
            (partial / rel).parent.mkdir(parents=True, exist_ok=True)
            remote.fs.get_file(f"{remote.path}/{rel}", str(partial / rel))
    (partial / NAME).write_text(json.dumps(manifest, indent=0, sort_keys=True))
    check_manifest(partial, full=True)  # every byte as published, or an error naming the file
    if target.exists():
        shutil.rmtree(target)
    partial.replace(target)
    return target


def upload(local: Path, remote: Remote, keep: bool = False) -> None:
    """Publish a complete local output to ``remote``: every file its manifest lists, then the
    manifest. An older output there is removed first (a reader finds none, not a mix), or with
    ``keep`` a complete one is moved beside (``<name>.previous``), as ``--force`` keeps it locally."""
    manifest = read_manifest(local)
    if manifest is None:
        raise RuntimeError(f"{local}: uploaded before it was published")  # a bug: callers publish first
    if keep and read_manifest(remote) is not None:
        keep_remote_beside(remote)
    clear_remote_output(remote)
    with storage_errors(remote.url):
        for rel in manifest["files"]:
            remote.fs.put_file(str(local / rel), f"{remote.path}/{rel}")
    (remote / NAME).write_text((local / NAME).read_text())
