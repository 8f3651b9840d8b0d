"""``vprscale bench``: benchmarks a build, an index, look-ups, an evaluation or the code scores."""

from __future__ import annotations

import argparse
import os
import shlex

from vprscale.cli.common import positive_int
from vprscale.core.errors import InputError


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("bench", help="benchmark a build, an index, look-ups, an evaluation or the one-shot commands' "
                                     "start-up (prints figures)")
    p.add_argument("job", choices=["build", "index", "lookup", "eval", "online", "format", "codes", "assign",
                                   "startup"],
                   help="what to benchmark")
    p.add_argument("target", help="build: a scale; index/eval/online/format/codes/assign: a store; lookup, startup: "
                   "an index")
    p.add_argument("--out", default="data/bench", help="build: output directory")
    p.add_argument("--deep1b", help="build: a Deep1B file (default: synthetic)")
    p.add_argument("--fas", help="build: a FAS100K .npz (default: synthetic)")
    p.add_argument("--script", metavar="PREPROCDATA_PY",
                   help="build: also run the paper authors' preProcData.py on the same --deep1b and --fas files, "
                        "alternating with the build, and print the ratio of their times")
    p.add_argument("--runs", type=positive_int, default=2, help="build --script: runs of each (default 2)")
    p.add_argument("--d", type=positive_int, help="index: hash digits (default ⌈log2 N_ref⌉)")
    p.add_argument("--index", help="eval, online, format: the index to evaluate")
    p.add_argument("--L", type=positive_int, help="online, codes, format: sequence length (default: online 1, 50 "
                   "and 100; codes and format 100)")
    p.add_argument("--compare", action="append", metavar="FACTORY",
                   help="codes, assign: a FAISS index_factory string (repeat; default codes: PQ3, OPQ3,PQ3, "
                   "IVF1024,PQ3; assign: IVF4096,PQ3, IVF1024,PQ3, IVF4096_HNSW32,PQ3)")
    p.add_argument("--places", type=positive_int,
                   help="codes, assign: references read (default: all of the store's)")
    p.add_argument("--workers", type=positive_int, default=os.cpu_count() or 1,
                   help="threads for the job (default: all cores)")
    p.add_argument("--eval-args", default="", help='eval: further eval options, e.g. "--L 100 --modes paper"')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vprscale.jobs import bench

    if args.job == "build" and args.script:
        from vprscale.jobs.scriptbench import bench_against_script

        print(bench_against_script(args.script, args.target, args.out, args.deep1b, args.fas, args.workers,
                                   args.runs))
    elif args.job == "build":
        print(bench.bench_build(args.target, args.out, args.deep1b, args.fas, args.workers))
    elif args.job == "index":
        print(bench.bench_index(args.target, args.d, args.workers))
    elif args.job == "startup":
        from vprscale.jobs.startupbench import bench_startup

        print(bench_startup(args.target))
    elif args.job == "lookup":
        print(bench.bench_lookup(args.target))
    elif args.job == "codes":
        from vprscale.jobs.codesbench import DEFAULT_FACTORIES, bench_codes

        print(bench_codes(args.target, args.compare or list(DEFAULT_FACTORIES), args.places, args.L or 100))
    elif args.job == "assign":
        from vprscale.jobs.assignbench import DEFAULT_FACTORIES as ASSIGN_FACTORIES
        from vprscale.jobs.assignbench import bench_assign

        print(bench_assign(args.target, args.compare or list(ASSIGN_FACTORIES), args.places))
    elif args.job in ("online", "format"):
        if not args.index:
            raise InputError(f"bench {args.job}: give --index")
        if args.job == "online":
            print(bench.bench_online(args.target, args.index, (args.L,) if args.L else (1, 50, 100)))
        else:
            from vprscale.jobs.formatbench import bench_format, bench_tables

            print(bench_tables(args.target, args.index, args.L or 100))
            print(bench_format(args.target, args.index, (1, args.L or 100)))
    else:
        if not args.index:
            raise InputError("bench eval: give --index")
        print(bench.bench_eval(args.target, args.index, shlex.split(args.eval_args), args.workers))
    return 0
