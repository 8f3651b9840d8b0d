"""``vprscale run``: batch pipelines of stages (synth, build, index, eval, report) from TOML.

A pipeline file names an output directory and an ordered list of stages. A stage re-runs
when its kind or parameters, what it reads (a build's recipe file and source files), a
stage it reads from, the code its job runs (the modules it imports, not the whole
package) or its outputs (missing, or changed since it wrote them) changed; otherwise it is
skipped, so re-running a finished pipeline does no work, and a change to the report code
re-runs the report, not the builds. ``vprscale run --dry-run`` says, stage by stage, what
would run and why. Every run writes a
JSON summary (times, peak memory, bytes on disk per stage) and a log under
``<out>/runs/``; two runs on the same output directory never overlap.

A run may cover some stages (:func:`select`: named ones, what they read, with ``downstream``
what reads them), override parameters (:func:`override`) and keep to a wall-clock budget
(:mod:`vprscale.jobs.budget`): a stage that checkpoints is stopped inside at a checkpoint, its
time so far kept in the state, and the next call resumes it. :func:`stage_graph` draws the plan.

Relative paths are taken from the current directory (run pipelines from the repository root).
"""

from __future__ import annotations

import hashlib
import importlib.machinery
import io
import json
import logging
import os
import re
import shlex
import signal
import subprocess
import sys
import time
import tomllib
import traceback
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import vprscale
from vprscale.core import deadline
from vprscale.core.deadline import BudgetSpent
from vprscale.core.digests import DigestCache
from vprscale.core.errors import InputError, JobFailed
from vprscale.core.manifest import check_manifest, read_manifest
from vprscale.core.objects import cache_root, redact
from vprscale.core.provenance import provenance
from vprscale.core.publish import check_writable, exclusive
from vprscale.dataset.recipe import load_recipe, read_toml, shipped
from vprscale.evaluation import stagerecord
from vprscale.evaluation.algorithms.registry import BUILTIN
from vprscale.jobs import budget as budget_rules
from vprscale.jobs import buildstages, estimates, stagegraph
from vprscale.jobs.child import vprscale_argv
from vprscale.jobs.parts import keep_part, kept_root, kept_stages, reproduction_lines

STAGE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")  # a stage's name is a file name under out: no '/' or '..'
MAX_STAGE_NAME = 100
STOPPED = ".stopped"  # in the state: stages a budget stopped at a checkpoint (time spent, peak), by name (no
# stage's name starts with a dot)
DIGESTS = ".input-digests.json"  # under out: the content digests of the pipeline's input and output files
# Parameter schema per stage kind: name → (type, required). Types: "str", "int", "bool",
# "list[int]", "list[str]", "stage" (the name of an earlier stage), "list[stage]".
SCHEMA: dict[str, dict[str, tuple[str, bool]]] = {
    "synth": {"deep1b_rows": ("int", True), "fas_dim": ("int", False), "seed": ("int", False)},
    "build": buildstages.KEYS,  # a recipe's, your own descriptors' or MSLS's (one form a stage)
    "index": {"store": ("stage", True), "d": ("int", False), "k": ("int", False)},
    "encode": {"store": ("stage", True), "compare": ("list[str]", True)},
    "eval": {"store": ("stage", True), "index": ("stage", False), "encodings": ("list[stage]", False),
             "d_sweep": ("list[int]", False),
             "noise": ("list[str]", False), "L": ("list[int]", False), "modes": ("list[str]", False),
             "baseline": ("bool", False), "z": ("int", False), "compare": ("list[str]", False),
             "faiss_k": ("list[int]", False), "faiss_nprobe": ("list[int]", False), "compare_queries": ("int", False),
             "flat_noise": ("list[str]", False), "radius_m": ("list[float]", False),
             "methods": ("list[str]", False), "method_k": ("list[int]", False), "repeats": ("int", False),
             "nn": ("bool", False), "nn_queries": ("int", False),
             "task": ("str", False), "seq_length": ("int", False), "subtask": ("str", False),
             "threshold": ("float", False)},
    "report": {"results": ("list[stage]", True), "indexes": ("list[stage]", False), "out": ("str", True)},
}
PRODUCERS = {"source": {"synth"}, "store": {"build"}, "index": {"index"}, "results": {"eval"},
             "indexes": {"index"}, "encodings": {"encode"}}


@dataclass
class Stage:
    name: str
    kind: str
    params: dict[str, Any]


@dataclass
class Part:
    """A group of a pipeline's stages that runs on its own, from nothing: every stage it reads
    from is in it (a ladder too long for one machine's time limit runs as its parts)."""

    name: str
    stages: list[str]


@dataclass
class Pipeline:
    path: Path
    name: str
    out: Path
    workers: int
    stages: list[Stage] = field(default_factory=list)
    parts: list[Part] = field(default_factory=list)

    def part(self, name: str) -> Part:
        """The part named ``name`` (one line naming the known ones if there is none)."""
        found = next((p for p in self.parts if p.name == name), None)
        if found is None:
            known = ", ".join(p.name for p in self.parts) or "none: it declares no [[parts]]"
            raise InputError(f"--part {name}: {self.path} has no such part (parts: {known})")
        return found


def _type_ok(value: Any, kind: str) -> bool:
    if kind in ("str", "stage"):
        return isinstance(value, str)
    if kind == "int":
        return isinstance(value, int) and not isinstance(value, bool)
    if kind == "bool":
        return isinstance(value, bool)
    if kind == "float":
        return isinstance(value, int | float) and not isinstance(value, bool)
    inner = kind[5:-1]
    return isinstance(value, list) and all(_type_ok(v, "str" if inner == "stage" else inner) for v in value)


_TYPE_WORDS = {"str": "a string", "stage": "the name of an earlier stage", "int": "an integer", "bool": "true or false",
               "list[int]": "a list of integers", "list[str]": "a list of strings", "list[float]": "a list of numbers",
               "list[stage]": "a list of earlier stage names"}


def pipeline_path(name: str | Path) -> Path:
    """A pipeline file: ``name`` itself when it is a path, else the pipeline shipped with vprscale of
    that name (``quickstart``, ``paper``)."""
    path = Path(name)
    if path.suffix == ".toml" or path.exists():
        return path
    found = shipped("vprscale.pipelines") / f"{name}.toml"
    if not found.is_file():
        known = sorted(p.stem for p in shipped("vprscale.pipelines").glob("*.toml"))
        raise InputError(f"{name}: no such pipeline file, nor a shipped pipeline (shipped: {', '.join(known)})")
    return found


