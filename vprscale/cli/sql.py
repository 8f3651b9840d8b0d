"""``vprscale sql``: read-only SQL over an index and evaluations."""

from __future__ import annotations

import argparse
from pathlib import Path

from vprscale.cli.common import bounded_int, positive_float

MAX_SQL_THREADS = 256


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("sql", help="read-only SQL over an index and evaluations (views lists, buckets, model, "
                                   "results, queries)")
    p.add_argument("paths", nargs="+", metavar="PATH [QUERY]",
                   help="an index directory and/or evaluation folders (viewed together, with a run column), then "
                        "one SELECT statement; without it, an interactive shell")
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--csv", dest="format", action="store_const", const="csv")
    fmt.add_argument("--json", dest="format", action="store_const", const="json")
    p.add_argument("--timeout", type=positive_float, default=30.0,
                   help="seconds before a query is stopped (default 30)")
    p.add_argument("--memory-limit", default="2GB", help="DuckDB's memory cap (default 2GB)")
    p.add_argument("--threads", type=bounded_int(MAX_SQL_THREADS, "DuckDB starts every thread it is given"),
                   default=2, help="DuckDB's threads (default 2)")
    p.set_defaults(func=run, format="table")


def run(args: argparse.Namespace) -> int:
    from vprscale.evaluation.sql import run_sql, shell

    paths, query = args.paths, None
    if len(paths) > 1 and not Path(paths[-1]).exists():  # the last word is the statement, not a folder
        paths, query = paths[:-1], paths[-1]
    if query is None:
        return shell(paths, timeout=args.timeout, memory_limit=args.memory_limit, threads=args.threads)
    print(run_sql(paths, query, fmt=args.format, timeout=args.timeout, memory_limit=args.memory_limit,
                  threads=args.threads), end="")
    return 0
