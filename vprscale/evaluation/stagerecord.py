"""A pipeline's stage record: the code each stage ran and what it cost, for a report of the pipeline.

A pipeline's stages may run in separate calls (``vprscale run --budget``), sessions and commits;
what makes their results one state is that every stage's code is the code of one vprscale. So
``vprscale run`` gives its report stage this record (``vprscale report --stages FILE``), one entry
per stage, and the report states the code state stage by stage instead of counting commits: the
digest of the modules the stage ran, the commit it ran at, and whether that code differs from
the vprscale drawing the report (the modules that do). The report's time table is this record
(each stage's time summed over the calls it took), and the report keeps it as ``stages.json``.

The record holds no paths: a report is read, and committed, on other machines.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from vprscale.core.errors import InputError
from vprscale.core.plaintext import markdown, markdown_code

FILE = "stages.json"  # its name in a report
PARTS = "parts"  # a report's folder of what its pipeline's parts kept (vprscale run --part), kept with it
_NONE = type(None)
_FIELDS: dict[str, tuple[type, ...]] = {
    "name": (str,), "kind": (str,), "code": (str,), "differs": (list,), "commit": (str, _NONE),
    "dirty": (bool, _NONE), "vprscale": (str, _NONE), "finished": (str, _NONE), "seconds": (int, float, _NONE),
    "peak_rss_bytes": (int, _NONE), "bytes_on_disk": (int, _NONE), "places": (int, _NONE), "part": (str, _NONE)}
_PART_FIELDS: dict[str, tuple[type, ...]] = {
    "name": (str,), "stages": (list,), "kept_bytes": (int, _NONE), "wall_s": (int, float, _NONE),
    "from_nothing": (bool, _NONE), "caches_empty": (bool, _NONE), "cpu": (str, _NONE), "cores": (int, _NONE),
    "commit": (str, _NONE), "dirty": (bool, _NONE)}


def write_record(path: Path, pipeline: str, stages: list[dict[str, Any]], one_code_state: bool | None = None,
                 parts: list[dict[str, Any]] | None = None) -> None:
    """Write the record of ``pipeline``'s ``stages`` (each with the fields of :data:`_FIELDS`):
    ``one_code_state`` whether every module ran at one digest in every stage, ``parts`` the kept
    parts' runs (:data:`_PART_FIELDS`) of a pipeline in parts."""
    record = {"pipeline": pipeline, "stages": [{k: s.get(k) for k in _FIELDS} for s in stages],
              "one_code_state": one_code_state, "parts": [{k: p.get(k) for k in _PART_FIELDS} for p in parts or []]}
    check(record, str(path))
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(record, indent=1) + "\n")
    tmp.replace(path)


def read_record(path: str | Path) -> dict[str, Any]:
    """A stage record, checked (one line naming the file and the stage where it is not one)."""
    try:
        record = json.loads(Path(path).read_text())
    except OSError as exc:
        raise InputError(f"--stages {path}: cannot be read ({exc.strerror or exc})") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"--stages {path}: not JSON ({exc})") from None
    check(record, f"--stages {path}")
    return record


def check(record: Any, where: str) -> None:
    if not isinstance(record, dict) or not isinstance(record.get("pipeline"), str) or not isinstance(
            record.get("stages"), list):
        raise InputError(f"{where}: not a stage record (a pipeline's name and its stages)")
    for i, stage in enumerate(record["stages"]):
        if not isinstance(stage, dict):
            raise InputError(f"{where}: stages[{i}] is not an object")
        for key, kind in _FIELDS.items():
            value = stage.get(key)
            if not isinstance(value, kind) or (isinstance(value, bool) and bool not in kind):
                raise InputError(f"{where}: stages[{i}] ({stage.get('name')!r}): '{key}' is missing or of the "
                                 "wrong type")
        if not all(isinstance(m, str) for m in stage["differs"]):
            raise InputError(f"{where}: stages[{i}] ({stage['name']!r}): 'differs' must list module names")
    if not isinstance(record.get("one_code_state"), bool | _NONE) or not isinstance(record.get("parts", []), list):
        raise InputError(f"{where}: 'one_code_state' must be true or false, 'parts' a list")
    for i, part in enumerate(record.get("parts", [])):
        if not isinstance(part, dict) or any(not isinstance(part.get(k), kind) or (
                isinstance(part.get(k), bool) and bool not in kind) for k, kind in _PART_FIELDS.items()):
            raise InputError(f"{where}: parts[{i}] is not a kept part's run (a name, its stages, its wall time)")


