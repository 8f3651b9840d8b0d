"""``vprscale run``: runs a pipeline, skipping the stages that are up to date."""

from __future__ import annotations

import argparse


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("run", help="run a pipeline (pipelines/*.toml), skipping stages that are up to date")
    p.add_argument("pipeline", help="a pipeline TOML file, or the name of a shipped one (quickstart, paper)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="address of a Dask distributed scheduler")
    p.add_argument("--force", action="store_true", help="re-run every stage, even those up to date")
    p.add_argument("--dry-run", action="store_true",
                   help="list every stage with run or skip and the reason (which parameter, input, module or output)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
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
