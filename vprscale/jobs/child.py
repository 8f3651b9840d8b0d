"""A child ``vprscale`` process: what pipeline stages and benchmarks spawn."""

from __future__ import annotations

import sys
from pathlib import Path

import vprscale


def vprscale_argv(*args: str) -> list[str]:
    """The command line of a child ``vprscale ARGS`` that imports this very vprscale: ``-P`` keeps
    the current directory off its import path (a ``vprscale/`` folder there — the parent of a
    clone, an untrusted directory — would be imported first), and the folder this vprscale was
    imported from goes first instead (a checkout run without installing it still works)."""
    root = str(Path(vprscale.__file__).resolve().parents[1])
    boot = f"import sys; sys.path.insert(0, {root!r}); from vprscale.cli import main; sys.exit(main())"
    return [sys.executable, "-P", "-c", boot, *args]
