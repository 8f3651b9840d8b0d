"""``vprscale build``: builds a localisation dataset store from a recipe (docs/dataset.md) or your own descriptors."""

from __future__ import annotations

import argparse
from pathlib import Path

from vprscale.cli.common import MAX_FAS_DIM, bounded_int, positive_float, positive_int, write_summary
from vprscale.core.errors import InputError

# what it reads: no output may be written over them
INPUTS = ('deep1b', 'base', 'fas', 'scale', 'ref', 'query', 'gt', 'part', 'ref_pos', 'query_pos', 'ref_seq',
          'query_seq', 'msls', 'descriptors', 'keys')


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("build", parents=[cluster, summary],
                       help="build a localisation dataset (docs/dataset.md) into <out>/<scale>.zarr")
    p.add_argument("--scale", help="20K, 1M, 10M, 100M, 1B or a recipe .toml (no default: give a scale, or --ref, "
                                   "--query and --gt for your own descriptors)")
    own = p.add_argument_group("your own descriptors (docs/bring-your-own.md), instead of --scale")
    own.add_argument("--ref", help="reference rows: .npy (or a folder of .npy shards), .fbin, .f16bin, .u8bin, "
                                   ".i8bin, fvecs, bvecs, FILE.hdf5:DATASET or FILE.parquet:COLUMN (or a folder of "
                                   "Parquet files); the bin and vecs forms also by URL")
    own.add_argument("--query", action="append", default=[], metavar="NAME=PATH",
                     help="a query set, evaluated as --noise NAME; repeatable. Sets sharing one --gt are the same "
                          "traverse row for row; sets of any lengths give each label flag once per set, NAME=PATH")
    own.add_argument("--gt", action="append", default=None, metavar="[NAME=]PATH",
                     help=".npy of int, one per query row: its reference row, −1 for no truth (or the "
                          "first neighbour of an .ibin or .ivecs ground truth; with "
                          "--ref-pos and --query-pos: optional, the nearest reference by position)"),
    own.add_argument("--gt-radius-m", type=positive_float, default=25.0, metavar="R",
                     help="without --gt: a query row's truth is its nearest reference within R metres, else none "
                          "(default 25, VPR-methods-evaluation's positives)")
    own.add_argument("--part", action="append", default=None, metavar="[NAME=]PATH",
                     help=".npy of 0/1 per query row (0s first): two parts reported apart (optional)")
    own.add_argument("--ref-pos", metavar="PATH",
                     help="positions of the references in metres, for eval --radius-m: an .npy of (east, north) or "
                          "(x, y, z) per row, or a text file of image names with @UTM_east@UTM_north@ (optional)")
    own.add_argument("--query-pos", action="append", default=None, metavar="[NAME=]PATH",
                     help="positions of the query rows, as --ref-pos (with it)")
    own.add_argument("--ref-seq", metavar="PATH",
                     help="many sequences: each reference row's sequence and frame number, a CSV or Parquet table "
                          "with sequence_key and frame_number columns (MSLS's seq_info.csv) or an .npy of 2 integer "
                          "columns; a window never crosses a sequence's end or a gap in its frame numbers (optional)")
    own.add_argument("--query-seq", action="append", default=None, metavar="[NAME=]PATH",
                     help="the query rows' sequences, as --ref-seq (with it)")
    own.add_argument("--name", help="the store's name, <out>/<name>.zarr (default: the --ref file's stem)")
    own.add_argument("--stride", type=positive_int, default=1,
                     help="the evaluation's default query stride z (default 1: every centre)")
    msls = p.add_argument_group("MSLS as it is laid out (docs/bring-your-own.md), instead of --scale")
    msls.add_argument("--msls", metavar="ROOT", help="MSLS's root folder (train_val/<city>/{database,query}/ with "
                                                   "seq_info.csv, postprocessed.csv, raw.csv, subtask_index.csv)")
    msls.add_argument("--cities", help="the cities to store, comma-separated (e.g. cph,sf, MSLS's validation set)")
    msls.add_argument("--descriptors", metavar="FILE",
                      help="your descriptors of every image of those cities: a Parquet file with a key column and "
                           "a descriptor column (FILE.parquet[:COLUMN]), or any --ref form with --keys")
    msls.add_argument("--keys", metavar="FILE", help="a text file of the --descriptors rows' image keys, one a line")
    p.add_argument("--base", metavar="[CORPUS:]PATH",
                   help="the recipe's large corpus, by path or URL, in any form --ref takes (.fbin, .u8bin, .i8bin, "
                        ".f16bin, fvecs, bvecs, .npy or shards, FILE.hdf5:DATASET, FILE.parquet:COLUMN); CORPUS "
                        "(deep1b, bigann, text2image, turing, spacev) checks its published width; rows wider than 96 "
                        "are projected by the recipe's PCA (default: synthetic Deep1B; docs/dataset.md)")
    p.add_argument("--deep1b", help="Deep1B as the corpus: --base deep1b:PATH (fvecs file, directory of fvecs "
                                    "chunks, or .fbin)")
    p.add_argument("--fas", help="FAS100K .npz (default: synthetic)")
    p.add_argument("--out", default="data", help="output directory (default: data)")
    p.add_argument("--fas-dim", type=bounded_int(MAX_FAS_DIM, "the real FAS100K has 4,096"), default=4096,
                   help="width of the synthetic FAS descriptors when --fas is not given")
    p.add_argument("--dry-run", action="store_true", help="print what would be read, written and needed")
    p.add_argument("--force", action="store_true", help="rebuild a complete store (replaced only when done)")
    p.add_argument("--no-rescale", dest="rescale", action="store_false",
                   help="skip the variance rescaling of Deep1B (ablation of Fig. 4d; writes <scale>-norescale.zarr)")
    p.add_argument("--shard-chunks", type=positive_int, default=None, metavar="N",
                   help="store N chunks per zarr shard (one object each on object storage, written whole by one "
                        "task); default: the recipe's, 1 (unsharded) unless it says otherwise (docs/storage.md)")
    p.add_argument("--layout", choices=["full", "compact"], default=None,
                   help="full: every row of every array; compact: only what the index and the evaluation read "
                        "(default: the recipe's; compact at 100M and 1B)")
    p.set_defaults(func=run, input_flags=INPUTS, out_is_dir=True)


