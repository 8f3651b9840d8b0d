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
                   help="list every stage with run or skip and the reason (which parameter, input, module or "
                   "output), each stage's estimated time, peak memory and disk, and the run's")
    p.add_argument("--save-costs", action="store_true",
                   help="after the run, write the stages' measured figures beside the pipeline file "
                   "(PIPELINE.costs.json), which --dry-run reads on a machine that has not run it")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vprscale.jobs.pipeline import run_pipeline

    summary = run_pipeline(args.pipeline, scheduler=args.scheduler, force=args.force, dry_run=args.dry_run,
                           save_costs=args.save_costs)
    if args.dry_run:
        for s in summary["stages"]:
            why = "; ".join(s["reasons"]) if s["run"] else "up to date"
            cost = f" [{_cost(s['estimate'])}]" if s["run"] else ""
            print(f"{'run ' if s['run'] else 'skip'}  {s['name']} ({s['kind']}): {why}{cost}")
        total = summary["estimate"]
        running = sum(1 for s in summary["stages"] if s["run"])
        if running and total["unmeasured"] == running:  # nothing to add up: no figure, not a zero
            print(f"estimated: nothing (none of the {running} stage(s) to run was ever measured here, nor has a "
                  "costs file beside the pipeline: docs/pipelines.md)")
            return 0
        left = (f"; at least that: {total['unmeasured']} of the {running} stage(s) to run never measured, left out"
                if total["unmeasured"] else "")
        print(f"estimated: {_duration(total['seconds'])} of wall time, peak memory {_gb(total['peak_bytes'])}, "
              f"{_gb(total['disk_bytes'])} on disk{left}")
        return 0
    ran = [s["name"] for s in summary["stages"] if s["status"] == "ran"]
    print(f"pipeline {summary['name']}: {summary['status']}; ran {len(ran)} of {len(summary['stages'])} stages "
          f"({', '.join(ran) or 'none: everything was up to date'}); summary {summary['summary_file']}")
    if "costs_file" in summary:
        print(f"stage costs written to {summary['costs_file']} (what --dry-run estimates from on another machine)")
    return 0


def _duration(seconds: float) -> str:
    minutes = seconds / 60
    return f"{minutes:.0f} min" if minutes >= 10 else f"{minutes:.1f} min" if minutes >= 1 else f"{seconds:.0f} s"


def _gb(n: int | None) -> str:
    return "?" if n is None else f"{n / 1e9:.2f} GB" if n < 1e10 else f"{n / 1e9:.0f} GB"


def _cost(e) -> str:
    """One stage's estimate, as a line's tail: its figures and where they come from."""
    if e.seconds is None:
        return "no estimate: never measured"
    return f"{_duration(e.seconds)}, peak {_gb(e.peak_bytes)}, disk {_gb(e.disk_bytes)}; {e.basis}"
