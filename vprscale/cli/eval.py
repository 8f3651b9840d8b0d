"""``vprscale eval``: localises query sequences and evaluates the grid of docs/protocol.md."""

from __future__ import annotations

import argparse
from pathlib import Path

from vprscale.cli.common import csv_of, local_output, positive_float, positive_int, write_summary
from vprscale.core.errors import InputError
from vprscale.core.objects import is_url, location, public

INPUTS = ('store', 'index')  # the flags naming what it reads: no output may be written over them


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("eval", parents=[cluster, summary],
                       help="localise query sequences and evaluate the grid of docs/protocol.md")
    p.add_argument("store", help="a complete <scale>.zarr dataset store")
    p.add_argument("index", nargs="?", help="an index of that store (or use --d to index several widths)")
    p.add_argument("--noise", type=csv_of(str), default=None,
                   help="the store's query sets to evaluate, e.g. qm1,qm2 (default: every one it holds)")
    p.add_argument("--L", type=csv_of(int), default=None, help="sequence lengths (default: 1,50,100)")
    p.add_argument("--modes", type=csv_of(str), default=["paper", "aligned"], help="paper,aligned")
    p.add_argument("--baseline", action=argparse.BooleanOptionalAction, default=True,
                   help="also run the baseline of docs/method.md (default on)")
    p.add_argument("--z", type=positive_int, default=None, help="query stride (default: the recipe's)")
    p.add_argument("--baseline-queries", type=positive_int, default=None,
                   help="localise an evenly spaced sample of this many centres per baseline run (default: all "
                        "below 10^8 query rows, 64 beyond: each baseline query scans every place)")
    p.add_argument("--d", type=csv_of(int), default=None, help="index widths to sweep, e.g. 12,14,16,18,20")
    p.add_argument("--compare", metavar="FACTORY", action="append", default=[],
                   help="also evaluate a FAISS index_factory string as method faiss:FACTORY, e.g. PQ3, OPQ3,PQ3, "
                        "ITQ24,LSH, IVF4096,PQ3; or a pooled sequence descriptor held in one: seq:FACTORY (the "
                        "mean of each window of L frames), seq-gem3:FACTORY (GeM), with +rerank for CoarseHash's "
                        "window score over its 20 best (repeat for several; docs/protocol.md)")
    p.add_argument("--faiss-k", type=csv_of(int), default=None,
                   help="references each query frame retrieves from a FAISS index, e.g. 4,16,64: one operating "
                        "point each (default: CoarseHash's mean list size on INDEX, the same candidate budget)")
    p.add_argument("--faiss-nprobe", type=csv_of(int), default=[16],
                   help="inverted lists an IVF index visits per frame, e.g. 1,8,64: one operating point each, "
                        "with every --faiss-k (default 16)")
    p.add_argument("--method", metavar="CLASS", action="append", default=[], dest="methods",
                   help="also evaluate your own method: package.module:Class of the contract in "
                        "docs/bring-your-own.md, or an installed method's name (repeat for several)")
    p.add_argument("--method-k", type=csv_of(int), default=None,
                   help="references each query frame retrieves from a --method, e.g. 4,16,64: one operating point "
                        "each (default: CoarseHash's mean list size on INDEX)")
    p.add_argument("--compare-queries", type=positive_int, default=None,
                   help="centres per compared (FAISS or --method) run (default: flat FAISS codes that scan, such as "
                        "fast-scan PQ: all while the run's frames visit at most 2^35 codes, beyond, an evenly spaced "
                        "sample that fits, at least 1,000; every other code and --method: all)")
    p.add_argument("--flat-noise", type=csv_of(str), default=None,
                   help="noise levels the scanning flat FAISS codes (fast-scan PQ, decoded-vector codes) run on, e.g. "
                        "qm1 (default: every --noise): at least 1,000 centres of L frames each scan every code, about "
                        "5 minutes per code and noise level at 10M on 2 cores for PQ6x4fs; PQ, OPQ and binary codes "
                        "find their exact top-k without a scan and run on every level (docs/protocol.md)")
    p.add_argument("--deep1b", metavar="PATH", help="a compact store built from files: its Deep1B file (--compare "
                   "and --method recompute the references from the sources; not needed for synthetic stores)")
    p.add_argument("--fas", metavar="PATH", help="a compact store built from files: its FAS file (as --deep1b)")
    p.add_argument("--force", action="store_true",
                   help="replace an evaluation already in the output; the old one is kept beside, as <out>.previous")
    p.add_argument("--radius-m", type=csv_of(float), default=None, metavar="R",
                   help="also count a match correct within these radii in metres of the query's position, e.g. "
                        "10,25,50 (a store with positions: build --ref-pos --query-pos); rows in results_m.parquet")
    p.add_argument("--nn", action="store_true",
                   help="also the nearest-neighbour axis: 1-NN recall at 1, 10 and 100 of CoarseHash and each FAISS "
                        "code against exact neighbours found by brute force, on Deep1B query rows; nn.parquet")
    p.add_argument("--nn-queries", type=positive_int, default=10_000, metavar="N",
                   help="Deep1B query rows per noise level for --nn, evenly spaced (default 10,000)")
    p.add_argument("--repeats", type=positive_int, default=3,
                   help="timing repeats of every timed kernel, on one thread (default 3; docs/accounting.md)")
    task = p.add_argument_group("MSLS's tasks (a store of many sequences: build --msls, or --ref-seq and --query-seq)")
    task.add_argument("--task", choices=["im2im", "seq2im", "im2seq", "seq2seq"], default=None,
                      help="evaluate MSLS's task instead of the frame grid: recall@k and map@k, k = 1, 5, 10, 20")
    task.add_argument("--seq-length", type=positive_int, default=3,
                      help="frames of a sequence in seq2im, im2seq, seq2seq (odd; default 3)")
    task.add_argument("--subtask", default="all", choices=["all", "s2w", "w2s", "o2n", "n2o", "d2n", "n2d"],
                      help="MSLS's subtask: its query and database windows only (default all)")
    task.add_argument("--threshold", type=positive_float, default=25.0, metavar="M",
                      help="a positive holds a frame within M metres of a query frame (default 25, MSLS's)")
    task.add_argument("--export-msls", metavar="FILE",
                      help="write each method's answers as MSLS's prediction file, which its evaluate.py scores "
                           "(several methods: FILE with the method's name before the suffix)")
    p.add_argument("--out", help="output directory (default: INDEX/eval)")
    p.set_defaults(func=run, input_flags=INPUTS, out_is_dir=True)


