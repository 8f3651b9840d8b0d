"""``vprscale results``: shows any number of evaluations as one table."""

from __future__ import annotations

import argparse

from vprscale.cli.common import local_output, positive_float


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("results", help="any number of evaluations as one table (filter with --where SQL)")
    p.add_argument("paths", nargs="+", help="evaluation folders (INDEX/eval, eval --out) or indexes")
    p.add_argument("--where", help="an SQL condition on the columns, e.g. \"method = 'coarsehash' AND radius = 20\"")
    table = p.add_mutually_exclusive_group()
    table.add_argument("--queries", action="store_true", help="the per-query rows instead of the recall table")
    table.add_argument("--metres", action="store_true",
                       help="recall within radii in metres of each query's position (eval --radius-m) instead of "
                            "radii in frames")
    p.add_argument("--all-columns", action="store_true",
                   help="every column in the table (--csv and --json always have every column)")
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--csv", dest="format", action="store_const", const="csv", default="table",
                     help="CSV with a header row")
    fmt.add_argument("--json", dest="format", action="store_const", const="json", help="one JSON object per row")
    best = p.add_argument_group("operating points", "each method family's best recall within a budget, as "
                                "big-ann-benchmarks names them (docs/protocol.md, \"Operating points\")")
    best.add_argument("--best-bytes", type=positive_float, metavar="B",
                      help="the best recall at or under B bytes per place, per scale, noise, L and family")
    best.add_argument("--best-qps", type=positive_float, metavar="Q",
                      help="the best recall at or above Q queries per second per core (with --best-bytes: both)")
    best.add_argument("--radius", type=int, default=20, help="the recall radius (frames) --best-* rank by")
    p.add_argument("--timeout", type=positive_float, default=30.0, help="seconds the --where query may run")
    p.add_argument("--memory-limit", default="2GB", help="memory cap of the --where query (default 2GB)")
    p.set_defaults(func=run)


# What a reader asks of a recall row first: which method, of which family, configured how, at which point, how
# well. (--best-*: each operating point's series, a method in one mode, its parameters, queries per second per core)
TABLE_COLUMNS = ("run", "scale", "noise", "method", "series", "family", "params", "mode", "L", "part", "radius",
                 "recall", "recall_lo", "recall_hi", "recall_at_20", "n_queries", "nr_mean", "bytes_per_place",
                 "us_per_query", "qps_per_core")
METRE_COLUMNS = tuple("radius_m" if c == "radius" else c for c in TABLE_COLUMNS)
QUERY_COLUMNS = ("run", "noise", "method", "params", "mode", "L", "centre", "gt", "match", "score", "n_r")
# an evaluation of MSLS's tasks (eval --task): its own metrics, recall@k and map@k
TASK_KS = (1, 5, 10, 20)
TASK_COLUMNS = ("run", "scale", "task", "seq_length", "subtask", "method", "family", "params", "mode", "part",
                "n_queries", *(f"recall_at_{k}" for k in TASK_KS), *(f"map_at_{k}" for k in TASK_KS),
                "bytes_per_place", "us_per_query")


def _is_task(table) -> bool:
    """Whether every row is a task's (``eval --task``): then the table shows recall@k and map@k."""
    return "task" in table.column_names and table.column("task").null_count == 0 and table.num_rows > 0


