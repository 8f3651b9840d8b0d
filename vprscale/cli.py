"""The ``vprscale`` command line. User errors print one line and exit with status 2."""

from __future__ import annotations

import argparse
import errno
import json
import os
import shlex
import shutil
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from vprscale.core.errors import InputError, JobFailed
from vprscale.core.provenance import set_command

EXIT_USAGE = 2  # bad input
EXIT_FAILURE = 1  # vprscale itself failed
MAX_FAS_DIM = 16_384  # a synthetic FAS row of more features is drawn in memory, a chunk at a time
MAX_SQL_THREADS = 256


def _positive_int(text: str) -> int:
    try:
        value = int(text.replace("_", "").replace(",", ""))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be positive")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"{text!r} must be a positive, finite number")
    return value


def _bounded_int(upper: int, why: str):
    """A positive whole number of at most ``upper`` (``why`` says where the bound comes from)."""
    def parse(text: str) -> int:
        value = _positive_int(text)
        if value > upper:
            raise argparse.ArgumentTypeError(f"{text!r} is more than {upper:,} ({why})")
        return value
    return parse


def _write_summary(args: argparse.Namespace, data: dict) -> None:
    """``--summary FILE``: the command's summary as JSON (what pipelines read back), written whole."""
    if getattr(args, "summary", None):
        path = Path(args.summary)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(json.dumps(data, indent=1, default=str))
        tmp.replace(path)


# The flags that name what a command reads, and what it writes.
INPUT_FLAGS = {"build": ("deep1b", "fas", "scale"), "index": ("store", "upgrade"), "eval": ("store", "index"),
               "localise": ("index", "queries"), "report": ("results", "index")}
OUTPUT_FLAGS = ("out", "summary")


def _flag_paths(args: argparse.Namespace, names: Sequence[str]) -> list[tuple[str, Path]]:
    found = []
    for name in names:
        value = getattr(args, name, None)
        for v in value if isinstance(value, list) else [value]:
            if isinstance(v, str) and v and (name != "scale" or Path(v).suffix == ".toml"):
                found.append((name, Path(v)))
    return found


def _owner(path: Path) -> Path | None:
    """The vprscale store or index that ``path`` lies inside (symlinks followed), if any."""
    for parent in path.resolve().parents:
        if (parent / "index.json").is_file() or (parent / "zarr.json").is_file():
            return parent
    return None


def _check_not_over_inputs(args: argparse.Namespace) -> None:
    """No output flag may name one of the command's inputs, lie inside one, or lie inside a
    store or index the command does not own (paths resolved, symlinks followed)."""
    inputs = _flag_paths(args, INPUT_FLAGS.get(args.command, ()))
    for out_flag, out in _flag_paths(args, OUTPUT_FLAGS):
        target = out.resolve()
        for in_flag, src in inputs:
            where = src.resolve()
            if target == where or where in target.parents:
                raise InputError(f"--{out_flag} {out}: would write {'over' if target == where else 'into'} the "
                                 f"input {src} (--{in_flag})")
        owner = _owner(out)
        own_eval = (args.command == "eval" and out_flag == "out" and getattr(args, "index", None)
                    and target == (Path(args.index) / "eval").resolve())
        if owner is not None and not own_eval:
            raise InputError(f"--{out_flag} {out}: lies inside {owner}, a vprscale store or index this command does "
                             "not own; write elsewhere")


def _check_outputs(args: argparse.Namespace) -> None:
    """Refuse unusable output paths before any work (a bad --summary must not fail after publishing)."""
    _check_not_over_inputs(args)
    summary = getattr(args, "summary", None)
    if summary:
        path = Path(summary)
        if path.is_dir():
            raise InputError(f"--summary {summary}: is a directory; give a file name")
        if not path.parent.is_dir():
            raise InputError(f"--summary {summary}: the folder {path.parent} does not exist")
        if not os.access(path.parent, os.W_OK | os.X_OK):
            raise InputError(f"--summary {summary}: the folder {path.parent} is not writable")
    out = getattr(args, "out", None)
    if out and args.command in ("synth", "report", "build", "eval") and Path(out).exists() and not Path(out).is_dir():
        raise InputError(f"--out {out}: is a file, not a directory")


