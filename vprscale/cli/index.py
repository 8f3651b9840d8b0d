"""``vprscale index``: fits CoarseHash on a store and writes its index (or converts an older index in place)."""

from __future__ import annotations

import argparse
from pathlib import Path

from vprscale.cli.common import positive_int, write_summary
from vprscale.core.errors import InputError

INPUTS = ('store', 'upgrade')  # the flags naming what it reads: no output may be written over them


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("index", parents=[cluster, summary],
                       help="fit CoarseHash on a dataset store and write its inverted lists")
    p.add_argument("store", nargs="?", help="a complete <scale>.zarr dataset store")
    p.add_argument("--upgrade", metavar="INDEX",
                   help="convert an index of an older format (2) in place, without refitting")
    p.add_argument("--d", type=positive_int, default=None, help="hash digits (default ⌈log2 N_ref⌉)")
    p.add_argument("--k", type=int, default=2, help="levels per component (default 2)")
    p.add_argument("--force", action="store_true",
                   help="re-index even if the index holds evaluations (they are kept in <index>.previous-eval/)")
    p.add_argument("--out", help="index directory (default: beside the store, <scale>-d<d>-k<K>.index)")
    p.set_defaults(func=run, input_flags=INPUTS)


def run(args: argparse.Namespace) -> int:
    from vprscale.evaluation.storage import format_parts, format_storage, index_parts
    from vprscale.jobs.indexing import build_index, upgrade_index

    if args.upgrade:
        if args.store:
            raise InputError(f"--upgrade {args.upgrade}: converts an index; give no store ({args.store})")
        meta = upgrade_index(args.upgrade)
        print(f"{args.upgrade}: format {meta['format']}" + (f" (converted from format {meta['upgraded_from']}, "
                                                             "no refit)" if meta.get("converted") else " already"))
        print(format_parts(index_parts(Path(args.upgrade)), meta["n_ref"], meta["d"], meta["k"]))
        write_summary(args, meta)
        return 0
    if not args.store:
        raise InputError("index: give a dataset store (or --upgrade INDEX)")
    meta = build_index(args.store, d=args.d, k=args.k, out=args.out, scheduler=args.scheduler,
                       workers=args.workers, force=args.force)
    print(f"indexed {meta['n_ref']:,} refs of {args.store} → {meta['index']}")
    print(f"  d = {meta['d']}, K = {meta['k']}, {meta['occupied']:,} occupied addresses "
          f"({meta['occupied'] / meta['k'] ** meta['d']:.4%} of K^d)")
    for name, secs in meta["timings_s"].items():
        print(f"  {secs:8.1f} s  {name}")
    print(f"  peak memory {meta['peak_rss_bytes'] / 2**30:.2f} GiB")
    print(format_storage(meta["storage"]))
    print(format_parts(meta["parts_published"], meta["n_ref"], meta["d"], meta["k"]))
    write_summary(args, meta)
    return 0
