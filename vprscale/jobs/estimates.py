"""What a pipeline run will cost before it starts: each stage's time, peak memory and disk
(``vprscale run --dry-run``).

Estimates come from measurements, never from constants in the code. Every run records each
stage it ran (wall time, peak memory, bytes written) in its summary under ``<out>/runs/``, with
the stage's parameters; a stage is then estimated by, in order:

1. **measured**: the last run of the same stage (same name, kind and parameters) under this
   output directory, or in the costs file shipped beside a pipeline (``<pipeline>.costs.json``:
   the stage figures of a whole run on the reference machine kind, written by ``vprscale run
   --save-costs``);
2. **scaled**: a measured stage of the same kind and parameters at another scale of the same
   store layout (a compact store's build, index and encodings are other jobs than a full one's),
   its time and disk scaled by the ratio of the places each reads, its memory too except a
   build's, which streams its rows in chunks;
3. **unmeasured**: nothing to go on; the totals say how many stages they leave out.

The run's time is the sum of the stages that would run, its peak memory the largest of theirs
(stages run one after another), its disk what every stage's output holds afterwards.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vprscale.core.errors import InputError
from vprscale.dataset.recipe import load_recipe

COSTS_SUFFIX = ".costs.json"
REFERENCE = "on the reference machine"  # a shipped costs file's figures
_STREAMED = {"build", "synth"}  # stages whose memory does not grow with the rows they stream
_STORE_KEYS = ("store", "source", "index", "encodings", "results", "indexes")  # references, not parameters


@dataclass
class Estimate:
    """One stage's expected cost and where the figure comes from."""

    seconds: float | None
    peak_bytes: int | None
    disk_bytes: int | None
    basis: str  # "measured <when>", "scaled from <stage> ×<ratio>" or "unmeasured"


@dataclass
class _Measured:
    name: str
    kind: str
    params: dict[str, Any]
    places: int | None
    layout: str | None
    seconds: float
    peak_bytes: int | None
    disk_bytes: int | None
    when: str  # the run's stamp (a costs file's entry: the stamp it was measured at)
    reference: bool = False  # from the shipped costs file, not a run under the output


def places(stage_params: dict[str, Any], kind: str, stages: dict[str, tuple[str, dict[str, Any]]]) -> int | None:
    """The places a stage works on: its build's recipe's rows (read through the stage it reads
    from), None where no build is named (a store given by path, a synth or report stage)."""
    recipe = _recipe(stage_params, kind, stages)
    return None if recipe is None else int(recipe.deep1b_rows_read)


def layout(stage_params: dict[str, Any], kind: str, stages: dict[str, tuple[str, dict[str, Any]]]) -> str | None:
    """The layout of the store a stage works on (its build's recipe's), None where no build is named."""
    recipe = _recipe(stage_params, kind, stages)
    return None if recipe is None else recipe.layout


def _recipe(stage_params: dict[str, Any], kind: str, stages: dict[str, tuple[str, dict[str, Any]]]) -> Any:
    seen = 0
    params = stage_params
    while kind != "build" and seen < len(stages) + 1:
        ref = next((params[k] for k in ("store", "index") if isinstance(params.get(k), str)), None)
        if ref is None or ref not in stages:
            return None
        kind, params = stages[ref]
        seen += 1
    if kind != "build" or "scale" not in params:  # your own descriptors and MSLS: no recipe
        return None
    try:
        return load_recipe(params["scale"])
    except InputError:
        return None


def _own_params(params: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in params.items() if k not in _STORE_KEYS and k != "scale"}


def read_measurements(out: Path, pipeline_path: Path) -> list[_Measured]:
    """Every stage run recorded under ``out/runs`` (oldest first), then the shipped costs file's."""
    found: list[_Measured] = []
    files = sorted((out / "runs").glob("*.json")) if (out / "runs").is_dir() else []
    costs = pipeline_path.with_name(pipeline_path.stem + COSTS_SUFFIX)
    for path in ([costs] if costs.is_file() else []) + files:
        try:
            summary = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError, UnicodeDecodeError):
            continue
        if not isinstance(summary, dict):
            continue
        for s in summary.get("stages", []):
            if not isinstance(s, dict) or s.get("status") != "ran" or "params" not in s:
                continue
            outputs = s.get("outputs") or {}
            found.append(_Measured(s["name"], s["kind"], s["params"], s.get("places"), s.get("layout"),
                                   float(s["seconds"]),
                                   outputs.get("peak_rss_bytes"), outputs.get("bytes_on_disk"),
                                   s.get("measured", "?") if path == costs else summary.get("started", "?"),
                                   path == costs))
    return found


