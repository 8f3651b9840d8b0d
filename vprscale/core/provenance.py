"""What produced an output: the code (commit, dirty tree, version), the command, the machine
and the time. Every output of vprscale carries it (docs/accounting.md, "Provenance").

It lives in metadata beside the bytes that define a result (a store's ``build.json``, an
index's ``index.json``, an evaluation's ``eval.json`` and Parquet key-value metadata), so
the same seed still gives the same data bytes on any machine.
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import subprocess
import sys
from datetime import UTC, datetime
from functools import cache
from pathlib import Path
from typing import Any

import vprscale

PARQUET_KEY = b"vprscale.provenance"
_command: list[str] = []


def set_command(argv: list[str]) -> None:
    """The command line this process runs (the CLI says it once, at its start)."""
    _command[:] = argv


@cache
def code_state() -> dict[str, Any]:
    """The vprscale version, and the git commit of its checkout with whether the tree was dirty
    (None where vprscale is installed without one)."""
    root = Path(vprscale.__file__).resolve().parents[1]
    state: dict[str, Any] = {"vprscale": vprscale.__version__, "commit": None, "dirty": None}
    if not (root / ".git").exists():
        return state
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
        status = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no", "--",
                                 "vprscale", "pyproject.toml", "datasets", "pipelines"],
                                capture_output=True, text=True, timeout=10, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return state
    return {**state, "commit": head, "dirty": bool(status.strip())}


@cache
def cpu_model() -> str:
    """The processor's model name (``/proc/cpuinfo``; the platform's word elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def provenance(command: str | None = None, **extra: Any) -> dict[str, Any]:
    """The provenance record of an output made now, by ``command`` (default: this process's command line)."""
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    if command is None:
        command = shlex.join(_command or sys.argv)  # outside the CLI: the process's own command line
    return {**code_state(), "command": command,
            "cpu": cpu_model(), "cores": os.cpu_count(), "load_average": [round(x, 2) for x in load],
            "host": platform.node(), "python": sys.version.split()[0],
            "time": datetime.now(UTC).isoformat(timespec="seconds"), **extra}


def parquet_metadata(record: dict[str, Any]) -> dict[bytes, bytes]:
    """The record as Parquet key-value metadata."""
    return {PARQUET_KEY: json.dumps(record, sort_keys=True, default=str).encode()}
