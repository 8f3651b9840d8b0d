"""Folders only this user can write: where a process may keep what it later trusts.

vprscale keeps two caches it reads back without checking every byte: numba's compiled kernels
(whose index files numba unpickles, so whoever can write them runs code in the next process)
and the query engine's decoded arrays (which a kernel indexes without bounds checks). Both live
under folders a user names (``$NUMBA_CACHE_DIR``, ``$VPRSCALE_CACHE``), which may be shared,
world-writable or links to somewhere else. :func:`private_folder` makes such a folder, or
accepts it as it is, only when it is a real directory (not a symbolic link), owned by this
user, writable by nobody else, in a parent that nobody else can rename it out of; anything
else is refused, and the caller works without the cache.
"""

from __future__ import annotations

import logging
import os
import stat
from pathlib import Path

log = logging.getLogger(__name__)


def _safe(info: os.stat_result) -> bool:
    """A directory of this user's, not a link, that neither its group nor others can write."""
    return (stat.S_ISDIR(info.st_mode) and info.st_uid == os.geteuid()
            and not info.st_mode & (stat.S_IWGRP | stat.S_IWOTH))


def _safe_parent(info: os.stat_result) -> bool:
    """A parent from which a stranger cannot remove or rename an entry of ours: one with the sticky
    bit (``/tmp``), or one not everybody can write that is this user's or root's (a group-writable
    folder of this user's is the usual ``~/.cache`` under a umask of 002: its group is the user's own)."""
    if not stat.S_ISDIR(info.st_mode):
        return False
    if info.st_mode & stat.S_ISVTX:
        return True
    return not info.st_mode & stat.S_IWOTH and (info.st_uid in (os.geteuid(), 0) or not info.st_mode & stat.S_IWGRP)


def private_folder(path: Path, what: str) -> Path | None:
    """``path`` as a folder only this user can write, made (mode 0700) if it is absent; None, with
    one warning naming it and why, if it exists and is not (a link, another user's, writable by
    others) or cannot be made. ``what`` says in the warning what goes without it."""
    path = Path(os.path.abspath(path))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if not _safe_parent(os.stat(path.parent)):
            return _refused(path, what, f"its parent {path.parent} can be written by other users")
        try:
            path.mkdir(mode=0o700)
        except FileExistsError:
            pass
        info = os.lstat(path)
    except OSError as exc:
        return _refused(path, what, exc.strerror or type(exc).__name__)
    if stat.S_ISLNK(info.st_mode):
        return _refused(path, what, "it is a symbolic link")
    if not _safe(info):
        owner = ("another user's" if info.st_uid != os.geteuid()
                 else f"writable by other users; `chmod go-w {path}` makes it yours alone")
        return _refused(path, what, owner if stat.S_ISDIR(info.st_mode) else "not a directory")
    return path


def _refused(path: Path, what: str, why: str) -> None:
    log.warning("%s is not used (%s): %s", path, why, what)
    return None


def entries(folder: Path) -> list[Path]:
    """The folders directly in ``folder`` that are real directories (links and files left out),
    for a prune that must never follow a link out of the folder."""
    found = []
    try:
        with os.scandir(folder) as it:
            for entry in it:
                if entry.is_dir(follow_symlinks=False):
                    found.append(Path(entry.path))
    except OSError:
        pass
    return found


def owned(path: Path) -> bool:
    """Whether the file ``path`` is this user's, writable by nobody else, in a folder of this
    user's that not everybody can write: what a process may unpickle (a checkpoint it wrote with
    mode 0600), since whoever could write it could have planted code in it."""
    try:
        file, folder = os.lstat(path), os.stat(Path(path).parent)
    except OSError:
        return False
    return (stat.S_ISREG(file.st_mode) and file.st_uid == os.geteuid()
            and not file.st_mode & (stat.S_IWGRP | stat.S_IWOTH)
            and folder.st_uid == os.geteuid() and not folder.st_mode & stat.S_IWOTH)