def load_pipeline(path: str | Path) -> Pipeline:
    """Parse and validate a pipeline file (or a shipped pipeline's name); every error names the file,
    the stage and the key."""
    path = pipeline_path(path)
    data = read_toml(path, "pipeline")
    for key in ("name", "out", "stages"):
        if key not in data:
            raise InputError(f"{path}: missing key '{key}'")
    unknown = set(data) - {"name", "out", "stages", "workers", "parts"}
    if unknown:
        raise InputError(f"{path}: unknown key(s) {sorted(unknown)}")
    workers = data.get("workers", 2)
    if not _type_ok(workers, "int") or workers < 1:
        raise InputError(f"{path}: key 'workers' must be a positive integer")
    if not isinstance(data["stages"], list) or not data["stages"]:
        raise InputError(f"{path}: key 'stages' must be a non-empty array of tables ([[stages]])")
    for key in ("name", "out"):
        if not isinstance(data[key], str) or not data[key]:
            raise InputError(f"{path}: key '{key}' must be a non-empty string, got {data[key]!r}")
    pipe = Pipeline(path, data["name"], Path(data["out"]), workers)
    kinds: dict[str, str] = {}
    for i, raw in enumerate(data["stages"]):
        where = f"{path}: stages[{i}]"
        if not isinstance(raw, dict) or "name" not in raw or "kind" not in raw:
            raise InputError(f"{where}: every stage needs the keys 'name' and 'kind'")
        name, kind = raw["name"], raw["kind"]
        if not isinstance(name, str) or not name or not isinstance(kind, str):
            raise InputError(f"{where}: 'name' and 'kind' must be non-empty strings, got {name!r} and {kind!r}")
        if not STAGE_NAME.fullmatch(name) or len(name) > MAX_STAGE_NAME:  # it names files under the pipeline's out
            raise InputError(f"{where}: stage name {name!r} must be letters, digits, '.', '_' or '-', starting "
                             f"with a letter or digit, at most {MAX_STAGE_NAME} characters (it names files)")
        where = f"{path}: stage '{name}'"
        if kind not in SCHEMA:
            raise InputError(f"{where}: unknown stage kind '{kind}' (known: {', '.join(SCHEMA)})")
        if name in kinds:
            raise InputError(f"{where}: the name is used twice")
        params = {k: v for k, v in raw.items() if k not in ("name", "kind")}
        _check_params(where, kind, params, kinds)
        kinds[name] = kind
        pipe.stages.append(Stage(name, kind, params))
    buildstages.check_stores(str(path), [(s.name, s.params) for s in pipe.stages if s.kind == "build"])
    for stage in pipe.stages:  # a report draws MSLS's tasks or the frame grid, not both
        results = stage.params.get("results", []) if stage.kind == "report" else []
        tasks = [r for r in results if "task" in _stage(pipe, r).params]
        grid = [r for r in results if r not in tasks]
        if tasks and grid:
            raise InputError(f"{path}: stage '{stage.name}': key 'results': '{tasks[0]}' evaluates MSLS's task, "
                             f"'{grid[0]}' the frame grid; a report draws one or the other")
    pipe.parts = _parts_of(path, data.get("parts", []), pipe.stages)
    _check_compared(pipe)
    return pipe


def _stage(pipe: Pipeline, name: str) -> Stage:
    return next(s for s in pipe.stages if s.name == name)


def _parts_of(path: Path, raw: Any, stages: list[Stage]) -> list[Part]:
    """The ``[[parts]]`` tables, checked: each a name and the stages it runs, holding every stage
    they read from (a part runs from nothing); no report stage (the report is assembled from
    what the parts keep); every other stage in some part."""
    if not isinstance(raw, list):
        raise InputError(f"{path}: key 'parts' must be an array of tables ([[parts]])")
    by_name = {s.name: s for s in stages}
    parts: list[Part] = []
    for i, table in enumerate(raw):
        where = f"{path}: parts[{i}]"
        if not isinstance(table, dict) or set(table) != {"name", "stages"}:
            raise InputError(f"{where}: a part is a table of 'name' and 'stages'")
        name, names = table["name"], table["stages"]
        if not isinstance(name, str) or not STAGE_NAME.fullmatch(name) or any(p.name == name for p in parts):
            raise InputError(f"{where}: 'name' must be a new name of letters, digits, '.', '_' or '-', got {name!r}")
        if not _type_ok(names, "list[str]") or not names:
            raise InputError(f"{where}: 'stages' must be a non-empty list of stage names")
        for stage in names:
            if stage not in by_name:
                raise InputError(f"{where} ({name}): no stage '{stage}'")
            if by_name[stage].kind == "report":
                raise InputError(f"{where} ({name}): '{stage}' is a report; it is assembled from what the parts keep")
            missing = [r for r in references(by_name[stage]) if r not in names]
            if missing:
                raise InputError(f"{where} ({name}): '{stage}' reads '{missing[0]}', which the part does not run "
                                 "(a part runs from nothing)")
        parts.append(Part(name, [s.name for s in stages if s.name in names]))
    loose = [s.name for s in stages if s.kind != "report" and parts and not any(s.name in p.stages for p in parts)]
    if loose:
        raise InputError(f"{path}: stage '{loose[0]}' is in no part")
    return parts


def _check_compared(pipe: Pipeline) -> None:
    """Every FAISS code a stage compares, buildable for the rows its build makes: a typo in the
    last stage of a ladder is refused now, not hours into the run."""
    from vprscale.compared.faisscodes import FaissCodes
    from vprscale.compared.pooled import is_pooled, parse_pooled

    kinds = {s.name: (s.kind, s.params) for s in pipe.stages}
    for stage in pipe.stages:
        store = kinds.get(stage.params.get("store", ""))
        if not stage.params.get("compare") or store is None or store[0] != "build":
            continue
        if "scale" not in store[1]:
            continue  # your own rows' width is known when they are read: the evaluation checks the codes then
        try:
            dim = load_recipe(store[1]["scale"]).dim
        except InputError:
            continue  # the build stage's own check names its scale
        for spec in stage.params["compare"]:
            try:
                if stage.kind == "encode" and is_pooled(spec):
                    raise InputError(f"--compare {spec}: a pooled sequence descriptor is encoded by its evaluation, "
                                     "not by an encode stage")
                if is_pooled(spec):  # its FAISS code, over pooled rows of the same width
                    FaissCodes(parse_pooled(spec).factory, dim, k=1, windows=False)
                else:
                    FaissCodes(spec, dim, k=1)
            except InputError as exc:
                raise InputError(f"{pipe.path}: stage '{stage.name}': key 'compare': {exc}") from None


def _check_params(where: str, kind: str, params: dict[str, Any], earlier: dict[str, str]) -> None:
    """Every key known to a ``kind`` stage, of its type, required ones present, and stage references
    naming an ``earlier`` stage (name → kind) of a kind that makes what the key reads."""
    schema = SCHEMA[kind]
    for key in params:
        if key not in schema:
            raise InputError(f"{where}: unknown key '{key}' for a {kind} stage (known: {', '.join(schema)})")
    for key, (typ, required) in schema.items():
        if key not in params:
            if required:
                raise InputError(f"{where}: missing key '{key}'")
            continue
        if not _type_ok(params[key], typ):
            raise InputError(f"{where}: key '{key}' must be {_TYPE_WORDS[typ]}, got {params[key]!r}")
        if typ in ("stage", "list[stage]"):
            for ref in params[key] if isinstance(params[key], list) else [params[key]]:
                if earlier.get(ref) not in PRODUCERS[key]:
                    raise InputError(f"{where}: key '{key}' must name an earlier "
                                     f"{' or '.join(sorted(PRODUCERS[key]))} stage, got '{ref}'")
    if kind == "build":
        buildstages.check_build(where, params)
    if kind == "eval":
        _check_task(where, params)


