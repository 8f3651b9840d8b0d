"""Content digests of input files, each computed once and kept while the file is untouched.

A pipeline decides whether a stage is up to date from what it reads. Sizes and modification
times miss a file rewritten in place with both kept (``os.utime`` sets any mtime), and the
sampled head-and-tail hash of a source's fingerprint misses a change in the middle, so an input
file's SHA-256 is part of the decision. Hashing a source of hundreds of GB on every run would
cost minutes, so a digest is cached under the file's identity: path, device, inode, size,
modification time and *change* time. The change time is the kernel's (any write, ``utime``,
rename or ``chmod`` moves it, and no call sets it back), so a cached digest is never served for
changed bytes.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)

FORMAT = 1
LOUD_BYTES = 1 << 30  # a file this large is announced before hashing (it takes a second or more)


def _identity(path: Path) -> list[int]:
    st = path.stat()
    return [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns]


class DigestCache:
    """SHA-256 digests of files, kept in one JSON file (``path``) across runs."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        try:
            saved = json.loads(self.path.read_text())
            self.known = saved["files"] if saved.get("format") == FORMAT else {}
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            self.known = {}  # none yet, or unreadable: every digest is computed again, which is safe
        self.changed = False

    def digest(self, file: str | os.PathLike) -> str:
        """The SHA-256 of ``file``'s bytes, read again only where its identity changed."""
        p = Path(file).resolve()
        ident = _identity(p)
        entry = self.known.get(str(p))
        if isinstance(entry, dict) and entry.get("identity") == ident:
            return entry["sha256"]
        if ident[2] >= LOUD_BYTES:
            log.info(f"… hashing {p} ({ident[2] / 2**30:.1f} GiB), once: its digest is kept while it is untouched")
        with open(p, "rb") as fh:
            sha = hashlib.file_digest(fh, "sha256").hexdigest()
        if _identity(p) != ident:  # written while it was read: its digest describes no state of the file
            return f"changing:{sha}"
        self.known[str(p)] = {"identity": ident, "sha256": sha}
        self.changed = True
        return sha

    def save(self) -> None:
        """Write the cache (atomically) if a digest was computed."""
        if not self.changed:
            return
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(json.dumps({"format": FORMAT, "files": self.known}, indent=0, sort_keys=True))
            tmp.replace(self.path)
        except OSError:  # a cache: where it cannot be written (a read-only folder), digests are computed again
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
            return
        self.changed = False
