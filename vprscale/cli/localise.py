"""``vprscale localise``: matches a traverse frame by frame (online)."""

from __future__ import annotations

import argparse

from vprscale.cli.common import bounded_int, local_output, positive_int, write_summary
from vprscale.protocol import MAX_BEST

INPUTS = ('index', 'queries', 'store')  # the flags naming what it reads: no output may be written over them


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("localise", parents=[summary],
                       help="match a traverse frame by frame (online) and write one row per frame")
    p.add_argument("index", help="an index directory")
    p.add_argument("queries", help="query frames in order: STORE.zarr/<array>, or any descriptor form build --ref "
                                   "reads (.npy, .fbin, .u8bin, fvecs, FILE.hdf5:DATASET, FILE.parquet:COLUMN, …)")
    p.add_argument("--L", type=positive_int, default=100, help="sequence length (default 100)")
    p.add_argument("--mode", choices=["paper", "aligned"], default="paper", help="candidate mode (default paper)")
    p.add_argument("--top", type=bounded_int(MAX_BEST, "a window's best-first list"), default=None, metavar="N",
                   help="also write each window's N best candidates, best first, as columns top_1 … top_N (the "
                        "batch's ranking)")
    p.add_argument("--out", help="a .parquet or .csv file of (frame, centre, match, n_r, score), one row per "
                                 "frame (default: CSV on standard output)")
    p.add_argument("--force", action="store_true", help="replace an existing --out file (kept beside, as .previous)")
    p.add_argument("--store", metavar="STORE",
                   help="the index's store, for a map of many sequences (build --ref-seq, --msls): no window that "
                        "crosses a sequence's end or a gap is answered")
    p.set_defaults(func=run, input_flags=INPUTS)


def run(args: argparse.Namespace) -> int:
    from vprscale.jobs.localise import localise

    summary = localise(local_output(args.index), args.queries, args.L, mode=args.mode, out=args.out or "-",
                       top=args.top, force=args.force, store=local_output(args.store) if args.store else None)
    write_summary(args, summary)
    return 0