def _last(measured: list[_Measured], name: str, kind: str, params: dict[str, Any]) -> _Measured | None:
    """The latest measurement of this stage (same name, kind and parameters), if any."""
    return next((m for m in reversed(measured) if m.name == name and m.kind == kind and m.params == params), None)


def estimate(name: str, kind: str, params: dict[str, Any], n: int | None, measured: list[_Measured],
             store_layout: str | None = None) -> Estimate:
    """One stage's estimate from the measurements (the latest of each kind wins)."""
    m = _last(measured, name, kind, params)
    if m is not None:
        basis = REFERENCE if m.reference else _when(m.when)
        return Estimate(m.seconds, m.peak_bytes, m.disk_bytes, f"measured {basis}")
    own = _own_params(params)
    alike = [m for m in measured if m.kind == kind and _own_params(m.params) == own and m.places and n
             and m.layout == store_layout]
    if alike:
        m = min(reversed(alike), key=lambda m: abs(m.places - n))  # the nearest scale, latest first
        ratio = n / m.places
        peak = m.peak_bytes if kind in _STREAMED or m.peak_bytes is None else int(m.peak_bytes * ratio)
        disk = None if m.disk_bytes is None else int(m.disk_bytes * ratio)
        return Estimate(m.seconds * ratio, peak, disk, f"scaled from {m.name} ×{ratio:,.3g}")
    return Estimate(None, None, None, "unmeasured")


def _when(stamp: str) -> str:
    """A run's stamp (``20261203T064222Z``) as a reader says it: ``in the run of 2026-12-03 06:42 UTC``."""
    if len(stamp) == 16 and stamp[8] == "T":
        return f"in the run of {stamp[:4]}-{stamp[4:6]}-{stamp[6:8]} {stamp[9:11]}:{stamp[11:13]} UTC"
    return stamp


def totals(running: list[Estimate], every: list[Estimate]) -> dict[str, Any]:
    """The run's time (stages that run), peak memory (theirs), disk (every stage's output), and
    how many running stages have no estimate."""
    return {"seconds": sum(e.seconds for e in running if e.seconds is not None),
            "peak_bytes": max((e.peak_bytes for e in running if e.peak_bytes is not None), default=None),
            "disk_bytes": sum(e.disk_bytes for e in every if e.disk_bytes is not None),
            "unmeasured": sum(e.seconds is None for e in running)}


def save_costs(pipeline_path: Path, out: Path, stages: list[tuple[str, str, dict[str, Any]]],
               machine: dict[str, Any]) -> Path:
    """Write each stage's last measured figures under ``out`` (whichever run measured it) to the
    pipeline's costs file, with the machine they were measured on; returns its path.

    A stage no run under ``out`` measured keeps the file's entry as it was: a ladder that runs
    over several calls, or starts again on a new machine of the same kind with an empty ``out``,
    refreshes the figures it measures without dropping those of the stages it has not reached.
    """
    path = pipeline_path.with_name(pipeline_path.stem + COSTS_SUFFIX)
    measured = read_measurements(out, pipeline_path)
    ran, shipped = [m for m in measured if not m.reference], [m for m in measured if m.reference]
    entries = []
    for name, kind, params in stages:
        m = _last(ran, name, kind, params) or _last(shipped, name, kind, params)
        if m is not None:
            entries.append({"name": name, "kind": kind, "params": params, "places": m.places, "layout": m.layout,
                            "status": "ran",
                            "seconds": m.seconds, "measured": m.when,
                            "outputs": {"peak_rss_bytes": m.peak_bytes, "bytes_on_disk": m.disk_bytes}})
    costs = {"machine": machine, "stages": entries}
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(costs, indent=1, default=str) + "\n")
    tmp.replace(path)
    return path
