"""``vprscale synth``: writes synthetic Deep1B and FAS100K source files (the embedded default's inputs)."""

from __future__ import annotations

import argparse
from pathlib import Path

from vprscale.cli.common import MAX_FAS_DIM, bounded_int, positive_int, write_summary


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("synth", parents=[summary],
                       help="write synthetic Deep1B (fvecs, fbin) and FAS100K (npz) files")
    p.add_argument("--out", required=True, help="directory to write into")
    p.add_argument("--deep1b-rows", type=positive_int, default=1_000_000, help="rows of the Deep1B-like files")
    p.add_argument("--fas-dim", type=bounded_int(MAX_FAS_DIM, "the real FAS100K has 4,096"), default=4096,
                   help="FAS descriptor width (real: 4096)")
    p.add_argument("--seed", type=int, default=0, help="the generator's seed: the same seed writes the same bytes")
    p.add_argument("--rows-per-file", type=positive_int, default=None,
                   help="split the fvecs output into base_NN files of this many rows")
    p.add_argument("--force", action="store_true",
                   help="write where Deep1B/… or FAS/… files already are in --out (refused without it): synth's "
                        "own earlier files are replaced, any other is kept beside as <name>.previous")
    msls = p.add_argument_group("a synthetic MSLS tree (docs/bring-your-own.md, \"MSLS\"), instead of Deep1B and FAS")
    msls.add_argument("--msls", action="store_true",
                      help="write MSLS's layout (train_val/<city>/{database,query}/*.csv) with descriptors.npy and "
                           "keys.txt, for build --msls OUT --descriptors OUT/descriptors.npy --keys OUT/keys.txt")
    msls.add_argument("--frames", type=positive_int, default=20_000,
                      help="database images over all cities (default 20,000)")
    msls.add_argument("--cities", default="cph,sf", help="city names, comma-separated (default: cph,sf)")
    msls.add_argument("--dim", type=positive_int, default=64, help="descriptor width (default 64)")
    p.set_defaults(func=run, out_is_dir=True)


def run(args: argparse.Namespace) -> int:
    from vprscale.dataset.synth import write_synthetic

    if args.msls:
        return _msls(args)

    paths = write_synthetic(Path(args.out), args.deep1b_rows, args.fas_dim, args.seed,
                            rows_per_file=args.rows_per_file, force=args.force)
    for p in paths:
        print(p)
    write_summary(args, {"dir": args.out, "fvecs": str(paths[0].parent), "fbin": str(paths[-2]),
                          "fas": str(paths[-1])})
    return 0


def _msls(args: argparse.Namespace) -> int:
    from vprscale.dataset.msls import parse_cities
    from vprscale.dataset.synthmsls import MslsSynth, write_msls

    paths = write_msls(MslsSynth(Path(args.out), args.frames, parse_cities(args.cities), args.dim, seed=args.seed))
    print(f"wrote {len(paths)} files under {args.out}: build it with\n  vprscale build --msls {args.out} --cities "
          f"{args.cities} --descriptors {paths[0]} --keys {paths[1]}")
    write_summary(args, {"dir": args.out, "descriptors": str(paths[0]), "keys": str(paths[1])})
    return 0