def _check_task(where: str, params: dict[str, Any]) -> None:
    """MSLS's task keys: a known task and subtask, the task's keys only with ``task``, and not the
    frame grid's lengths (a task sets its own)."""
    from vprscale.dataset.msls import SUBTASKS
    from vprscale.evaluation.tasks import TASKS

    if "task" in params and params["task"] not in TASKS:
        raise InputError(f"{where}: key 'task' must be one of {', '.join(TASKS)}, got {params['task']!r}")
    if params.get("subtask", "all") not in SUBTASKS:
        raise InputError(f"{where}: key 'subtask' must be one of {', '.join(SUBTASKS)}, got {params['subtask']!r}")
    if "task" not in params:
        stray = next((k for k in ("seq_length", "subtask", "threshold") if k in params), None)
        if stray:
            raise InputError(f"{where}: key '{stray}' is MSLS's task's; give 'task' too")
    elif "L" in params:
        raise InputError(f"{where}: key 'L': a task sets its own lengths ('seq_length')")


def references(stage: Stage) -> list[str]:
    """The stages ``stage`` reads from (its keys that name stages)."""
    found = []
    for key, value in stage.params.items():
        if SCHEMA[stage.kind][key][0] in ("stage", "list[stage]"):
            found += value if isinstance(value, list) else [value]
    return found


def override(pipe: Pipeline, settings: Sequence[str]) -> None:
    """Apply ``--set STAGE.KEY=VALUE`` (VALUE in TOML: ``7``, ``[1, 50]``, ``false``, ``"x"``; a bare word
    is a string) to the pipeline, checked as the file's own keys are. An override is a parameter like
    any other: it is part of the stage's fingerprint, so the stage re-runs with it, and again without."""
    kinds = {s.name: s.kind for s in pipe.stages}
    for setting in settings:
        target, eq, raw = setting.partition("=")
        name, dot, key = target.rpartition(".")
        if not eq or not dot or not name or not key:
            raise InputError(f"--set {setting!r}: give STAGE.KEY=VALUE, e.g. --set eval-1M.L=[1,50]")
        stage = next((s for s in pipe.stages if s.name == name), None)
        if stage is None:
            raise InputError(f"--set {setting!r}: {pipe.path} has no stage '{name}' (stages: {', '.join(kinds)})")
        try:
            value = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw
        earlier = dict(list(kinds.items())[: pipe.stages.index(stage)])
        _check_params(f"--set {setting!r}: stage '{name}'", stage.kind, {**stage.params, key: value}, earlier)
        stage.params[key] = value


def select(pipe: Pipeline, names: Sequence[str], downstream: bool) -> tuple[list[Stage], set[str]]:
    """The stages a run covers, in the file's order, and those asked for (``--force`` forces those).

    Asked: the named stages (all if none), with ``downstream`` every stage that reads from them,
    directly or not. Covered: those and every stage they read from, which run only if out of
    date, as ``make`` does with a target's prerequisites.
    """
    known = [s.name for s in pipe.stages]
    for name in names:
        if name not in known:
            raise InputError(f"{pipe.path}: no stage '{name}' (stages: {', '.join(known)})")
    if not names:
        return list(pipe.stages), set(known)
    asked = set(names)
    if downstream:
        for stage in pipe.stages:  # a stage reads only from earlier ones: one pass in order closes the set
            if asked & set(references(stage)):
                asked.add(stage.name)
    covered = set(asked)
    for stage in reversed(pipe.stages):
        if stage.name in covered:
            covered |= set(references(stage))
    return [s for s in pipe.stages if s.name in covered], asked


class _Tee(io.TextIOBase):
    def __init__(self, *streams) -> None:
        self.streams = streams

    def write(self, s: str) -> int:
        for st in self.streams:
            st.write(s)
            st.flush()
        return len(s)


@dataclass
class Decision:
    """One stage's plan: run or not and why, its fingerprint, its estimated cost."""

    stage: Stage
    parts: dict[str, Any]
    fingerprint: str
    reasons: list[str]  # empty: up to date
    estimate: estimates.Estimate
    spent: float = 0.0  # seconds that calls stopped by a budget already spent on it (same fingerprint)

    @property
    def run(self) -> bool:
        return bool(self.reasons)

    def state(self) -> tuple[str, str]:
        """``(state, why)``: done (up to date), pending (never finished: no complete run recorded,
        or stopped at a checkpoint) or stale (it finished once and something it depends on changed)."""
        if not self.run:
            return "done", ""
        never = self.reasons == ["no complete run recorded"] or self.spent > 0
        return ("pending" if never else "stale"), "; ".join(self.reasons)

    def pending(self) -> budget_rules.Pending:
        left = None if self.estimate.seconds is None else max(self.estimate.seconds - self.spent, 0.0)
        return budget_rules.Pending(self.stage.name, self.stage.kind, left)


def decide(pipe: Pipeline, stages: list[Stage], asked: set[str], state: dict[str, Any], force: bool,
           graph: Any, digests: DigestCache, known: dict[str, str] | None = None) -> list[Decision]:
    """Each covered stage's decision, in order: a stage's fingerprint is of what it reads, not
    of what it made, so the whole plan is known before anything runs. ``known``: fingerprints of
    stages not covered (a report's, from the parts that kept them)."""
    kinds = {s.name: (s.kind, s.params) for s in pipe.stages}
    measured = estimates.read_measurements(pipe.out, pipe.path)
    stopped = state.get(STOPPED, {})
    decisions: list[Decision] = []
    fingerprints: dict[str, str] = dict(known or {})
    for stage in stages:
        parts = _parts(stage, fingerprints, graph, digests)
        fp = fingerprints[stage.name] = _digest(parts)
        reasons = _reasons(stage, parts, state.get(stage.name, {}), {d.stage.name for d in decisions if d.run},
                           force and stage.name in asked, digests)
        partial = stopped.get(stage.name) or {}
        spent = float(partial.get("seconds", 0.0)) if partial.get("fingerprint") == fp else 0.0
        if spent and reasons == ["no complete run recorded"]:
            reasons = [f"stopped at a checkpoint by a budget after {budget_rules.words(spent)}; resumes from it"]
        cost = estimates.estimate(stage.name, stage.kind, stage.params,
                                  estimates.places(stage.params, stage.kind, kinds), measured,
                                  estimates.layout(stage.params, stage.kind, kinds))
        decisions.append(Decision(stage, parts, fp, reasons, cost, spent))
    return decisions


