"""``vprscale encode``: encodes a store's references with FAISS methods, beside it, for ``eval --compare``."""

from __future__ import annotations

import argparse

from vprscale.cli.common import write_summary


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("encode", parents=[cluster, summary],
                       help="encode a store's references with FAISS methods, beside it, for eval --compare "
                            "(resumable; needed at 100M and 1B)")
    p.add_argument("store", help="a complete <scale>.zarr dataset store (full or compact)")
    p.add_argument("--compare", action="append", metavar="FACTORY", required=True,
                   help="a FAISS index_factory string (repeat for several)")
    p.add_argument("--deep1b", metavar="PATH", help="a compact store built from files: its Deep1B file")
    p.add_argument("--fas", metavar="PATH", help="a compact store built from files: its FAS file")
    p.add_argument("--force", action="store_true", help="encode again (the old encoding replaced once done)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vprscale.core.throughput import throughput
    from vprscale.jobs.encoding import encode_store

    summary = encode_store(args.store, args.compare or [], deep1b=args.deep1b, fas=args.fas,
                           workers=args.workers, scheduler=args.scheduler, force=args.force)
    for factory, m in summary["methods"].items():
        done = "up to date, kept" if m.get("skipped") else f"{m['wall_s']:,.1f} s, {m['code_bytes']} B a code"
        print(f"faiss:{factory}: {summary['n_ref']:,} references → {m['out']} ({done})")
    if not all(m.get("skipped") for m in summary["methods"].values()):
        print("  encoded " + throughput(summary["n_ref"], summary["n_ref"] * summary["dim"] * 4, summary["wall_s"],
                                        args.workers))
    print(f"  peak memory {summary['peak_rss_bytes'] / 2**30:.2f} GiB")
    write_summary(args, summary)
    return 0