def run(args: argparse.Namespace) -> int:
    from vprscale.dataset.build import BuildRequest, build, format_summary
    from vprscale.dataset.corpora import CORPORA, parse_base

    if args.msls or args.cities or args.descriptors or args.keys:
        return _build_msls(args)
    if args.ref or args.query or args.gt or args.ref_pos or args.query_pos or args.ref_seq or args.query_seq:
        return _build_own(args)
    if not args.scale:
        raise InputError("build: give --scale (a recipe), or --ref, --query and --gt (your own descriptors)")
    if args.base and args.deep1b:
        raise InputError("--base and --deep1b: give the corpus once (--deep1b PATH is --base deep1b:PATH)")
    corpus, base = parse_base(args.base) if args.base else (CORPORA["deep1b"] if args.deep1b else None, args.deep1b)
    summary = build(BuildRequest(scale=args.scale, out=args.out, deep1b=base, corpus=corpus, fas=args.fas,
                                 workers=args.workers, scheduler=args.scheduler, dry_run=args.dry_run,
                                 force=args.force, fas_dim=args.fas_dim, rescale=args.rescale,
                                 layout=args.layout, shard_chunks=args.shard_chunks))
    if not summary.get("dry_run") and not summary.get("skipped"):
        print(format_summary(summary))
    write_summary(args, summary)
    return 0


def _build_own(args: argparse.Namespace) -> int:
    from vprscale.dataset.build import format_summary
    from vprscale.dataset.own import OwnRequest, build_own, parse_query

    for flag in ("scale", "deep1b", "base", "fas", "layout"):
        if getattr(args, flag):
            raise InputError(f"--{flag}: a recipe's option; your own descriptors (--ref) are stored as given")
    positions = bool(args.ref_pos and args.query_pos)  # the truth follows from them where --gt is not given
    missing = [f for f, v in (("--ref", args.ref), ("--query", args.query), ("--gt", args.gt or positions)) if not v]
    if missing:
        raise InputError(f"{' and '.join(missing)} missing (your own descriptors need --ref, --query, and "
                         "--gt or --ref-pos with --query-pos)")
    if args.dry_run:
        raise InputError("--dry-run: plans a recipe's build; your own descriptors are copied as they are")
    queries = dict(parse_query(q) for q in args.query)
    if len(queries) != len(args.query):
        raise InputError("--query: a name is given twice")
    labels = {flag: per_set(getattr(args, flag), queries, flag) for flag in ("gt", "part", "query_pos", "query_seq")}
    summary = build_own(OwnRequest(ref=args.ref, queries=queries, gt=labels["gt"], part=labels["part"],
                                   out=Path(args.out),
                                   name=args.name, stride=args.stride, force=args.force, workers=args.workers,
                                   scheduler=args.scheduler, ref_pos=args.ref_pos, query_pos=labels["query_pos"],
                                   ref_seq=args.ref_seq, query_seq=labels["query_seq"], gt_radius_m=args.gt_radius_m))
    print(format_summary(summary))
    write_summary(args, summary)
    return 0


def _build_msls(args: argparse.Namespace) -> int:
    from vprscale.dataset.build import format_summary
    from vprscale.dataset.mslsbuild import MslsRequest, build_msls

    for flag in ("scale", "deep1b", "base", "fas", "layout", "ref", "gt", "part", "ref_pos", "query_pos", "ref_seq",
                 "query_seq", "stride", "dry_run"):
        if getattr(args, flag) not in (None, False, [], 1):
            raise InputError(f"--{flag.replace('_', '-')}: not an option of an MSLS build (--msls, --cities, "
                             "--descriptors, --keys, --name, --gt-radius-m, --out)")
    if args.query:
        raise InputError("--query: not an option of an MSLS build: its query images are the cities' own")
    missing = [f for f, v in (("--msls", args.msls), ("--cities", args.cities), ("--descriptors", args.descriptors))
               if not v]
    if missing:
        raise InputError(f"{' and '.join(missing)} missing (an MSLS build needs --msls ROOT, --cities and "
                         "--descriptors)")
    summary = build_msls(MslsRequest(root=args.msls, cities=args.cities, descriptors=args.descriptors,
                                     keys=args.keys, out=Path(args.out), name=args.name or "msls",
                                     threshold_m=args.gt_radius_m, force=args.force, workers=args.workers,
                                     scheduler=args.scheduler))
    print(format_summary(summary))
    write_summary(args, summary)
    return 0


def per_set(values: list[str] | None, queries: dict[str, str], flag: str) -> str | dict[str, str] | None:
    """A label flag's files: one PATH every query set shares, or NAME=PATH once for each set."""
    if not values:
        return None
    named = [v.partition("=") for v in values]
    if len(values) == 1 and not (named[0][1] and named[0][0] in queries):
        return values[0]
    option = "--" + flag.replace("_", "-")
    found: dict[str, str] = {}
    for name, sep, path in named:
        if not sep or name not in queries:
            raise InputError(f"{option} {name}{sep}{path}: give one PATH for every query set, or NAME=PATH once for "
                             f"each ({', '.join(queries)})")
        if name in found:
            raise InputError(f"{option} {name}=…: given twice")
        found[name] = path
    return found