def run_pipeline(path: str | Path, scheduler: str | None = None, force: bool = False,
                 dry_run: bool = False, save_costs: bool = False, stages: Sequence[str] = (),
                 downstream: bool = False, settings: Sequence[str] = (), budget: float | None = None,
                 part: str | None = None) -> dict[str, Any]:
    """Run a pipeline; returns the run summary (also written to ``<out>/runs/<stamp>.json``).

    Each stage runs when something it depends on changed (:func:`decide` says what) and is
    skipped otherwise; ``force`` re-runs every stage asked for. ``stages`` (names) with
    ``downstream`` restrict the run (:func:`select`); ``settings`` override parameters
    (:func:`override`). ``budget`` (seconds) runs stages while it lasts (:mod:`vprscale.jobs.budget`):
    the summary's status is then ``"more to do"`` if it ran out, with what is left and its
    estimate. ``dry_run`` decides and reports, stage by stage, with each stage's estimated cost
    (:mod:`vprscale.jobs.estimates`) and, under a budget, the call that runs it, without running
    anything or writing a summary. ``save_costs`` writes the figures of the stages that ran beside
    the pipeline file, for a dry run on a machine that has not run it yet. ``part`` runs one of
    the pipeline's parts (its stages, from nothing where they are not done).
    """
    pipe = load_pipeline(path)
    override(pipe, settings)
    if part is not None:
        if stages:
            raise InputError(f"--part {part}: runs the part's own stages; give STAGE names or --part, not both")
        stages = pipe.part(part).stages
    kept: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {}
    if pipe.parts and part is None and not dry_run:
        reports = [s.name for s in pipe.stages if s.kind == "report"]
        if not stages:  # the whole ladder: its parts in turn, each kept, then the report drawn from them
            return _run_parts(pipe, path, reports, scheduler, force, save_costs, settings, budget)
        if set(stages) <= set(reports):  # its report: assembled from what the parts kept
            kept = _kept_inputs(pipe, stages)
    covered, asked = select(pipe, stages, downstream)
    if kept:  # the report alone: what it reads comes from the kept parts, not from stages run here
        covered = [s for s in covered if s.name in asked]
    state_file = pipe.out / "pipeline-state.json"
    graph = _import_graph()
    digests = DigestCache(pipe.out / DIGESTS)
    if dry_run:
        decisions = decide(pipe, covered, asked, _read_state(state_file), force, graph, digests)
        if pipe.out.is_dir():  # a cache, not an output: the next run need not hash the sources again
            digests.save()
        running = [d for d in decisions if d.run]
        calls = iter(budget_rules.plan_calls([d.pending() for d in running], budget) if budget else [])
        total = estimates.totals([d.estimate for d in running], [d.estimate for d in decisions])
        return {"name": pipe.name, "dry_run": True, "estimate": total, "parts": part_estimates(pipe, graph),
                "stages": [{"name": d.stage.name, "kind": d.stage.kind, "fingerprint": d.fingerprint, "run": d.run,
                            "reasons": d.reasons, "estimate": d.estimate,
                            **(dict(zip(("calls", "call"), next(calls), strict=True)) if d.run and budget else {})}
                           for d in decisions]}
    # what a part's record says of its start: no output folder, and whether vprscale's cache held anything
    from_nothing = not pipe.out.exists() or not any(pipe.out.iterdir())
    caches_empty = not cache_root().is_dir() or not any(f.is_file() for f in cache_root().rglob("*"))
    t_start = time.perf_counter()
    check_writable(pipe.out, f"{pipe.path}: out")  # before any stage: its state, logs and summaries are written there
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    end = None if budget is None else time.time() + budget
    runs = pipe.out / "runs"
    runs.mkdir(exist_ok=True)
    summary: dict[str, Any] = {"pipeline": str(pipe.path), "name": pipe.name, "started": stamp, "stages": [],
                               "vprscale": vprscale.__version__, "status": "running",
                               "selected": list(stages), "downstream": downstream, "set": list(settings),
                               "budget_s": budget,
                               "provenance": provenance(inputs={"pipeline": hashlib.sha256(
                                   pipe.path.read_bytes()).hexdigest()[:16]})}
    with exclusive(pipe.out / "pipeline"), open(runs / f"{stamp}.log", "w") as log:
        state = _read_state(state_file)  # as it is now that the run holds the lock
        outputs: dict[str, dict[str, Any]] = {n: out for n, (_, out) in kept.items()}
        kinds = {s.name: (s.kind, s.params) for s in pipe.stages}
        # the run's log file gets everything; the console only what the logging level lets through
        tee_err = _Tee(*([sys.stderr] if logging.getLogger(__name__).isEnabledFor(logging.INFO) else []), log)
        started_any = False
        summary["covered"] = len(covered)
        try:
            decisions = decide(pipe, covered, asked, state, force, graph, digests,
                               {n: rec["fingerprint"] for n, (rec, _) in kept.items()})  # a bad source fails the run
            digests.save()
            if budget is not None:
                budget_rules.check([d.pending() for d in decisions if d.run], budget)
            for i, d in enumerate(decisions):
                stage, prev = d.stage, state.get(d.stage.name, {})
                entry: dict[str, Any] = {"name": stage.name, "kind": stage.kind, "fingerprint": d.fingerprint,
                                         "params": redact(stage.params),
                                         "places": estimates.places(stage.params, stage.kind, kinds),
                                         "layout": estimates.layout(stage.params, stage.kind, kinds)}
                if not d.run:
                    outputs[stage.name] = prev["outputs"]
                    entry |= {"status": "skipped", "outputs": prev["outputs"], "seconds": 0.0}
                    print(f"= {stage.name} ({stage.kind}): up to date, skipped", file=tee_err)
                    summary["stages"].append(entry)
                    continue
                if end is not None:
                    why = budget_rules.may_start(d.pending(), end - time.time(), not started_any)
                    if why is not None:
                        _left(summary, decisions[i:], why, tee_err)
                        break
                print(f"▶ {stage.name} ({stage.kind}): {'; '.join(d.reasons)}", file=tee_err)
                t0 = time.perf_counter()
                started_any = True
                state.pop(stage.name, None)  # a stage that fails midway is not up to date
                _write_json(state_file, state)
                deadline_given = end if stage.kind in budget_rules.CHECKPOINTED else None
                if stage.kind == "report":
                    _write_stage_record(pipe, stage, {**state, **{n: rec for n, (rec, _) in kept.items()}}, graph)
                try:
                    out = _run_stage(pipe, stage, outputs, scheduler, tee_err, deadline_given)
                except BudgetSpent as stop:
                    seconds = d.spent + time.perf_counter() - t0
                    state.setdefault(STOPPED, {})[stage.name] = {"fingerprint": d.fingerprint, "seconds": seconds,
                                                                 "peak_rss_bytes": max(stop.args[1], _stopped_peak(
                                                                     state, stage.name, d.fingerprint))}
                    _write_json(state_file, state)
                    entry |= {"status": "stopped", "reasons": d.reasons, "seconds": time.perf_counter() - t0}
                    summary["stages"].append(entry)
                    _left(summary, decisions[i:], f"'{stage.name}' stopped at a checkpoint", tee_err,
                          spent={stage.name: seconds})
                    break
                outputs[stage.name] = out
                earlier_peak = _stopped_peak(state, stage.name, d.fingerprint)  # the calls a budget stopped count too
                if earlier_peak:
                    out["peak_rss_bytes"] = max(out.get("peak_rss_bytes") or 0, earlier_peak)
                entry |= {"status": "ran", "reasons": d.reasons, "outputs": out,
                          # a stage resumed after a budget's stop: its whole time, for the estimates
                          "seconds": d.spent + time.perf_counter() - t0}
                state.get(STOPPED, {}).pop(stage.name, None)
                # what a report of the pipeline states of each stage: the code it ran (at which commit), its cost
                state[stage.name] = {"fingerprint": d.fingerprint, "parts": d.parts, "outputs": out,
                                     "signatures": _signatures(out, digests),
                                     "finished": datetime.now(UTC).isoformat(), "seconds": entry["seconds"],
                                     "vprscale": vprscale.__version__,
                                     **{k: summary["provenance"].get(k) for k in ("commit", "dirty")}}
                digests.save()
                _write_json(state_file, state)
                summary["stages"].append(entry)
            summary["status"] = "more to do" if "left" in summary else "ok"
            if part is not None and summary["status"] == "ok":  # what lasts: kept beside the report, whole
                summary["kept"] = str(_keep(pipe, pipe.part(part), state, outputs, summary,
                                            {"from_nothing": from_nothing, "caches_empty": caches_empty},
                                            time.perf_counter() - t_start))
                print(f"kept part {part}'s results in {summary['kept']}", file=tee_err)
                for line in reproduction_lines(json.loads((Path(summary["kept"]) / "part.json").read_text())):
                    print(f"  {line}", file=tee_err)
        except BaseException as exc:  # a signal too (Ctrl-C, a scheduler's SIGTERM): the record says so
            summary["status"] = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
            summary["error"] = f"{type(exc).__name__}: {exc}"
            log.write(traceback.format_exc())
            raise
        finally:
            summary["finished"] = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
            summary["figures"] = [f for s in summary["stages"] for f in s.get("outputs", {}).get("figures", [])]
            _write_json(runs / f"{stamp}.json", summary)
            summary["summary_file"] = str(runs / f"{stamp}.json")
    if save_costs:  # this run's figures and earlier runs' for the stages it skipped
        machine = {k: summary["provenance"].get(k) for k in ("cpu", "cores", "vprscale", "commit")}
        summary["costs_file"] = str(estimates.save_costs(pipe.path, pipe.out,
                                                         [(s.name, s.kind, s.params) for s in pipe.stages], machine))
    return summary


