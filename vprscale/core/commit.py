"""The commit vprscale's code comes from, however it was installed.

A checkout (an editable install, or running from a clone) asks git. A wheel or an sdist has no
git beside it, so the build writes the commit into the package as ``_build.json`` (``setup.py``
calls :func:`record` while it builds), and an installed vprscale reads it back. Standard library
only: ``setup.py`` loads this file by path, before any of vprscale's dependencies exist.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

BUILD_FILE = "_build.json"  # inside the vprscale package of a wheel or an sdist
CODE_PATHS = ("vprscale", "pyproject.toml", "setup.py", "datasets", "pipelines")  # what a dirty tree means


def from_git(root: Path) -> dict[str, Any] | None:
    """``{"commit", "dirty"}`` of the git checkout at ``root`` (dirty: the code in it differs from
    the commit), or None where ``root`` is not one or git cannot say."""
    if not (root / ".git").exists():
        return None
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
        status = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no", "--",
                                 *CODE_PATHS], capture_output=True, text=True, timeout=10, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    return {"commit": head, "dirty": bool(status.strip())}


def from_build(package: Path) -> dict[str, Any] | None:
    """What the build recorded in the installed package ``package``, or None."""
    try:
        recorded = json.loads((package / BUILD_FILE).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(recorded, dict) or not isinstance(recorded.get("commit"), str):
        return None
    return {"commit": recorded["commit"], "dirty": bool(recorded.get("dirty"))}


def record(root: Path, package: Path) -> None:
    """Write the checkout's commit into ``package`` (a copy of the package being built) where
    ``root`` is a checkout; elsewhere (a build from an sdist) keep the file the sdist carries."""
    state = from_git(root)
    if state is not None:
        package.mkdir(parents=True, exist_ok=True)
        (package / BUILD_FILE).write_text(json.dumps(state, sort_keys=True) + "\n")