def cmd_synth(args: argparse.Namespace) -> int:
    from vprscale.dataset.synth import write_synthetic

    paths = write_synthetic(Path(args.out), args.deep1b_rows, args.fas_dim, args.seed,
                            rows_per_file=args.rows_per_file)
    for p in paths:
        print(p)
    _write_summary(args, {"dir": args.out, "fvecs": str(paths[0].parent), "fbin": str(paths[-2]),
                          "fas": str(paths[-1])})
    return 0


def cmd_build(args: argparse.Namespace) -> int:
    from vprscale.dataset.build import BuildRequest, build, format_summary

    if args.ref or args.query or args.gt:
        return _build_own(args)
    if not args.scale:
        raise InputError("build: give --scale (a recipe), or --ref, --query and --gt (your own descriptors)")
    summary = build(BuildRequest(scale=args.scale, out=Path(args.out), deep1b=args.deep1b, fas=args.fas,
                                 workers=args.workers, scheduler=args.scheduler, dry_run=args.dry_run,
                                 force=args.force, fas_dim=args.fas_dim, rescale=args.rescale,
                                 layout=args.layout))
    if not summary.get("dry_run") and not summary.get("skipped"):
        print(format_summary(summary))
    _write_summary(args, summary)
    return 0


def _build_own(args: argparse.Namespace) -> int:
    from vprscale.dataset.build import format_summary
    from vprscale.dataset.own import OwnRequest, build_own, parse_query

    for flag in ("scale", "deep1b", "fas", "layout"):
        if getattr(args, flag):
            raise InputError(f"--{flag}: a recipe's option; your own descriptors (--ref) are stored as given")
    missing = [f for f, v in (("--ref", args.ref), ("--query", args.query), ("--gt", args.gt)) if not v]
    if missing:
        raise InputError(f"build: {' and '.join(missing)} missing (your own descriptors need --ref, --query, --gt)")
    if args.dry_run:
        raise InputError("--dry-run: plans a recipe's build; your own descriptors are copied as they are")
    queries = dict(parse_query(q) for q in args.query)
    if len(queries) != len(args.query):
        raise InputError("--query: a name is given twice")
    summary = build_own(OwnRequest(ref=args.ref, queries=queries, gt=args.gt, part=args.part, out=Path(args.out),
                                   name=args.name, stride=args.stride, force=args.force, workers=args.workers,
                                   scheduler=args.scheduler))
    print(format_summary(summary))
    _write_summary(args, summary)
    return 0


def cmd_encode(args: argparse.Namespace) -> int:
    from vprscale.jobs.encoding import encode_store

    summary = encode_store(Path(args.store), args.compare or [], deep1b=args.deep1b, fas=args.fas,
                           workers=args.workers, scheduler=args.scheduler, force=args.force)
    for factory, m in summary["methods"].items():
        done = "up to date, kept" if m.get("skipped") else f"{m['wall_s']:,.1f} s, {m['code_bytes']} B a code"
        print(f"faiss:{factory}: {summary['n_ref']:,} references → {m['out']} ({done})")
    print(f"  peak memory {summary['peak_rss_bytes'] / 2**30:.2f} GiB")
    _write_summary(args, summary)
    return 0


def cmd_index(args: argparse.Namespace) -> int:
    from vprscale.evaluation.storage import format_parts, format_storage, index_parts
    from vprscale.jobs.indexing import build_index, upgrade_index

    if args.upgrade:
        if args.store:
            raise InputError(f"--upgrade {args.upgrade}: converts an index; give no store ({args.store})")
        meta = upgrade_index(args.upgrade)
        print(f"{args.upgrade}: format {meta['format']}" + (" (converted from format 2, no refit)"
                                                             if meta.get("converted") else " already"))
        print(format_parts(index_parts(Path(args.upgrade)), meta["n_ref"], meta["d"], meta["k"]))
        _write_summary(args, meta)
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
    print(format_parts(index_parts(Path(meta["index"])), meta["n_ref"], meta["d"], meta["k"]))
    _write_summary(args, meta)
    return 0


