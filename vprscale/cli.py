"""The ``vprscale`` command line. User errors print one line and exit with status 2."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

os.environ.setdefault("DASK_ARRAY__QUERY_PLANNING", "False")

from vprscale.errors import InputError  # noqa: E402

EXIT_USAGE = 2


def _positive_int(text: str) -> int:
    try:
        value = int(text.replace("_", "").replace(",", ""))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be positive")
    return value


def cmd_synth(args: argparse.Namespace) -> int:
    from vprscale.synth import write_synthetic

    paths = write_synthetic(Path(args.out), args.deep1b_rows, args.fas_dim, args.seed,
                            rows_per_file=args.rows_per_file)
    for p in paths:
        print(p)
    return 0


def cmd_build(args: argparse.Namespace) -> int:
    from vprscale.build import BuildRequest, build, format_summary

    summary = build(BuildRequest(scale=args.scale, out=Path(args.out), deep1b=args.deep1b, fas=args.fas,
                                 workers=args.workers, scheduler=args.scheduler, dry_run=args.dry_run,
                                 force=args.force, fas_dim=args.fas_dim))
    if not summary.get("dry_run") and not summary.get("skipped"):
        print(format_summary(summary))
    return 0


def _add_cluster(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scheduler", metavar="ADDRESS", help="address of a Dask distributed scheduler "
                   "(tcp://host:8786); default: a local in-process cluster")
    p.add_argument("--workers", type=_positive_int, default=os.cpu_count() or 1,
                   help="threads of the local cluster (default: all cores)")


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(prog="vprscale", description=__doc__)
    top.add_argument("--version", action="version", version=_version())
    sub = top.add_subparsers(dest="command", required=True)

    p = sub.add_parser("synth", help="write synthetic Deep1B (fvecs, fbin) and FAS100K (npz) files")
    p.add_argument("--out", required=True, help="directory to write into")
    p.add_argument("--deep1b-rows", type=_positive_int, default=1_000_000)
    p.add_argument("--fas-dim", type=_positive_int, default=4096, help="FAS descriptor width (real: 4096)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--rows-per-file", type=_positive_int, default=None,
                   help="split the fvecs output into base_NN files of this many rows")
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser("build", help="build a localisation dataset (SPEC §2) into <out>/<scale>.zarr")
    p.add_argument("--scale", required=True, help="20K, 1M, 10M, 100M, 1B or a recipe .toml")
    p.add_argument("--deep1b", help="fvecs file, directory of fvecs chunks, or .fbin (default: synthetic)")
    p.add_argument("--fas", help="FAS100K .npz (default: synthetic)")
    p.add_argument("--out", default="data", help="output directory (default: data)")
    p.add_argument("--fas-dim", type=_positive_int, default=4096,
                   help="width of the synthetic FAS descriptors when --fas is not given")
    p.add_argument("--dry-run", action="store_true", help="print what would be read, written and needed")
    p.add_argument("--force", action="store_true", help="rebuild a complete store (replaced only when done)")
    _add_cluster(p)
    p.set_defaults(func=cmd_build)
    return top


def _version() -> str:
    from vprscale import __version__

    return f"vprscale {__version__}"


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except InputError as exc:
        print(f"vprscale {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
