"""``vprscale report``: draws the figures and writes report.md from evaluation results."""

from __future__ import annotations

import argparse

from vprscale.cli.common import local_output, write_summary
from vprscale.core.objects import location

INPUTS = ('results', 'index', 'stages')  # the flags naming what it reads: no output may be written over them


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("report", parents=[summary],
                       help="figures and report.md from evaluation results")
    p.add_argument("results", nargs="+", help="eval output directories (or results.parquet files)")
    p.add_argument("--out", required=True, help="report directory, e.g. reports/<name>")
    p.add_argument("--index", action="append", default=[], help="an extra index (e.g. the no-rescale ablation)")
    p.add_argument("--force", action="store_true",
                   help="replace a report already in --out; the old one is kept beside, as <out>.previous")
    p.add_argument("--stages", metavar="FILE",
                   help="the stage record of the pipeline the results come from (vprscale run gives its report "
                   "stage one): the report states each stage's code and its time, and keeps it as stages.json")
    p.set_defaults(func=run, input_flags=INPUTS, out_is_dir=True)


def run(args: argparse.Namespace) -> int:
    from vprscale.evaluation.report import write_report

    rep = write_report([str(local_output(p)) for p in args.results], location(args.out),
                       extra_indexes=[str(local_output(p)) for p in args.index], force=args.force,
                       stages=args.stages)
    print(f"wrote {rep['report']} and {len(rep['figures'])} figure files")
    write_summary(args, rep)
    return 0
