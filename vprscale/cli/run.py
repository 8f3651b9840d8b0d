"""``vprscale run``: runs a pipeline, or part of it, skipping the stages that are up to date."""

from __future__ import annotations

import argparse

from vprscale.core.errors import InputError


def add(sub: argparse._SubParsersAction, cluster: argparse.ArgumentParser,
        summary: argparse.ArgumentParser) -> None:
    p = sub.add_parser("run", help="run a pipeline (pipelines/*.toml), skipping stages that are up to date")
    p.add_argument("pipeline", help="a pipeline TOML file, or the name of a shipped one (quickstart, paper)")
    p.add_argument("stages", nargs="*", metavar="STAGE",
                   help="run only these stages (and, where out of date, the stages they read from)")
    p.add_argument("--part", metavar="PART",
                   help="run one of the pipeline's parts ([[parts]]: a group of stages that fits one job, from "
                        "nothing); --dry-run lists every part with its estimate")
    p.add_argument("--downstream", action="store_true",
                   help="with STAGE names: also every stage that reads from them, directly or not")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="STAGE.KEY=VALUE",
                   help="override a stage's parameter for this run (VALUE in TOML: 7, [1,50], false, or a word); "
                   "part of the stage's fingerprint, so it re-runs with it and again without it")
    p.add_argument("--budget", metavar="DURATION",
                   help="wall-clock limit (2h, 90m, 1h30m, 3600): run stages while it lasts; a build or an encoding "
                   "stops at a checkpoint inside it; exit status 75 when stages are left (run it again to continue)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="address of a Dask distributed scheduler")
    p.add_argument("--force", action="store_true", help="re-run every stage asked for, even those up to date")
    p.add_argument("--dry-run", action="store_true",
                   help="list every stage with run or skip and the reason (which parameter, input, module or "
                   "output), each stage's estimated time, peak memory and disk, and the run's; with --budget, "
                   "the call that runs each stage")
    p.add_argument("--dag", nargs="?", const="mermaid", choices=("mermaid", "dot"),
                   help="print the stage graph with each stage's state (done, stale and why, pending) as Mermaid "
                   "(the default) or Graphviz dot, and run nothing")
    p.add_argument("--save-costs", action="store_true",
                   help="after the run, write the stages' measured figures beside the pipeline file "
                   "(PIPELINE.costs.json), which --dry-run reads on a machine that has not run it")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vprscale.core.deadline import EXIT_MORE
    from vprscale.jobs.budget import parse_duration
    from vprscale.jobs.pipeline import left_words, run_pipeline, stage_graph

    if args.downstream and not args.stages:
        raise InputError("--downstream needs STAGE names (without them every stage runs)")
    budget = None if args.budget is None else parse_duration(args.budget)
    if args.dag:
        print(stage_graph(args.pipeline, args.dag, args.settings, args.stages, args.downstream, args.force), end="")
        return 0
    summary = run_pipeline(args.pipeline, scheduler=args.scheduler, force=args.force, dry_run=args.dry_run,
                           save_costs=args.save_costs, stages=args.stages, downstream=args.downstream,
                           settings=args.settings, budget=budget, part=args.part)
    if args.dry_run:
        return _plan(summary, args.budget)
    ran = [s["name"] for s in summary["stages"] if s["status"] == "ran"]
    print(f"pipeline {summary['name']}: {summary['status']}; ran {len(ran)} of {summary['covered']} stages "
          f"({', '.join(ran) or 'none: everything was up to date'}); summary {summary['summary_file']}")
    if "costs_file" in summary:
        print(f"stage costs written to {summary['costs_file']} (what --dry-run estimates from on another machine)")
    if "left" in summary:
        left = summary["left"]
        print(f"more to do: {len(left)} stage(s) left ({', '.join(s['name'] for s in left)}), "
              f"{left_words(summary['left_s'], summary['left_unmeasured'])}; run the same command to continue")
        return EXIT_MORE
    return 0


def _plan(summary: dict, budget: str | None) -> int:
    import psutil

    memory = psutil.virtual_memory().total
    for s in summary["stages"]:
        why = "; ".join(s["reasons"]) if s["run"] else "up to date"
        cost = f" [{_cost(s['estimate'])}]" if s["run"] else ""
        when = f" — {s['call']}" if "call" in s else ""
        print(f"{'run ' if s['run'] else 'skip'}  {s['name']} ({s['kind']}): {why}{cost}{when}")
        peak = s["estimate"].peak_bytes if s["run"] else None
        if peak is not None and peak > memory:
            print(f"      ! its estimated peak, {_gb(peak)}, is more than this machine's {_gb(memory)} of memory: it "
                  "will start, and the system will likely stop it for memory part way; run it on a machine with "
                  f"at least {_gb(peak)} (the estimate is {s['estimate'].basis})")
    for part in summary.get("parts", []):  # each from nothing: on a fresh machine, within one job
        gap = f", {part['unmeasured']} of its stages never measured, left out" if part["unmeasured"] else ""
        print(f"part {part['name']}: {part['kept']}; {len(part['stages'])} stages, from nothing "
              f"{_duration(part['seconds'])} of wall time, peak memory {_gb(part['peak_bytes'])}{gap} "
              f"(vprscale run {summary['name']} --part {part['name']})")
    total = summary["estimate"]
    running = [s for s in summary["stages"] if s["run"]]
    if running and total["unmeasured"] == len(running):  # nothing to add up: no figure, not a zero
        print(f"estimated: nothing (none of the {len(running)} stage(s) to run was ever measured here, nor is in a "
              "costs file beside the pipeline: docs/pipelines.md)")
        return 0
    left = (f"; at least that: {total['unmeasured']} of the {len(running)} stage(s) to run never measured, left out"
            if total["unmeasured"] else "")
    print(f"estimated: {_duration(total['seconds'])} of wall time, peak memory {_gb(total['peak_bytes'])}, "
          f"{_gb(total['disk_bytes'])} on disk{left}")
    if budget and running:
        calls = max(s["calls"] for s in running)
        print(f"--budget {budget}: {calls} call(s) of vprscale run; a build or an encoding stops at a checkpoint "
              "and continues in the next call, other stages start only where their estimate fits")
    return 0


def _duration(seconds: float) -> str:
    minutes = seconds / 60
    if minutes >= 90:
        return f"{minutes / 60:.1f} h"
    return f"{minutes:.0f} min" if minutes >= 10 else f"{minutes:.1f} min" if minutes >= 1 else f"{seconds:.0f} s"


def _gb(n: int | None) -> str:
    return "?" if n is None else f"{n / 1e9:.2f} GB" if n < 1e10 else f"{n / 1e9:.0f} GB"


def _cost(e) -> str:
    """One stage's estimate, as a line's tail: its figures and where they come from."""
    if e.seconds is None:
        return "no estimate: never measured"
    return f"{_duration(e.seconds)}, peak {_gb(e.peak_bytes)}, disk {_gb(e.disk_bytes)}; {e.basis}"