def _run_parts(pipe: Pipeline, path: str | Path, reports: list[str], scheduler: str | None, force: bool,
               save_costs: bool, settings: Sequence[str], budget: float | None) -> dict[str, Any]:
    """A pipeline in parts run whole: each part in turn (each kept), then its report from them;
    under a budget, the calls left stop where it is spent (the first not finished is returned)."""
    end = None if budget is None else time.time() + budget
    for p in pipe.parts:
        left = None if end is None else max(1.0, end - time.time())
        done = run_pipeline(path, scheduler, force, False, save_costs, (), False, settings, left, part=p.name)
        if done["status"] != "ok":
            return done
    left = None if end is None else max(1.0, end - time.time())
    return run_pipeline(path, scheduler, force, False, save_costs, reports, False, settings, left)


def _kept_inputs(pipe: Pipeline, reports: Sequence[str]) -> dict[str, tuple[dict[str, Any], dict[str, Any]]]:
    """What a report of a pipeline in parts reads, from the kept parts: every stage it reads,
    directly or not, by name (its record and where its kept results are); a stage no part has
    kept is one line naming the part that keeps it."""
    report = next(s for s in pipe.stages if s.name in reports)
    kept = kept_stages(kept_root(report.params["out"]))
    by_name = {s.name: s for s in pipe.stages}
    for name in reports:
        needed = list(references(by_name[name]))
        while needed:
            ref = needed.pop()
            if ref not in kept:
                owner = next((p.name for p in pipe.parts if ref in p.stages), "?")
                raise InputError(f"{pipe.path}: stage '{ref}' has no kept results; run its part first: vprscale run "
                                 f"{pipe.name} --part {owner}")
            needed += references(by_name[ref])
    return kept


def _keep(pipe: Pipeline, part: Part, state: dict[str, Any], outputs: dict[str, dict[str, Any]],
          summary: dict[str, Any], start: dict[str, bool], wall_s: float) -> Path:
    """Keep a finished part's results (:mod:`vprscale.jobs.parts`) beside the pipeline's report."""
    report = next((s for s in pipe.stages if s.kind == "report"), None)
    root = kept_root(report.params["out"] if report else pipe.out)
    records = [{"name": n, **{k: v for k, v in state[n].items() if k != "signatures"}} for n in part.stages]
    evals = {n: Path(outputs[n]["eval"]) for n in part.stages if "eval" in outputs.get(n, {})}
    index_stages = [Path(outputs[n]["index"]) for n in part.stages if "index" in outputs.get(n, {})]
    run = {"pipeline": str(pipe.path), "started": summary["started"], "wall_s": wall_s, **start,
           "stages_run": [s["name"] for s in summary["stages"] if s.get("status") == "ran"],
           **{k: summary["provenance"].get(k) for k in ("cpu", "cores", "vprscale", "commit", "dirty")}}
    return keep_part(part.name, records, evals, index_stages, root, run)


def part_estimates(pipe: Pipeline, graph: Any) -> list[dict[str, Any]]:
    """Each part's estimate from nothing (every one of its stages run, whatever is done here): the
    sum of its stages' times, their largest peak, and how many were never measured; and what it
    kept (:func:`part_state`)."""
    kinds = {s.name: (s.kind, s.params) for s in pipe.stages}
    measured = estimates.read_measurements(pipe.out, pipe.path)
    report = next((s for s in pipe.stages if s.kind == "report"), None)
    kept = {}
    for folder in sorted(kept_root(report.params["out"] if report else pipe.out).glob("*/part.json")):
        try:
            kept[folder.parent.name] = json.loads(folder.read_text())
        except (OSError, ValueError):
            continue  # unreadable: said as not kept
    found = []
    for part in pipe.parts:
        costs = [estimates.estimate(s.name, s.kind, s.params, estimates.places(s.params, s.kind, kinds), measured,
                                    estimates.layout(s.params, s.kind, kinds))
                 for s in pipe.stages if s.name in part.stages]
        found.append({"name": part.name, "stages": part.stages, **estimates.totals(costs, costs),
                      "kept": part_state(pipe, part, kept.get(part.name), graph)})
    return found


def part_state(pipe: Pipeline, part: Part, record: dict[str, Any] | None, graph: Any) -> str:
    """``current`` when the part's kept stages ran this vprscale's code with these parameters,
    else why not (``not kept``, or ``stale: …`` naming the stage and what changed)."""
    if record is None:
        return "not kept"
    ran = {r.get("name"): r for r in record.get("stages", [])}
    for stage in (s for s in pipe.stages if s.name in part.stages):
        kept_parts = (ran.get(stage.name) or {}).get("parts") or {}
        if not kept_parts:
            return f"stale: stage {stage.name} not in what it kept"
        if kept_parts.get("params") != json.loads(json.dumps(redact(stage.params), sort_keys=True, default=str)):
            return f"stale: stage {stage.name}'s parameters changed"
        now = stage_code(stage.kind, graph)
        changed = sorted(m for m in set(now) | set(kept_parts.get("code", {}))
                         if now.get(m) != kept_parts.get("code", {}).get(m))
        if changed:
            more = ", …" if len(changed) > 3 else ""
            return f"stale: stage {stage.name}'s code changed ({', '.join(changed[:3])}{more})"
    return "current"


def stage_record_path(pipe: Pipeline, stage: Stage) -> Path:
    return pipe.out / "runs" / f".{stage.name}.stages.json"


