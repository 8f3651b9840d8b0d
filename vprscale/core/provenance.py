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
import sys
from datetime import UTC, datetime
from functools import cache
from pathlib import Path
from typing import Any

import vprscale
from vprscale.core import commit
from vprscale.core.objects import redact

PARQUET_KEY = b"vprscale.provenance"
_command: list[str] = []


def set_command(argv: list[str]) -> None:
    """The command line this process runs (the CLI says it once, at its start)."""
    _command[:] = redact(argv)  # a URL's password or signature is never recorded


@cache
def code_state() -> dict[str, Any]:
    """The vprscale version and the commit its code comes from, with whether the tree was dirty:
    git's answer in a checkout, the build's record in a wheel or sdist install (None where neither
    says: a copy of the sources without git)."""
    package = Path(vprscale.__file__).resolve().parent
    found = commit.from_git(package.parent) or commit.from_build(package) or {"commit": None, "dirty": None}
    return {"vprscale": vprscale.__version__, **found}


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
        command = shlex.join(_command or redact(sys.argv))  # outside the CLI: the process's own command line
    return {**code_state(), "command": command,
            "cpu": cpu_model(), "cores": os.cpu_count(), "load_average": [round(x, 2) for x in load],
            "host": platform.node(), "python": sys.version.split()[0],
            "time": datetime.now(UTC).isoformat(timespec="seconds"), **extra}


def parquet_metadata(record: dict[str, Any]) -> dict[bytes, bytes]:
    """The record as Parquet key-value metadata."""
    return {PARQUET_KEY: json.dumps(record, sort_keys=True, default=str).encode()}
