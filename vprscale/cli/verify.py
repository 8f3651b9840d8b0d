"""``vprscale verify``: checks a store, index, evaluation or encoding against its manifest, and
an index's evaluation (``INDEX/eval``) with it."""

from __future__ import annotations

import argparse
from pathlib import Path

from vprscale.core.errors import InputError
from vprscale.core.objects import Remote, location

KINDS = {"zarr.json": "dataset store", "index.json": "index", "eval.json": "evaluation", "encoding.json": "encoding"}


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("verify", help="check a store, index, evaluation or encoding against its manifest (sizes and "
                                      "checksums); an index's evaluation is checked with it")
    p.add_argument("path", help="a dataset store, an index, an evaluation folder or an encoding "
                                "(<store>.faiss/<method>)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    path = location(args.path)
    kind = next((k for f, k in KINDS.items() if (path / f).is_file()), None)
    if kind is None:
        raise InputError(f"{path}: not a vprscale store, index, evaluation or encoding")
    found = [(path, kind)]
    if kind == "index":
        from vprscale.evaluation.results import PUBLISHED

        if any((path / "eval" / f).exists() for f in PUBLISHED):
            found.append((path / "eval", "evaluation"))  # its evaluation, published apart: checked whole
    for root, what in found:
        n = _verify(root, what)
        print(f"{root}: {what} verified, {n:,} files with their sizes and checksums")
    return 0


def _verify(root: Path | Remote, kind: str) -> int:
    """Every checksum of one output, through the reader of its kind where that is light (an index's
    metadata, an evaluation's folder), which refuses one published without its manifest; a store
    or encoding by its recorded provenance and version. Returns the files checked."""
    from vprscale.core.manifest import check_manifest, made_since_manifests, read_manifest, read_record, remake

    if isinstance(root, Remote):  # on object storage an output is its manifest's: no older forms to allow
        check_manifest(root, full=True)
    elif kind == "index":
        from vprscale.method.indexmeta import load_index_meta

        load_index_meta(root, upgradable=True, full=True)
    elif kind == "evaluation":
        from vprscale.evaluation.results import eval_folder

        eval_folder(root, full=True)
    else:
        usual = f"re-run the vprscale command that made this {kind}, with --force"
        if kind == "dataset store":  # its provenance is in build.json; zarr.json records the version that built it
            attrs = read_record(root / "zarr.json").get("attributes", {}).get("vprscale", {})
            how = remake(read_record(root / "build.json"), usual,
                         made_since_manifests(attrs.get("versions", {}).get("vprscale", "0.3")))
        else:  # every encoding of the format read today had a manifest from birth
            how = remake(read_record(root / "encoding.json"), usual, published=True)
        check_manifest(root, full=True, remake=how)
    manifest = read_manifest(root)
    if manifest is None:
        raise InputError(f"{root}: this {kind} has no manifest (written before vprscale 0.3); rebuild it to verify")
    return len(manifest["files"])