def _write_stage_record(pipe: Pipeline, report: Stage, state: dict[str, Any], graph: Any) -> None:
    """The record a report stage states its pipeline's code and costs from
    (:mod:`vprscale.evaluation.stagerecord`): every stage it reads from, directly or not, as the
    state recorded it, and where its code differs from this vprscale's."""
    kinds = {s.name: (s.kind, s.params) for s in pipe.stages}
    read = set(references(report))
    for stage in reversed(pipe.stages):
        if stage.name in read:
            read |= set(references(stage))
    entries = []
    ran: dict[str, set[str]] = {}  # module → the digests the stages ran of it
    for stage in (s for s in pipe.stages if s.name in read):
        done = state[stage.name]
        code, now = done["parts"]["code"], stage_code(stage.kind, graph)
        for module, digest in code.items():
            ran.setdefault(module, set()).add(digest)
        out = done.get("outputs", {})
        entries.append({"name": stage.name, "kind": stage.kind, "code": _digest(code),
                        "differs": sorted(m for m in set(code) | set(now) if code.get(m) != now.get(m)),
                        **{k: done.get(k) for k in ("commit", "dirty", "vprscale", "finished", "seconds")},
                        "peak_rss_bytes": out.get("peak_rss_bytes"), "bytes_on_disk": out.get("bytes_on_disk"),
                        "places": estimates.places(stage.params, stage.kind, kinds),
                        "part": next((p.name for p in pipe.parts if stage.name in p.stages), None)})
    stagerecord.write_record(stage_record_path(pipe, report), pipe.name, entries,
                             one_code_state=all(len(d) == 1 for d in ran.values()), parts=_part_runs(pipe, report))


def _part_runs(pipe: Pipeline, report: Stage) -> list[dict[str, Any]]:
    """Each kept part's run as its ``part.json`` recorded it (wall time, whether from nothing,
    machine, what it kept weighs), in the pipeline file's order; none for a pipeline without parts."""
    root = kept_root(report.params["out"])
    runs = []
    for part in pipe.parts:
        try:
            kept = json.loads((root / part.name / "part.json").read_text())
        except (OSError, ValueError):
            continue  # not kept (the report refused already) or unreadable: nothing to state
        run = kept.get("run", {})
        runs.append({"name": part.name, "stages": list(part.stages), "kept_bytes": kept.get("kept_bytes"),
                     **{k: run.get(k) for k in ("wall_s", "from_nothing", "caches_empty", "cpu", "cores", "commit",
                                                     "dirty")}})
    return runs


def stage_graph(path: str | Path, form: str, settings: Sequence[str] = (), stages: Sequence[str] = (),
                downstream: bool = False, force: bool = False) -> str:
    """The covered stages' graph with their states (:mod:`vprscale.jobs.stagegraph`), decided as a
    dry run decides, running nothing."""
    pipe = load_pipeline(path)
    override(pipe, settings)
    covered, asked = select(pipe, stages, downstream)
    digests = DigestCache(pipe.out / DIGESTS)
    decisions = decide(pipe, covered, asked, _read_state(pipe.out / "pipeline-state.json"), force, _import_graph(),
                       digests)
    if pipe.out.is_dir():
        digests.save()
    edges = [(ref, d.stage.name) for d in decisions for ref in dict.fromkeys(references(d.stage))]
    return stagegraph.render([(d.stage.name, d.stage.kind, *d.state()) for d in decisions], edges, form)


def _left(summary: dict[str, Any], rest: list[Decision], why: str, console: io.TextIOBase,
          spent: dict[str, float] | None = None) -> None:
    """Record and say what a budgeted run leaves for the next call, and its estimate."""
    spent = spent or {}
    left = []
    for d in (d for d in rest if d.run):
        e = d.estimate.seconds
        left.append({"name": d.stage.name, "estimate_s": None if e is None else
                     max(e - spent.get(d.stage.name, d.spent), 0.0)})
    known = [x["estimate_s"] for x in left if x["estimate_s"] is not None]
    summary |= {"left": left, "left_s": sum(known), "left_unmeasured": len(left) - len(known), "stopped_because": why}
    print(f"⏸ {why}: {len(left)} stage(s) left ({', '.join(x['name'] for x in left)}), "
          f"{left_words(sum(known), len(left) - len(known))}; the same command continues", file=console)


def left_words(seconds: float, unmeasured: int) -> str:
    """What is left, as a reader says it: its estimate and how many stages it leaves out."""
    if seconds == 0 and unmeasured:
        return "no estimate (never measured)"
    return f"about {budget_rules.words(seconds)}" + (f", {unmeasured} never measured left out" if unmeasured else "")


def _stopped_peak(state: dict[str, Any], name: str, fingerprint: str) -> int:
    record = state.get(STOPPED, {}).get(name) or {}
    return int(record.get("peak_rss_bytes") or 0) if record.get("fingerprint") == fingerprint else 0


def _read_state(path: Path) -> dict[str, Any]:
    """The pipeline's record of its last complete stages (empty if there is none or it is unreadable:
    then every stage re-runs, which is safe)."""
    try:
        state = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        return {}
    return state if isinstance(state, dict) else {}


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=1, default=str))
    tmp.replace(path)


# The modules a stage's job starts from; the code a stage runs is these, every vprscale module they
# import (function-level imports included), the command line and the package's version.
ENTRY_MODULES = {"synth": ["vprscale.dataset.synth"], "build": ["vprscale.dataset.build"],
                 "index": ["vprscale.jobs.indexing"], "report": ["vprscale.evaluation.report"],
                 "encode": ["vprscale.jobs.encoding"],
                 "eval": ["vprscale.evaluation.evaluate", "vprscale.jobs.indexing",
                          *(target.partition(":")[0] for target in BUILTIN.values())]}
# The package's version and the command line's dispatcher; a stage's own command module
# (vprscale.cli.<kind>, with what it imports) joins its entry modules, so a change to another
# command re-runs nothing.
ALWAYS = ("vprscale", "vprscale.cli")


def _import_graph() -> Any:
    import grimp

    return grimp.build_graph("vprscale", cache_dir=None)


def stage_code(kind: str, graph: Any) -> dict[str, str]:
    """Digest of every module the job of a ``kind`` stage runs, by module name."""
    modules = set(ALWAYS)
    for entry in [*ENTRY_MODULES[kind], f"vprscale.cli.{kind}"]:
        modules |= {entry} | graph.find_upstream_modules(entry)
    root = Path(vprscale.__file__).parent
    code = {}
    for name in sorted(m for m in modules if m.startswith("vprscale")):
        rel = Path(*name.split(".")[1:])
        path = root / rel / "__init__.py" if (root / rel).is_dir() else (root / rel).with_suffix(".py")
        code[name] = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    return code


def _method_source(spec: str) -> str:
    """Digest of the source file of a ``--method`` (its module, outside vprscale): an
    evaluation re-runs when the user's method changes, as when vprscale's own code does."""
    from vprscale.evaluation.algorithms.plugged import with_working_directory
    from vprscale.evaluation.algorithms.registry import installed_methods

    with_working_directory()
    module = installed_methods().get(spec, spec).partition(":")[0]
    origin = _module_file(module)
    if origin is None:
        raise InputError(f"methods: {spec}: no module {module} to import")
    return hashlib.sha256(origin.read_bytes()).hexdigest()