def provenance_lines(record: dict[str, Any], table: Callable[[list[str], list[list[Any]]], str]) -> list[str]:
    """The code state of the pipeline, stage by stage: one line that says whether every stage ran
    this vprscale's code, a warning per stage that did not, and the table."""
    stages = record["stages"]
    stale = [s for s in stages if s["differs"]]
    commits = sorted({_commit(s) for s in stages})
    lines = [f"- pipeline {markdown_code(record['pipeline'])}: {len(stages)} stages, run at "
             f"{len(commits)} commit(s) ({', '.join(commits)}); "
             + ("**every stage's code is this vprscale's**" if not stale else
                f"**{len(stale)} stage(s) ran code that differs from this vprscale's**")]
    for s in stale:
        shown = ", ".join(s["differs"][:6]) + (", …" if len(s["differs"]) > 6 else "")
        lines.append(f"  - **{s['name']}** ran other code than this vprscale's in {len(s['differs'])} module(s) "
                     f"({shown}): its figures are not this code's")
    rows = [[s["name"], s["kind"], s["code"], _commit(s), (s["finished"] or "–")[:16].replace("T", " "),
             "yes" if not s["differs"] else f"no ({len(s['differs'])} modules)"] for s in stages]
    return [*lines, *_part_lines(record, table), "",
            "Each stage's code (a digest of the modules its job runs) and the commit it ran at:", "",
            table(["stage", "kind", "code", "commit", "finished (UTC)", "this vprscale's code"], rows), ""]


def _part_lines(record: dict[str, Any], table: Callable[[list[str], list[list[Any]]], str]) -> list[str]:
    """A pipeline in parts: whether its parts are one code state, and each part's run (from
    nothing or not, its wall time, what it kept) with the command that refreshes a part whose
    code is not this vprscale's."""
    parts = record.get("parts") or []
    if not parts:
        return []
    one = record.get("one_code_state")
    differs = {s["part"] for s in record["stages"] if s["differs"] and s.get("part")}
    pipeline = markdown_code(record["pipeline"])
    lines = [f"- parts: {len(parts)} kept; " + (
        "**one code state**: every module ran at one digest in every stage of every part" if one else
        "**not one code state**: some module ran at different digests in different stages" if one is False else
        "whether they are one code state was not recorded")]
    lines += [f"  - part **{markdown(p['name'])}** ran other code than this vprscale's: "
              f"{_refresh(record['pipeline'], p['name'])} refreshes it" for p in parts if p["name"] in differs]
    rows = [[markdown(p["name"]), len(p["stages"]), _commit(p),
             _number(None if p["wall_s"] is None else p["wall_s"] / 60, ",.1f"),
             _yes(p["from_nothing"]), _yes(p["caches_empty"]),
             markdown(f"{p['cpu']} ({p['cores']} cores)") if p["cpu"] else "–",
             _number(None if p["kept_bytes"] is None else p["kept_bytes"] / 1e3, ",.0f"),
             "yes" if p["name"] not in differs else f"no: {_refresh(record['pipeline'], p['name'])}"]
            for p in parts]
    return [*lines, "", f"Each part of {pipeline}, run on its own ({_refresh(record['pipeline'], 'NAME')}) "
            "and kept beside this report (parts/NAME/):", "",
            table(["part", "stages", "commit", "wall min", "from nothing", "caches empty", "machine", "kept KB",
                   "this vprscale's code"], rows)]


def time_table(record: dict[str, Any], table: Callable[[list[str], list[list[Any]]], str]) -> list[str]:
    """The pipeline's cost per stage: wall time (over every call it took), peak memory, bytes on disk."""
    gib = 2**30
    rows = [[s["name"], s["kind"], _number(s["places"], ","), _number(s["seconds"], ",.1f"),
             _number(None if s["peak_rss_bytes"] is None else s["peak_rss_bytes"] / gib, ".2f"),
             _number(None if s["bytes_on_disk"] is None else s["bytes_on_disk"] / gib, ".2f")]
            for s in record["stages"]]
    total = sum(s["seconds"] or 0 for s in record["stages"])
    return ["## Time (s), peak memory (GiB) and disk (GiB) per stage", "",
            f"As the pipeline recorded them ({FILE} beside this report): a stage's time is its wall time summed "
            f"over the calls it took; {total / 3600:.2f} hours in all, one stage after another.", "",
            table(["stage", "kind", "places", "time s", "peak GiB", "disk GiB"], rows), ""]


def _yes(flag: bool | None) -> str:
    return "–" if flag is None else "yes" if flag else "no"


def _refresh(pipeline: str, part: str) -> str:
    return markdown_code(f"vprscale run {pipeline} --part {part}")


def _commit(stage: dict[str, Any]) -> str:
    if not stage["commit"]:
        return "unknown"
    return stage["commit"][:12] + (" (dirty tree)" if stage["dirty"] else "")


def _number(x: float | None, fmt: str) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)
