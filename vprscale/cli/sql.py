"""``vprscale sql``: read-only SQL over an index and evaluations."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vprscale.cli.common import bounded_int, local_output, positive_float
from vprscale.core.objects import is_url

MAX_SQL_THREADS = 256


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("sql", help="read-only SQL over an index and evaluations (views lists, buckets, model, "
                                   "results, queries)")
    p.add_argument("paths", nargs="+", metavar="PATH [QUERY]",
                   help="an index directory and/or evaluation folders (viewed together, with a run column), then "
                        "one SELECT statement; without it, an interactive shell")
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--csv", dest="format", action="store_const", const="csv", help="CSV with a header row")
    fmt.add_argument("--json", dest="format", action="store_const", const="json", help="one JSON object per row")
    p.add_argument("--timeout", type=positive_float, default=30.0,
                   help="seconds before a query is stopped (default 30)")
    p.add_argument("--memory-limit", default="2GB", help="DuckDB's memory cap (default 2GB)")
    p.add_argument("--threads", type=bounded_int(MAX_SQL_THREADS, "DuckDB starts every thread it is given"),
                   default=2, help="DuckDB's threads (default 2)")
    p.set_defaults(func=run, format="table")


def _is_path(text: str) -> bool:
    """Whether a word names something on disk or by URL; a statement longer than a file name may be is not."""
    if is_url(text):
        return True
    try:
        return Path(text).exists()
    except (OSError, ValueError):  # ENAMETOOLONG, a NUL byte
        return False


def run(args: argparse.Namespace) -> int:
    paths, query = args.paths, None
    if len(paths) > 1 and not _is_path(paths[-1]):  # the last word is the statement, not a folder
        paths, query = paths[:-1], paths[-1]
    paths = [str(local_output(p)) for p in paths]
    if query is None:
        from vprscale.cli.sqlshell import shell

        return shell(paths, timeout=args.timeout, memory_limit=args.memory_limit, threads=args.threads)
    from vprscale.evaluation.sql import run_sql

    run_sql(paths, query, fmt=args.format, timeout=args.timeout, memory_limit=args.memory_limit, threads=args.threads,
            out=sys.stdout)
    return 0
