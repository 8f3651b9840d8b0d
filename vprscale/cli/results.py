"""``vprscale results``: shows any number of evaluations as one table."""

from __future__ import annotations

import argparse

from vprscale.cli.common import positive_float


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("results", help="any number of evaluations as one table (filter with --where SQL)")
    p.add_argument("paths", nargs="+", help="evaluation folders (INDEX/eval, eval --out) or indexes")
    p.add_argument("--where", help="an SQL condition on the columns, e.g. \"method = 'coarsehash' AND radius = 20\"")
    p.add_argument("--queries", action="store_true", help="the per-query rows instead of the recall table")
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--csv", dest="format", action="store_const", const="csv", default="table")
    fmt.add_argument("--json", dest="format", action="store_const", const="json")
    p.add_argument("--timeout", type=positive_float, default=30.0, help="seconds the --where query may run")
    p.add_argument("--memory-limit", default="2GB", help="memory cap of the --where query (default 2GB)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vprscale.evaluation.results import eval_folder, load_results
    from vprscale.evaluation.sql import format_table, sandbox

    if args.where is None and args.format == "table":
        frame = load_results(*args.paths, queries=args.queries)
        print(frame.to_string(max_rows=60, max_cols=12))
        return 0
    folders = [eval_folder(p) for p in args.paths]
    query = f"SELECT * FROM {'queries' if args.queries else 'results'}" + (
        f" WHERE {args.where}" if args.where else "")  # the user's own predicate, in the sandbox
    with sandbox(folders, args.memory_limit, 2) as box:
        print(format_table(box.query(query, args.timeout), args.format), end="")
    return 0