def run(args: argparse.Namespace) -> int:
    from vprscale.evaluation.evaluate import EvalRequest, check_request, evaluate
    from vprscale.jobs.indexing import sweep_indexes

    if args.index and is_url(args.index) and not args.out:
        raise InputError(f"--out: give a folder for the evaluation of {public(args.index)} (an index on object "
                         "storage is read from a copy in the cache, which is no place for results)")
    req = EvalRequest(store=location(args.store), indexes=[local_output(args.index)] if args.index else [],
                      index_urls=[public(args.index) if is_url(args.index) else None] if args.index else [],
                      noises=args.noise, lengths=[1, 50, 100] if args.L is None else args.L, modes=args.modes,
                      baseline=args.baseline,
                      z=args.z, baseline_queries=args.baseline_queries,
                      compare=args.compare, faiss_k=args.faiss_k, methods=args.methods, method_k=args.method_k,
                      faiss_nprobe=args.faiss_nprobe, compare_queries=args.compare_queries,
                      flat_noise=args.flat_noise,
                      deep1b=args.deep1b, fas=args.fas, out=location(args.out) if args.out else None,
                      workers=args.workers, scheduler=args.scheduler, repeats=args.repeats,
                      force=args.force, radii_m=args.radius_m, nn=args.nn, nn_queries=args.nn_queries,
                      task=args.task, seq_length=args.seq_length, subtask=args.subtask, threshold_m=args.threshold,
                      export_msls=Path(args.export_msls).absolute() if args.export_msls else None)
    if args.task is not None and args.L is not None:
        raise InputError("--L: a task sets its own lengths (--seq-length)")
    if args.d:  # a sweep: its indexes are built (where missing) once the request is known to be sound
        if args.compare or args.methods:
            flag = "--compare" if args.compare else "--method"
            raise InputError(f"{flag}: compares with one index at a time, not with a --d sweep")
        check_request(req)
        req.indexes = sweep_indexes(args.store, args.d, scheduler=args.scheduler, workers=args.workers)
    summary = evaluate(req)
    if summary.get("recovered"):
        write_summary(args, summary)
        return 0
    print(summary["table"])
    for path in summary.get("predictions") or []:
        print(f"wrote {path} (MSLS's prediction format)")
    for L, count in (summary.get("windows") or {}).items():  # a store of many sequences
        if int(L) > 1:
            print(f"L = {L}: {count['query_centres_without_window']:,} query centres and "
                  f"{count['places_without_window']:,} places have no window of {L} frames inside one sequence "
                  "(left out: never a query, a candidate or an answer)")
    print(f"wrote {summary['out']}/results.parquet ({summary['rows']:,} rows) and queries.parquet "
          f"({summary['queries']:,} rows)" + (f", results_m.parquet (radii {','.join(f'{r:g}' for r in args.radius_m)}"
                                            " m)" if args.radius_m else "") + (", nn.parquet" if args.nn else "")
          + f"; z = {summary['z']}")
    write_summary(args, summary)
    return 0
