"""``vprscale verify``: checks a store, index or evaluation against its manifest."""

from __future__ import annotations

import argparse
from pathlib import Path

from vprscale.core.errors import InputError


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("verify", help="check a store, index or evaluation against its manifest (sizes and checksums)")
    p.add_argument("path", help="a dataset store, an index or an evaluation folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vprscale.core.manifest import check_manifest, read_manifest

    path = Path(args.path)
    kinds = {"zarr.json": "dataset store", "index.json": "index", "eval.json": "evaluation"}
    kind = next((k for f, k in kinds.items() if (path / f).is_file()), None)
    if kind is None:
        raise InputError(f"{path}: not a vprscale store, index or evaluation")
    if read_manifest(path) is None:
        raise InputError(f"{path}: this {kind} has no manifest (written before vprscale 0.3); rebuild it to verify")
    n = check_manifest(path, full=True)
    print(f"{path}: {kind} verified, {n:,} files with their sizes and checksums")
    return 0