def _module_file(module: str) -> Path | None:
    """The source file of ``module``, found on the import path package by package without importing
    anything (``importlib.util.find_spec`` of ``a.b`` runs ``a``'s ``__init__``: planning a run,
    ``--dry-run`` included, must run none of a method's code); None if there is none."""
    search: list[str] | None = None  # sys.path
    found = None
    for part in module.split("."):
        try:
            found = importlib.machinery.PathFinder.find_spec(part, search)
        except (ImportError, ValueError):
            return None
        if found is None:
            return None
        search = list(found.submodule_search_locations or [])
    origin = Path(found.origin) if found is not None and found.origin else None
    return origin if origin is not None and origin.is_file() else None


def _inputs(stage: Stage, digests: DigestCache) -> dict[str, Any]:
    """What a stage reads besides its parameters: a build's recipe file and source files (each
    source file's fingerprint with the SHA-256 of its bytes), an evaluation's own methods' source
    files."""
    if stage.kind == "eval":
        return {f"method:{m}": _method_source(m) for m in stage.params.get("methods", [])}
    if stage.kind != "build":
        return {}
    if buildstages.form(stage.params) != "scale":
        return buildstages.build_inputs(f"stage '{stage.name}'", stage.params, digests)
    from vprscale.dataset.corpora import parse_base
    from vprscale.dataset.recipe import recipe_path
    from vprscale.dataset.sources.deep1b import open_deep1b
    from vprscale.dataset.sources.fas import open_fas
    from vprscale.dataset.sources.rows import open_rows

    recipe = recipe_path(stage.params["scale"])
    found: dict[str, Any] = {"recipe": hashlib.sha256(recipe.read_bytes()).hexdigest()}
    if stage.params.get("deep1b"):
        found["deep1b"] = _with_digests(open_deep1b(stage.params["deep1b"]).fingerprint(), digests)
    if stage.params.get("base"):
        found["base"] = _with_digests(open_rows(parse_base(stage.params["base"])[1]).fingerprint(), digests)
    if stage.params.get("fas"):
        found["fas"] = _with_digests(open_fas(stage.params["fas"]).fingerprint(), digests)
    return found


def _with_digests(fingerprint: Any, digests: DigestCache) -> Any:
    """A source's fingerprint with every file in it (a dict with ``path`` and ``bytes``) given its
    content digest: any changed byte changes it, whatever the file's size and times say."""
    if isinstance(fingerprint, list):
        return [_with_digests(x, digests) for x in fingerprint]
    if not isinstance(fingerprint, dict):
        return fingerprint
    found = {k: _with_digests(v, digests) for k, v in fingerprint.items()}
    if {"path", "bytes"} <= found.keys() and Path(found["path"]).is_file():
        found["sha256"] = digests.digest(found["path"])
    return found


def _parts(stage: Stage, upstream: dict[str, str], graph: Any, digests: DigestCache) -> dict[str, Any]:
    """What a stage depends on: its kind and parameters, what it reads, the fingerprints of the
    stages it reads from, and the code its job runs (module by module)."""
    refs = {}
    for key, value in stage.params.items():
        for ref in value if isinstance(value, list) else [value]:
            if isinstance(ref, str) and ref in upstream:
                refs[f"{key}:{ref}"] = upstream[ref]
    # a URL's password or signature is not part of what the stage computes, nor recorded
    return json.loads(json.dumps({"kind": stage.kind, "params": redact(stage.params), "upstream": refs,
                                  "inputs": _inputs(stage, digests), "code": stage_code(stage.kind, graph)},
                                 sort_keys=True, default=str))


def _digest(parts: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]


def _reasons(stage: Stage, parts: dict[str, Any], prev: dict[str, Any], ran: set[str], force: bool,
             digests: DigestCache) -> list[str]:
    """Why a stage must run (empty: it is up to date), in words a user can act on."""
    if force:
        return ["--force"]
    if not prev or "parts" not in prev:
        return ["no complete run recorded"]
    old = prev["parts"]
    reasons = []
    if old.get("params") != parts["params"] or old.get("kind") != parts["kind"]:
        changed = sorted(k for k in set(parts["params"]) | set(old.get("params", {}))
                         if parts["params"].get(k) != old.get("params", {}).get(k))
        reasons.append(f"parameters changed ({', '.join(changed) or 'kind'})")
    for key in sorted(set(parts["inputs"]) | set(old.get("inputs", {}))):
        if parts["inputs"].get(key) != old.get("inputs", {}).get(key):
            reasons.append(f"input {key} changed")
    refs = [r.split(":", 1)[1] for r in parts["upstream"]]
    reran = sorted({r for r in refs if r in ran})
    if reran:
        reasons.append(f"upstream stage {', '.join(reran)} re-runs")
    elif parts["upstream"] != old.get("upstream"):
        reasons.append("an upstream stage changed")
    code, old_code = parts["code"], old.get("code", {})
    changed = sorted(m for m in set(code) | set(old_code) if code.get(m) != old_code.get(m))
    if changed:
        reasons.append(f"code changed ({', '.join(changed[:4])}{', …' if len(changed) > 4 else ''})")
    now = _signatures(prev.get("outputs", {}), digests)
    for out, sig in sorted(prev.get("signatures", {}).items()):
        if out not in now:
            reasons.append(f"output {out} missing")
        elif now[out] != sig:
            reasons.append(f"output {out} changed")
    if not prev.get("signatures"):
        reasons.append("no outputs recorded")
    for out in prev.get("signatures", {}):
        if Path(out).is_dir() and out in now:
            try:
                check_manifest(Path(out), budget=0)  # sizes only: the signature above already saw the content
            except InputError as exc:
                reasons.append(f"output damaged ({exc})")
    return reasons


def _signatures(outputs: dict[str, Any], digests: DigestCache) -> dict[str, str]:
    """A signature of every output file or directory that exists: its files' names, sizes and
    content digests. Sizes and modification times alone miss a file rewritten in place with both
    put back (``os.utime`` sets any mtime); a digest is read again only where a file's identity
    (its kernel change time included) moved, so an output moved away and back is still the same
    and costs one more read (:mod:`vprscale.core.digests`)."""
    paths = [v for k, v in outputs.items() if k not in ("peak_rss_bytes", "bytes_on_disk") and isinstance(v, str)]
    paths += [f for f in outputs.get("figures", []) if isinstance(f, str)]
    found = {}
    for p in map(Path, paths):
        if not p.exists():
            continue
        files = _own_files(p) if p.is_dir() else [p]
        body = [(str(f.relative_to(p)) if p.is_dir() else "", f.stat().st_size, digests.digest(f)) for f in files]
        found[str(p)] = hashlib.sha256(json.dumps(body).encode()).hexdigest()[:16]
    return found


def _own_files(directory: Path) -> list[Path]:
    """The files an output directory holds of its own: those its manifest lists (an index's later
    ``eval/`` folder is another stage's output), else every file in it."""
    manifest = read_manifest(directory)
    if manifest is None:
        return sorted(f for f in directory.rglob("*") if f.is_file())
    return [directory / rel for rel in sorted(manifest["files"]) if (directory / rel).is_file()] + [
        directory / "manifest.json"]


