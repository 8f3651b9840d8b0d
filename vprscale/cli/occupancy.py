"""``vprscale occupancy``: bucket sizes and occupancy of an index."""

from __future__ import annotations

import argparse
import json

from vprscale.cli.common import local_output, positive_int


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("occupancy", help="bucket sizes, occupied share of K^d and per-component balance")
    p.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    p.add_argument("index", help="an index directory")
    p.add_argument("--top", type=positive_int, default=10, help="how many of the largest buckets to list")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vprscale.evaluation.occupancy import format_occupancy, occupancy

    occ = occupancy(local_output(args.index), top=args.top)
    print(json.dumps(occ) if args.json else format_occupancy(occ))
    return 0