def cmd_sql(args: argparse.Namespace) -> int:
    from vprscale.evaluation.sql import run_sql, shell

    paths, query = args.paths, None
    if len(paths) > 1 and not Path(paths[-1]).exists():  # the last word is the statement, not a folder
        paths, query = paths[:-1], paths[-1]
    if query is None:
        return shell(paths, timeout=args.timeout, memory_limit=args.memory_limit, threads=args.threads)
    print(run_sql(paths, query, fmt=args.format, timeout=args.timeout, memory_limit=args.memory_limit,
                  threads=args.threads), end="")
    return 0


def cmd_occupancy(args: argparse.Namespace) -> int:
    from vprscale.evaluation.occupancy import format_occupancy, occupancy

    occ = occupancy(args.index, top=args.top)
    print(json.dumps(occ) if args.json else format_occupancy(occ))
    return 0


def cmd_localise(args: argparse.Namespace) -> int:
    from vprscale.jobs.localise import localise

    summary = localise(args.index, args.queries, args.L, mode=args.mode, out=args.out)
    if args.out is None:
        print(f"{summary['frames']:,} frames localised ({summary['us_per_frame']:.1f} µs per frame); "
              "give --out FILE to keep the matches")
    _write_summary(args, summary)
    return 0


def _csv(kind):
    def parse(text: str) -> list:
        try:
            return [kind(v) for v in text.split(",") if v.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list") from None
    return parse


def cmd_eval(args: argparse.Namespace) -> int:
    from vprscale.evaluation.evaluate import EvalRequest, check_request, evaluate
    from vprscale.jobs.indexing import sweep_indexes

    req = EvalRequest(store=Path(args.store), indexes=[Path(args.index)] if args.index else [],
                      noises=args.noise, lengths=args.L, modes=args.modes, baseline=args.baseline,
                      z=args.z, baseline_queries=args.baseline_queries,
                      compare=args.compare, faiss_k=args.faiss_k, methods=args.methods, method_k=args.method_k,
                      faiss_nprobe=args.faiss_nprobe, compare_queries=args.compare_queries,
                      flat_noise=args.flat_noise,
                      deep1b=args.deep1b, fas=args.fas, out=Path(args.out) if args.out else None,
                      workers=args.workers, scheduler=args.scheduler, repeats=args.repeats,
                      force=args.force)
    if args.d:  # a sweep: its indexes are built (where missing) once the request is known to be sound
        if args.compare or args.methods:
            flag = "--compare" if args.compare else "--method"
            raise InputError(f"{flag}: compares with one index at a time, not with a --d sweep")
        check_request(req)
        req.indexes = sweep_indexes(args.store, args.d, scheduler=args.scheduler, workers=args.workers)
    summary = evaluate(req)
    if summary.get("recovered"):
        _write_summary(args, summary)
        return 0
    print(summary["table"])
    print(f"wrote {summary['out']}/results.parquet ({summary['rows']:,} rows) and queries.parquet "
          f"({summary['queries']:,} rows); z = {summary['z']}")
    _write_summary(args, summary)
    return 0


def cmd_results(args: argparse.Namespace) -> int:
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


def cmd_methods(args: argparse.Namespace) -> int:
    from vprscale.evaluation.algorithms.registry import registered

    notes = {"built-in": "", "factory": "  (entry point vprscale.algorithms: joins every evaluation)",
             "method": "  (entry point vprscale.algorithms: eval --method NAME)"}
    for name, (target, kind) in registered().items():
        print(f"{name:<12} {target}{notes[kind]}")
    print("any class of the contract in docs/bring-your-own.md: eval --method package.module:Class")
    return 0


def cmd_verify(args: argparse.Namespace) -> int:
    from vprscale.core.manifest import check_manifest, read_manifest

    path = Path(args.path)
    kinds = {"zarr.json": "dataset store", "index.json": "index", "eval.json": "evaluation"}
    kind = next((k for f, k in kinds.items() if (path / f).is_file()), None)
    if kind is None:
        raise InputError(f"{path}: not a vprscale store, index or evaluation")
    if read_manifest(path) is None:
        raise InputError(f"{path}: this {kind} has no manifest (written before vprscale 0.3); rebuild it to verify")
    n = check_manifest(path, full=True)
    print(f"{path}: {kind} verified, {n:,} files with their sizes and checksums")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from vprscale.evaluation.report import write_report

    rep = write_report(args.results, Path(args.out), extra_indexes=args.index)
    print(f"wrote {rep['report']} and {len(rep['figures'])} figure files")
    _write_summary(args, rep)
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from vprscale.jobs.pipeline import run_pipeline

    summary = run_pipeline(args.pipeline, scheduler=args.scheduler, force=args.force, dry_run=args.dry_run)
    if args.dry_run:
        for s in summary["stages"]:
            why = "; ".join(s["reasons"]) if s["run"] else "up to date"
            print(f"{'run ' if s['run'] else 'skip'}  {s['name']} ({s['kind']}): {why}")
        return 0
    ran = [s["name"] for s in summary["stages"] if s["status"] == "ran"]
    print(f"pipeline {summary['name']}: {summary['status']}; ran {len(ran)} of {len(summary['stages'])} stages "
          f"({', '.join(ran) or 'none: everything was up to date'}); summary {summary['summary_file']}")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from vprscale.jobs import bench

    if args.job == "build":
        print(bench.bench_build(args.target, args.out, args.deep1b, args.fas, args.workers))
    elif args.job == "index":
        print(bench.bench_index(args.target, args.d, args.workers))
    elif args.job == "lookup":
        print(bench.bench_lookup(args.target))
    elif args.job == "codes":
        from vprscale.jobs.codesbench import DEFAULT_FACTORIES, bench_codes

        print(bench_codes(args.target, args.compare or list(DEFAULT_FACTORIES), args.places, args.L))
    elif args.job in ("online", "format"):
        if not args.index:
            raise InputError(f"bench {args.job}: give --index")
        if args.job == "online":
            print(bench.bench_online(args.target, args.index, args.L))
        else:
            from vprscale.jobs.formatbench import bench_format

            print(bench_format(args.target, args.index, (1, args.L)))
    else:
        if not args.index:
            raise InputError("bench eval: give --index")
        print(bench.bench_eval(args.target, args.index, shlex.split(args.eval_args), args.workers))
    return 0


def _shared_flags() -> tuple[argparse.ArgumentParser, argparse.ArgumentParser]:
    """The flags several commands share, declared once: (cluster, summary)."""
    cluster = argparse.ArgumentParser(add_help=False)
    cluster.add_argument("--scheduler", metavar="ADDRESS",
                         help="address of a Dask distributed scheduler (tcp://host:8786); default: none, the "
                              "work runs on threads of this process")
    cluster.add_argument("--workers", type=_positive_int, default=os.cpu_count() or 1,
                         help="threads of this process for Dask and for the numba kernels (default: all cores)")
    summary = argparse.ArgumentParser(add_help=False)
    summary.add_argument("--summary", metavar="FILE", help="also write the command's summary as JSON to FILE")
    return cluster, summary


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(prog="vprscale", description=__doc__)
    top.add_argument("--version", action="version", version=_version())
    sub = top.add_subparsers(dest="command", required=True)
    cluster, summary = _shared_flags()

    p = sub.add_parser("synth", parents=[summary],
                       help="write synthetic Deep1B (fvecs, fbin) and FAS100K (npz) files")
    p.add_argument("--out", required=True, help="directory to write into")
    p.add_argument("--deep1b-rows", type=_positive_int, default=1_000_000)
    p.add_argument("--fas-dim", type=_bounded_int(MAX_FAS_DIM, "the real FAS100K has 4,096"), default=4096,
                   help="FAS descriptor width (real: 4096)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--rows-per-file", type=_positive_int, default=None,
                   help="split the fvecs output into base_NN files of this many rows")
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser("build", parents=[cluster, summary],
                       help="build a localisation dataset (docs/dataset.md) into <out>/<scale>.zarr")
    p.add_argument("--scale", help="20K, 1M, 10M, 100M, 1B or a recipe .toml")
    own = p.add_argument_group("your own descriptors (docs/bring-your-own.md), instead of --scale")
    own.add_argument("--ref", help="reference rows: .npy, .fbin or fvecs")
    own.add_argument("--query", action="append", default=[], metavar="NAME=PATH",
                     help="a query set (rows aligned with the other sets'), evaluated as --noise NAME; repeatable")
    own.add_argument("--gt", help=".npy of int, one per query row: its reference row, −1 for no truth")
    own.add_argument("--part", help=".npy of 0/1 per query row (0s first): two parts reported apart (optional)")
    own.add_argument("--name", help="the store's name, <out>/<name>.zarr (default: the --ref file's stem)")
    own.add_argument("--stride", type=_positive_int, default=1,
                     help="the evaluation's default query stride z (default 1: every centre)")
    p.add_argument("--deep1b", help="fvecs file, directory of fvecs chunks, or .fbin (default: synthetic)")
    p.add_argument("--fas", help="FAS100K .npz (default: synthetic)")
    p.add_argument("--out", default="data", help="output directory (default: data)")
    p.add_argument("--fas-dim", type=_bounded_int(MAX_FAS_DIM, "the real FAS100K has 4,096"), default=4096,
                   help="width of the synthetic FAS descriptors when --fas is not given")
    p.add_argument("--dry-run", action="store_true", help="print what would be read, written and needed")
    p.add_argument("--force", action="store_true", help="rebuild a complete store (replaced only when done)")
    p.add_argument("--no-rescale", dest="rescale", action="store_false",
                   help="skip the variance rescaling of Deep1B (ablation of Fig. 4d; writes <scale>-norescale.zarr)")
    p.add_argument("--layout", choices=["full", "compact"], default=None,
                   help="full: every row of every array; compact: only what the index and the evaluation read "
                        "(default: the recipe's; compact at 100M and 1B)")
    p.set_defaults(func=cmd_build)

    p = sub.add_parser("index", parents=[cluster, summary],
                       help="fit CoarseHash on a dataset store and write its inverted lists")
    p.add_argument("store", nargs="?", help="a complete <scale>.zarr dataset store")
    p.add_argument("--upgrade", metavar="INDEX",
                   help="convert an index of an older format (2) in place, without refitting")
    p.add_argument("--d", type=_positive_int, default=None, help="hash digits (default ⌈log2 N_ref⌉)")
    p.add_argument("--k", type=int, default=2, help="levels per component (default 2)")
    p.add_argument("--force", action="store_true",
                   help="re-index even if the index holds evaluations (they are kept in <index>.previous-eval/)")
    p.add_argument("--out", help="index directory (default: beside the store, <scale>-d<d>-k<K>.index)")
    p.set_defaults(func=cmd_index)

    p = sub.add_parser("encode", parents=[cluster, summary],
                       help="encode a store's references with FAISS methods, beside it, for eval --compare "
                            "(resumable; needed at 100M and 1B)")
    p.add_argument("store", help="a complete <scale>.zarr dataset store (full or compact)")
    p.add_argument("--compare", action="append", metavar="FACTORY", required=True,
                   help="a FAISS index_factory string (repeat for several)")
    p.add_argument("--deep1b", metavar="PATH", help="a compact store built from files: its Deep1B file")
    p.add_argument("--fas", metavar="PATH", help="a compact store built from files: its FAS file")
    p.add_argument("--force", action="store_true", help="encode again (the old encoding replaced once done)")
    p.set_defaults(func=cmd_encode)

    p = sub.add_parser("eval", parents=[cluster, summary],
                       help="localise query sequences and evaluate the grid of docs/protocol.md")
    p.add_argument("store", help="a complete <scale>.zarr dataset store")
    p.add_argument("index", nargs="?", help="an index of that store (or use --d to index several widths)")
    p.add_argument("--noise", type=_csv(str), default=None,
                   help="the store's query sets to evaluate, e.g. qm1,qm2 (default: every one it holds)")
    p.add_argument("--L", type=_csv(int), default=[1, 50, 100], help="sequence lengths, e.g. 1,50,100")
    p.add_argument("--modes", type=_csv(str), default=["paper", "aligned"], help="paper,aligned")
    p.add_argument("--baseline", action=argparse.BooleanOptionalAction, default=True,
                   help="also run the baseline of docs/method.md (default on)")
    p.add_argument("--z", type=_positive_int, default=None, help="query stride (default: the recipe's)")
    p.add_argument("--baseline-queries", type=_positive_int, default=None,
                   help="localise an evenly spaced sample of this many centres per baseline run (default: all "
                        "below 10^8 query rows, 64 beyond: each baseline query scans every place)")
    p.add_argument("--d", type=_csv(int), default=None, help="index widths to sweep, e.g. 12,14,16,18,20")
    p.add_argument("--compare", metavar="FACTORY", action="append", default=[],
                   help="also evaluate a FAISS index_factory string as method faiss:FACTORY, e.g. PQ3, OPQ3,PQ3, "
                        "ITQ24,LSH, IVF4096,PQ3 (repeat for several; docs/protocol.md)")
    p.add_argument("--faiss-k", type=_csv(int), default=None,
                   help="references each query frame retrieves from a FAISS index, e.g. 4,16,64: one operating "
                        "point each (default: CoarseHash's mean list size on INDEX, the same candidate budget)")
    p.add_argument("--faiss-nprobe", type=_csv(int), default=[16],
                   help="inverted lists an IVF index visits per frame, e.g. 1,8,64: one operating point each, "
                        "with every --faiss-k (default 16)")
    p.add_argument("--method", metavar="CLASS", action="append", default=[], dest="methods",
                   help="also evaluate your own method: package.module:Class of the contract in "
                        "docs/bring-your-own.md, or an installed method's name (repeat for several)")
    p.add_argument("--method-k", type=_csv(int), default=None,
                   help="references each query frame retrieves from a --method, e.g. 4,16,64: one operating point "
                        "each (default: CoarseHash's mean list size on INDEX)")
    p.add_argument("--compare-queries", type=_positive_int, default=None,
                   help="centres per compared (FAISS or --method) run (default: flat FAISS codes: all while the "
                        "run's frames visit at most 2^35 codes, beyond, an evenly spaced sample that fits, at least "
                        "1,000; IVF codes and --method: all)")
    p.add_argument("--flat-noise", type=_csv(str), default=None,
                   help="noise levels flat (exhaustive-scan) FAISS codes run on, e.g. qm1 (default: every --noise): "
                        "at least 1,000 centres of L frames each scan every code, about 20 minutes per flat code and "
                        "noise level at 10M on 2 cores")
    p.add_argument("--deep1b", metavar="PATH", help="a compact store built from files: its Deep1B file (--compare "
                   "and --method recompute the references from the sources; not needed for synthetic stores)")
    p.add_argument("--fas", metavar="PATH", help="a compact store built from files: its FAS file (as --deep1b)")
    p.add_argument("--force", action="store_true",
                   help="replace an evaluation already in the output; the old one is kept beside, as <out>.previous")
    p.add_argument("--repeats", type=_positive_int, default=3,
                   help="timing repeats of every timed kernel, on one thread (default 3; docs/accounting.md)")
    p.add_argument("--out", help="output directory (default: INDEX/eval)")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("report", parents=[summary],
                       help="figures and report.md from evaluation results")
    p.add_argument("results", nargs="+", help="eval output directories (or results.parquet files)")
    p.add_argument("--out", required=True, help="report directory, e.g. reports/<name>")
    p.add_argument("--index", action="append", default=[], help="an extra index (e.g. the no-rescale ablation)")
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("results", help="any number of evaluations as one table (filter with --where SQL)")
    p.add_argument("paths", nargs="+", help="evaluation folders (INDEX/eval, eval --out) or indexes")
    p.add_argument("--where", help="an SQL condition on the columns, e.g. \"method = 'coarsehash' AND radius = 20\"")
    p.add_argument("--queries", action="store_true", help="the per-query rows instead of the recall table")
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--csv", dest="format", action="store_const", const="csv", default="table")
    fmt.add_argument("--json", dest="format", action="store_const", const="json")
    p.add_argument("--timeout", type=_positive_float, default=30.0, help="seconds the --where query may run")
    p.add_argument("--memory-limit", default="2GB", help="memory cap of the --where query (default 2GB)")
    p.set_defaults(func=cmd_results)

    p = sub.add_parser("methods", help="the evaluated methods' registry: built-in and installed (entry points)")
    p.set_defaults(func=cmd_methods)

    p = sub.add_parser("verify", help="check a store, index or evaluation against its manifest (sizes and checksums)")
    p.add_argument("path", help="a dataset store, an index or an evaluation folder")
    p.set_defaults(func=cmd_verify)

    p = sub.add_parser("run", help="run a pipeline (pipelines/*.toml), skipping stages that are up to date")
    p.add_argument("pipeline", help="a pipeline TOML file")
    p.add_argument("--scheduler", metavar="ADDRESS", help="address of a Dask distributed scheduler")
    p.add_argument("--force", action="store_true", help="re-run every stage, even those up to date")
    p.add_argument("--dry-run", action="store_true",
                   help="list every stage with run or skip and the reason (which parameter, input, module or output)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("bench", help="benchmark a build, an index, look-ups or an evaluation (prints figures)")
    p.add_argument("job", choices=["build", "index", "lookup", "eval", "online", "format", "codes"])
    p.add_argument("target", help="build: a scale; index/eval/online/format/codes: a store; lookup: an index")
    p.add_argument("--out", default="data/bench", help="build: output directory")
    p.add_argument("--deep1b")
    p.add_argument("--fas")
    p.add_argument("--d", type=_positive_int)
    p.add_argument("--index", help="eval, online, format: the index to evaluate")
    p.add_argument("--L", type=_positive_int, default=100, help="online, codes: sequence length (default 100)")
    p.add_argument("--compare", action="append", metavar="FACTORY",
                   help="codes: a FAISS index_factory string (repeat; default PQ3, OPQ3,PQ3, IVF1024,PQ3)")
    p.add_argument("--places", type=_positive_int, help="codes: references encoded (default: all of the store's)")
    p.add_argument("--workers", type=_positive_int, default=os.cpu_count() or 1)
    p.add_argument("--eval-args", default="", help='eval: further eval options, e.g. "--L 100 --modes paper"')
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("sql", help="read-only SQL over an index and evaluations (views lists, buckets, model, "
                                   "results, queries)")
    p.add_argument("paths", nargs="+", metavar="PATH [QUERY]",
                   help="an index directory and/or evaluation folders (viewed together, with a run column), then "
                        "one SELECT statement; without it, an interactive shell")
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--csv", dest="format", action="store_const", const="csv")
    fmt.add_argument("--json", dest="format", action="store_const", const="json")
    p.add_argument("--timeout", type=_positive_float, default=30.0,
                   help="seconds before a query is stopped (default 30)")
    p.add_argument("--memory-limit", default="2GB", help="DuckDB's memory cap (default 2GB)")
    p.add_argument("--threads", type=_bounded_int(MAX_SQL_THREADS, "DuckDB starts every thread it is given"),
                   default=2, help="DuckDB's threads (default 2)")
    p.set_defaults(func=cmd_sql, format="table")

    p = sub.add_parser("localise", parents=[summary],
                       help="match a traverse frame by frame (online) and write one row per frame")
    p.add_argument("index", help="an index directory")
    p.add_argument("queries", help="query frames in order: STORE.zarr/<array>, an .npy, fvecs or .fbin file")
    p.add_argument("--L", type=_positive_int, default=100, help="sequence length (default 100)")
    p.add_argument("--mode", choices=["paper", "aligned"], default="paper", help="candidate mode (default paper)")
    p.add_argument("--out", help="Parquet file of (frame, centre, match, n_r), one row per frame")
    p.set_defaults(func=cmd_localise)

    p = sub.add_parser("occupancy", help="bucket sizes, occupied share of K^d and per-component balance")
    p.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    p.add_argument("index", help="an index directory")
    p.add_argument("--top", type=_positive_int, default=10, help="how many of the largest buckets to list")
    p.set_defaults(func=cmd_occupancy)
    return top


def _version() -> str:
    from vprscale import __version__

    return f"vprscale {__version__}"


def _disk_full(exc: OSError, args: argparse.Namespace) -> bool:
    """Whether an I/O error is a full disk: ENOSPC/EDQUOT, or (numpy's short writes carry no errno)
    the output's filesystem has less than a mebibyte left."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    out = getattr(args, "out", None)
    if not out:
        return False
    path = Path(out).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free < 1 << 20


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser().parse_args(argv)
    set_command(["vprscale", *argv])
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        _check_outputs(args)
        return func(args)
    except InputError as exc:
        print(f"vprscale {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except JobFailed as exc:
        print(f"vprscale {args.command}: failed: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    except OSError as exc:
        if not _disk_full(exc, args):
            raise
        # Outputs are published whole, so nothing half-written is visible; checkpoints stay for the re-run.
        where = f" writing {exc.filename}" if exc.filename else ""
        print(f"vprscale {args.command}: error: the disk is full{where}; free space and run the same command "
              "again (finished work is kept and resumed)", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