def _shown(table, all_columns: bool, queries: bool, metres: bool = False):
    """The table's columns for the eye: the chosen few (``run`` only when several runs are shown,
    as a path relative to here), or every one."""
    import os

    import pyarrow as pa
    import pyarrow.compute as pc

    if "run" in table.column_names:
        runs = table.column("run").to_pylist()
        if len(set(runs)) > 1 or all_columns:
            table = table.set_column(table.column_names.index("run"), "run",
                                     pa.array([os.path.relpath(r) for r in runs], pa.string()))
        else:
            table = table.drop_columns(["run"])
    if all_columns:
        return table
    task = not queries and _is_task(table)
    keep = [c for c in (QUERY_COLUMNS if queries else TASK_COLUMNS if task else METRE_COLUMNS if metres
                        else TABLE_COLUMNS) if c in table.column_names]
    table = table.select(keep)
    for name in ("recall", "recall_lo", "recall_hi", "recall_at_20", "nr_mean", "bytes_per_place", "us_per_query",
                 "qps_per_core", *(f"{m}_at_{k}" for m in ("recall", "map") for k in TASK_KS)):
        if name in table.column_names:  # three decimals (one for µs and queries a second) read at a glance
            table = table.set_column(table.column_names.index(name), name,
                                     pc.round(table.column(name), 1 if name in ("us_per_query", "qps_per_core")
                                              else 3))
    return table


def _best(table, args: argparse.Namespace):
    """The operating points of ``table`` within the ``--best-*`` budget, as a pyarrow table."""
    import pyarrow as pa

    from vprscale.core.errors import InputError
    from vprscale.evaluation.operating import best_points

    if args.queries:
        raise InputError("--best-bytes/--best-qps: operating points come from the recall table, not --queries")
    if args.metres:
        raise InputError("--best-bytes/--best-qps: operating points rank by a radius in frames, not --metres")
    res = table.to_pandas()
    if args.radius not in set(res.radius):
        raise InputError(f"--radius {args.radius}: the evaluations hold radii {int(res.radius.min())} … "
                         f"{int(res.radius.max())}")
    return pa.Table.from_pandas(best_points(res, args.best_bytes, args.best_qps, args.radius), preserve_index=False)


def run(args: argparse.Namespace) -> int:
    import shutil
    import sys

    from vprscale.evaluation.results import eval_folder, load_tables
    from vprscale.evaluation.sql import sandbox, write_table

    args.paths = [str(local_output(p)) for p in args.paths]  # by URL: a verified copy in the cache

    if args.where is None:  # every row: read as it is, no SQL engine needed
        import pyarrow as pa

        parts = [t.append_column("run", pa.array([str(folder)] * t.num_rows, pa.string()))
                 for t, folder, _ in load_tables(*args.paths, queries=args.queries, metres=args.metres)]
        table = pa.concat_tables(parts, promote_options="permissive")
    else:
        folders = [eval_folder(p) for p in args.paths]
        view = "queries" if args.queries else "results_m" if args.metres else "results"
        query = f"SELECT * FROM {view} WHERE {args.where}"  # in the sandbox
        with sandbox(folders, args.memory_limit, 2) as box:
            table = box.query(query, args.timeout)
    if args.best_bytes is not None or args.best_qps is not None:
        table = _best(table, args)
    width = shutil.get_terminal_size().columns if args.format == "table" and sys.stdout.isatty() else None
    shown = _shown(table, args.all_columns, args.queries, args.metres) if args.format == "table" else table
    write_table(shown, args.format, sys.stdout, max_width=width)
    if args.format == "table" and not args.all_columns:
        legend = ([TASK_LEGEND] if _is_task(shown) else
                  [text for column, text in _legend(args.metres).items() if column in shown.column_names])
        if legend:
            print("; ".join(legend))
    return 0


TASK_LEGEND = ("recall_at_k: share of query windows with a positive (a database window holding a frame within the "
               "threshold of a query frame) among their k first answers; map_at_k: MSLS's mean average precision at "
               "k")


def _legend(metres: bool) -> dict[str, str]:
    """What each recall column of the table means, said under it: ``recall`` is the match within a
    radius of the truth, ``recall_at_20`` Recall@N (any of N candidates), two different things that
    a bare "R@20" would confuse."""
    within = "radius_m metres" if metres else "radius frames"
    return {"recall": f"recall: the match within {within} of the truth (recall_lo, recall_hi: its 95 % interval)",
            "recall_at_20": f"recall_at_20: Recall@N, any of the N = 20 best candidates within {within}"}