def stage_command(pipe: Pipeline, stage: Stage, outputs: dict[str, dict[str, Any]],
                  scheduler: str | None) -> list[str]:
    """The ``vprscale`` command line that runs a stage (shown in the log, run as a subprocess)."""
    p = stage.params
    cluster = ["--scheduler", scheduler] if scheduler else ["--workers", str(pipe.workers)]
    if stage.kind == "synth":
        # --force: the stage's own folder, which the pipeline decided is out of date
        return ["synth", "--out", str(pipe.out / stage.name), "--deep1b-rows", str(p["deep1b_rows"]),
                "--fas-dim", str(p.get("fas_dim", 4096)), "--seed", str(p.get("seed", 0)), "--force"]
    if stage.kind == "build" and buildstages.form(p) != "scale":
        return buildstages.build_command(p, stage.name, pipe.out) + cluster
    if stage.kind == "build":
        src = outputs.get(p.get("source", ""), {})
        cmd = ["build", "--scale", p["scale"], "--out", str(pipe.out), "--force",
               "--fas-dim", str(p.get("fas_dim", 4096))]
        for key, default in (("deep1b", None if "base" in p else src.get("fbin")), ("base", None),
                             ("fas", src.get("fas"))):
            if p.get(key, default):
                cmd += [f"--{key}", p.get(key, default)]
        return cmd + ([] if p.get("rescale", True) else ["--no-rescale"]) + cluster
    if stage.kind == "index":
        # --force: a re-run index stage replaces its old evaluations, which re-run downstream anyway
        cmd = ["index", outputs[p["store"]]["store"], "--k", str(p.get("k", 2)), "--force"]
        return cmd + (["--d", str(p["d"])] if "d" in p else []) + cluster
    if stage.kind == "encode":  # --force: the pipeline decided these encodings are out of date
        return ["encode", outputs[p["store"]]["store"], *(a for f in p["compare"] for a in ("--compare", f)),
                "--force", *cluster]
    if stage.kind == "eval":
        cmd = ["eval", outputs[p["store"]]["store"]] + ([outputs[p["index"]]["index"]] if "index" in p else [])
        cmd += (["--noise", ",".join(p["noise"])] if "noise" in p else []) + (
                ["--flat-noise", ",".join(p["flat_noise"])] if "flat_noise" in p else []) + (
                [] if "task" in p else ["--L", ",".join(map(str, p.get("L", [1, 50, 100])))]) + [
                "--modes", ",".join(p.get("modes", ["paper", "aligned"])),
                "--baseline" if p.get("baseline", True) else "--no-baseline"]
        cmd += (["--z", str(p["z"])] if "z" in p else []) + (["--d", ",".join(map(str, p["d_sweep"]))]
                                                             if "d_sweep" in p else [])
        for factory in p.get("compare", []):
            cmd += ["--compare", factory]
        for method in p.get("methods", []):
            cmd += ["--method", method]
        cmd += ["--nn"] if p.get("nn") else []
        cmd += ["--out", str(pipe.out / stage.name)] if _shares_output(pipe, stage) else []
        for key in ("faiss_k", "faiss_nprobe", "method_k", "compare_queries", "repeats", "radius_m", "nn_queries",
                    "task", "seq_length", "subtask", "threshold"):
            value = ",".join(map(str, p[key])) if isinstance(p.get(key), list) else str(p.get(key))
            cmd += ["--" + key.replace("_", "-"), value] if key in p else []
        # --force: the pipeline decided this evaluation is out of date (the old one is kept beside)
        return cmd + ["--force"] + cluster
    cmd = ["report", *(outputs[r]["eval"] for r in p["results"]), "--out", p["out"],
           "--stages", str(stage_record_path(pipe, stage))]
    for i in p.get("indexes", []):
        cmd += ["--index", outputs[i]["index"]]
    # --force: the pipeline decided this report is out of date (the old one is kept beside)
    return cmd + ["--force"]


def _shares_output(pipe: Pipeline, stage: Stage) -> bool:
    """Whether another eval stage would write this one's default folder (``INDEX/eval``, or a
    sweep's beside the store): both evaluate one index. Such stages each write ``<out>/<stage>``,
    or the last would replace the others' results; a stage alone on its index keeps the default,
    where ``vprscale results INDEX`` and ``sql INDEX`` find it."""
    def target(s: Stage) -> tuple[str, str]:
        return (s.params["index"], "") if "index" in s.params else ("", s.params["store"])

    return sum(s.kind == "eval" and target(s) == target(stage) for s in pipe.stages) > 1


_OUTPUT_KEYS = {"synth": ("dir", "fvecs", "fbin", "fas"), "build": ("store",), "index": ("index",),
                "encode": (), "eval": ("out",), "report": ("report", "figures")}


def _run_stage(pipe: Pipeline, stage: Stage, outputs: dict[str, dict[str, Any]],
               scheduler: str | None, console: io.TextIOBase, end: float | None = None) -> dict[str, Any]:
    """Run one stage as its own process (its memory is its own) and read back its summary. With
    ``end`` (a time), the stage's job stops at a checkpoint before it: :class:`BudgetSpent` with
    the process's peak memory."""
    argv = stage_command(pipe, stage, outputs, scheduler)
    summary_file = pipe.out / "runs" / f".{stage.name}.summary.json"
    summary_file.unlink(missing_ok=True)
    print("$ vprscale " + shlex.join(redact(argv)), file=console)
    env = {k: v for k, v in os.environ.items() if k != deadline.ENV}
    if end is not None:
        env[deadline.ENV] = repr(end)
    proc = subprocess.Popen(vprscale_argv(*argv, "--summary", str(summary_file)), env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
    try:
        for line in proc.stdout:
            console.write(line)
    except BaseException:  # the run was interrupted: so is its stage, which keeps its checkpoints
        proc.send_signal(signal.SIGTERM)
        proc.wait()
        raise
    _, status, usage = os.wait4(proc.pid, 0)  # the stage's own peak memory, whatever its job records
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode == deadline.EXIT_MORE and end is not None:
        raise BudgetSpent(f"stage '{stage.name}' stopped at a checkpoint", usage.ru_maxrss * 1024)
    if proc.returncode != 0:
        message = (f"{pipe.path}: stage '{stage.name}' failed (exit status {proc.returncode}); "
                   f"see the log under {pipe.out / 'runs'}")
        raise InputError(message) if proc.returncode == 2 else JobFailed(message)
    result = json.loads(summary_file.read_text())
    summary_file.unlink()
    out = {k: result[k] for k in _OUTPUT_KEYS[stage.kind] if k in result}
    if stage.kind == "eval":
        out = {"eval": out["out"]}
    if stage.kind == "encode":  # one directory per method
        out = {f"encoding {f}": m["out"] for f, m in result["methods"].items()}
    out["peak_rss_bytes"] = max(result.get("peak_rss_bytes") or 0, usage.ru_maxrss * 1024)
    main = out.get("store") or out.get("index") or out.get("eval") or out.get("dir")
    if stage.kind == "report" and out.get("report"):  # the report's folder: its page, tables and figures
        main = str(Path(out["report"]).parent)
    if main and Path(main).exists():
        out["bytes_on_disk"] = sum(f.stat().st_size for f in Path(main).rglob("*") if f.is_file())
    return out
