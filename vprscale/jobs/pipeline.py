"""``vprscale run``: batch pipelines of stages (synth, build, index, eval, report) from TOML.

A pipeline file names an output directory and an ordered list of stages. Each stage's
fingerprint covers its kind, its parameters, what it reads (a build's recipe file and
source files), the fingerprints of the stages it reads from, and vprscale's code; a stage
whose fingerprint matches its last complete run (and whose outputs still exist) is
skipped, so re-running a finished pipeline does no work and changing a parameter, an
input or the code re-runs that stage and everything downstream of it. Every run writes a
JSON summary (times, peak memory, bytes on disk per stage) and a log under
``<out>/runs/``; two runs on the same output directory never overlap.

Relative paths are taken from the current directory (run pipelines from the repository root).
"""

from __future__ import annotations

import hashlib
import io
import json
import shlex
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import vprscale
from vprscale.core.errors import InputError, JobFailed
from vprscale.core.publish import exclusive
from vprscale.dataset.recipe import read_toml

# Parameter schema per stage kind: name → (type, required). Types: "str", "int", "bool",
# "list[int]", "list[str]", "stage" (the name of an earlier stage), "list[stage]".
SCHEMA: dict[str, dict[str, tuple[str, bool]]] = {
    "synth": {"deep1b_rows": ("int", True), "fas_dim": ("int", False), "seed": ("int", False)},
    "build": {"scale": ("str", True), "source": ("stage", False), "deep1b": ("str", False), "fas": ("str", False),
              "fas_dim": ("int", False), "rescale": ("bool", False)},
    "index": {"store": ("stage", True), "d": ("int", False), "k": ("int", False)},
    "eval": {"store": ("stage", True), "index": ("stage", False), "d_sweep": ("list[int]", False),
             "noise": ("list[str]", False), "L": ("list[int]", False), "modes": ("list[str]", False),
             "baseline": ("bool", False), "z": ("int", False), "compare": ("list[str]", False),
             "faiss_k": ("int", False), "compare_queries": ("int", False),
             "repeats": ("int", False)},
    "report": {"results": ("list[stage]", True), "indexes": ("list[stage]", False), "out": ("str", True)},
}
PRODUCERS = {"source": {"synth"}, "store": {"build"}, "index": {"index"}, "results": {"eval"},
             "indexes": {"index"}}


@dataclass
class Stage:
    name: str
    kind: str
    params: dict[str, Any]


@dataclass
class Pipeline:
    path: Path
    name: str
    out: Path
    workers: int
    stages: list[Stage] = field(default_factory=list)


def _type_ok(value: Any, kind: str) -> bool:
    if kind in ("str", "stage"):
        return isinstance(value, str)
    if kind == "int":
        return isinstance(value, int) and not isinstance(value, bool)
    if kind == "bool":
        return isinstance(value, bool)
    inner = kind[5:-1]
    return isinstance(value, list) and all(_type_ok(v, "str" if inner == "stage" else inner) for v in value)


_TYPE_WORDS = {"str": "a string", "stage": "the name of an earlier stage", "int": "an integer", "bool": "true or false",
               "list[int]": "a list of integers", "list[str]": "a list of strings",
               "list[stage]": "a list of earlier stage names"}


def load_pipeline(path: str | Path) -> Pipeline:
    """Parse and validate a pipeline file; every error names the file, the stage and the key."""
    path = Path(path)
    data = read_toml(path, "pipeline")
    for key in ("name", "out", "stages"):
        if key not in data:
            raise InputError(f"{path}: missing key '{key}'")
    unknown = set(data) - {"name", "out", "stages", "workers"}
    if unknown:
        raise InputError(f"{path}: unknown key(s) {sorted(unknown)}")
    workers = data.get("workers", 2)
    if not _type_ok(workers, "int") or workers < 1:
        raise InputError(f"{path}: key 'workers' must be a positive integer")
    if not isinstance(data["stages"], list) or not data["stages"]:
        raise InputError(f"{path}: key 'stages' must be a non-empty array of tables ([[stages]])")
    pipe = Pipeline(path, str(data["name"]), Path(data["out"]), workers)
    kinds: dict[str, str] = {}
    for i, raw in enumerate(data["stages"]):
        where = f"{path}: stages[{i}]"
        if not isinstance(raw, dict) or "name" not in raw or "kind" not in raw:
            raise InputError(f"{where}: every stage needs the keys 'name' and 'kind'")
        name, kind = raw["name"], raw["kind"]
        where = f"{path}: stage '{name}'"
        if kind not in SCHEMA:
            raise InputError(f"{where}: unknown stage kind '{kind}' (known: {', '.join(SCHEMA)})")
        if name in kinds:
            raise InputError(f"{where}: the name is used twice")
        params = {k: v for k, v in raw.items() if k not in ("name", "kind")}
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
                    if kinds.get(ref) not in PRODUCERS[key]:
                        raise InputError(f"{where}: key '{key}' must name an earlier "
                                         f"{' or '.join(sorted(PRODUCERS[key]))} stage, got '{ref}'")
        kinds[name] = kind
        pipe.stages.append(Stage(name, kind, params))
    return pipe


class _Tee(io.TextIOBase):
    def __init__(self, *streams) -> None:
        self.streams = streams

    def write(self, s: str) -> int:
        for st in self.streams:
            st.write(s)
            st.flush()
        return len(s)


def run_pipeline(path: str | Path, scheduler: str | None = None, force: bool = False) -> dict[str, Any]:
    """Run a pipeline; returns the run summary (also written to ``<out>/runs/<stamp>.json``).

    ``force`` re-runs every stage even where nothing it depends on changed.
    """
    pipe = load_pipeline(path)
    pipe.out.mkdir(parents=True, exist_ok=True)
    state_file = pipe.out / "pipeline-state.json"
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    runs = pipe.out / "runs"
    runs.mkdir(exist_ok=True)
    summary: dict[str, Any] = {"pipeline": str(pipe.path), "name": pipe.name, "started": stamp, "stages": [],
                               "vprscale": vprscale.__version__, "status": "running"}
    with exclusive(pipe.out / "pipeline"), open(runs / f"{stamp}.log", "w") as log:
        state = json.loads(state_file.read_text()) if state_file.is_file() else {}
        fingerprints: dict[str, str] = {}
        outputs: dict[str, dict[str, Any]] = {}
        code = code_fingerprint()
        tee_err = _Tee(sys.stderr, log)
        try:
            for stage in pipe.stages:
                fp = _fingerprint(stage, fingerprints, code)
                fingerprints[stage.name] = fp
                prev = state.get(stage.name, {})
                entry: dict[str, Any] = {"name": stage.name, "kind": stage.kind, "fingerprint": fp}
                if not force and prev.get("fingerprint") == fp and _outputs_exist(prev.get("outputs", {})):
                    outputs[stage.name] = prev["outputs"]
                    entry |= {"status": "skipped", "outputs": prev["outputs"], "seconds": 0.0}
                    print(f"= {stage.name} ({stage.kind}): unchanged, skipped", file=tee_err)
                else:
                    print(f"▶ {stage.name} ({stage.kind})", file=tee_err)
                    t0 = time.perf_counter()
                    out = _run_stage(pipe, stage, outputs, scheduler, tee_err)
                    outputs[stage.name] = out
                    entry |= {"status": "ran", "outputs": out, "seconds": time.perf_counter() - t0}
                    state[stage.name] = {"fingerprint": fp, "outputs": out, "finished": datetime.now(UTC).isoformat()}
                    _write_json(state_file, state)
                summary["stages"].append(entry)
            summary["status"] = "ok"
        except Exception as exc:
            summary["status"] = "failed"
            summary["error"] = f"{type(exc).__name__}: {exc}"
            log.write(traceback.format_exc())
            raise
        finally:
            summary["finished"] = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
            summary["figures"] = [f for s in summary["stages"] for f in s.get("outputs", {}).get("figures", [])]
            _write_json(runs / f"{stamp}.json", summary)
            summary["summary_file"] = str(runs / f"{stamp}.json")
    return summary


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=1, default=str))
    tmp.replace(path)


def code_fingerprint() -> str:
    """A digest of vprscale's own source files: a change of code re-runs the stages it may change."""
    root = Path(vprscale.__file__).parent
    digest = hashlib.sha256(vprscale.__version__.encode())
    for f in sorted(root.rglob("*.py")):
        digest.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes())
    return digest.hexdigest()[:16]


def _inputs(stage: Stage) -> dict[str, Any]:
    """What a stage reads besides its parameters: a build's recipe file and source files."""
    if stage.kind != "build":
        return {}
    from vprscale.dataset.recipe import recipe_path
    from vprscale.dataset.sources.deep1b import open_deep1b
    from vprscale.dataset.sources.fas import open_fas

    recipe = recipe_path(stage.params["scale"])
    found: dict[str, Any] = {"recipe": hashlib.sha256(recipe.read_bytes()).hexdigest()}
    if stage.params.get("deep1b"):
        found["deep1b"] = open_deep1b(stage.params["deep1b"]).fingerprint()
    if stage.params.get("fas"):
        found["fas"] = open_fas(stage.params["fas"]).fingerprint()
    return found


def _fingerprint(stage: Stage, upstream: dict[str, str], code: str) -> str:
    """A stage's identity: its kind and parameters, what it reads, its upstream stages and the code."""
    refs = {}
    for key, value in stage.params.items():
        for ref in value if isinstance(value, list) else [value]:
            if isinstance(ref, str) and ref in upstream:
                refs[f"{key}:{ref}"] = upstream[ref]
    body = {"kind": stage.kind, "params": stage.params, "upstream": refs, "inputs": _inputs(stage), "code": code}
    return hashlib.sha256(json.dumps(body, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _outputs_exist(outputs: dict[str, Any]) -> bool:
    paths = [v for k, v in outputs.items() if k not in ("figures", "peak_rss_bytes", "bytes_on_disk")
             and isinstance(v, str)]
    return bool(paths) and all(Path(p).exists() for p in paths)


def stage_command(pipe: Pipeline, stage: Stage, outputs: dict[str, dict[str, Any]],
                  scheduler: str | None) -> list[str]:
    """The ``vprscale`` command line that runs a stage (shown in the log, run as a subprocess)."""
    p = stage.params
    cluster = ["--scheduler", scheduler] if scheduler else ["--workers", str(pipe.workers)]
    if stage.kind == "synth":
        return ["synth", "--out", str(pipe.out / stage.name), "--deep1b-rows", str(p["deep1b_rows"]),
                "--fas-dim", str(p.get("fas_dim", 4096)), "--seed", str(p.get("seed", 0))]
    if stage.kind == "build":
        src = outputs.get(p.get("source", ""), {})
        cmd = ["build", "--scale", p["scale"], "--out", str(pipe.out), "--force",
               "--fas-dim", str(p.get("fas_dim", 4096))]
        for key, default in (("deep1b", src.get("fbin")), ("fas", src.get("fas"))):
            if p.get(key, default):
                cmd += [f"--{key}", p.get(key, default)]
        return cmd + ([] if p.get("rescale", True) else ["--no-rescale"]) + cluster
    if stage.kind == "index":
        # --force: a re-run index stage replaces its old evaluations, which re-run downstream anyway
        cmd = ["index", outputs[p["store"]]["store"], "--k", str(p.get("k", 2)), "--force"]
        return cmd + (["--d", str(p["d"])] if "d" in p else []) + cluster
    if stage.kind == "eval":
        cmd = ["eval", outputs[p["store"]]["store"]] + ([outputs[p["index"]]["index"]] if "index" in p else [])
        cmd += ["--noise", ",".join(p.get("noise", ["qm1", "qm2"])),
                "--L", ",".join(map(str, p.get("L", [1, 50, 100]))),
                "--modes", ",".join(p.get("modes", ["paper", "aligned"])),
                "--baseline" if p.get("baseline", True) else "--no-baseline"]
        cmd += (["--z", str(p["z"])] if "z" in p else []) + (["--d", ",".join(map(str, p["d_sweep"]))]
                                                             if "d_sweep" in p else [])
        for factory in p.get("compare", []):
            cmd += ["--compare", factory]
        for key in ("faiss_k", "compare_queries", "repeats"):
            cmd += ["--" + key.replace("_", "-"), str(p[key])] if key in p else []
        return cmd + cluster
    cmd = ["report", *(outputs[r]["eval"] for r in p["results"]), "--out", p["out"]]
    for i in p.get("indexes", []):
        cmd += ["--index", outputs[i]["index"]]
    return cmd


_OUTPUT_KEYS = {"synth": ("dir", "fvecs", "fbin", "fas"), "build": ("store",), "index": ("index",),
                "eval": ("out",), "report": ("report", "figures")}


def _run_stage(pipe: Pipeline, stage: Stage, outputs: dict[str, dict[str, Any]],
               scheduler: str | None, console: io.TextIOBase) -> dict[str, Any]:
    """Run one stage as its own process (its memory is its own) and read back its summary."""
    argv = stage_command(pipe, stage, outputs, scheduler)
    summary_file = pipe.out / "runs" / f".{stage.name}.summary.json"
    summary_file.unlink(missing_ok=True)
    print("$ vprscale " + " ".join(shlex.quote(a) for a in argv), file=console)
    proc = subprocess.Popen([sys.executable, "-m", "vprscale.cli", *argv, "--summary", str(summary_file)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
    for line in proc.stdout:
        console.write(line)
    if proc.wait() != 0:
        message = (f"{pipe.path}: stage '{stage.name}' failed (exit status {proc.returncode}); "
                   f"see the log under {pipe.out / 'runs'}")
        raise InputError(message) if proc.returncode == 2 else JobFailed(message)
    result = json.loads(summary_file.read_text())
    summary_file.unlink()
    out = {k: result[k] for k in _OUTPUT_KEYS[stage.kind] if k in result}
    if stage.kind == "eval":
        out = {"eval": out["out"]}
    out["peak_rss_bytes"] = result.get("peak_rss_bytes")
    main = out.get("store") or out.get("index") or out.get("eval") or out.get("dir")
    if main and Path(main).exists():
        out["bytes_on_disk"] = sum(f.stat().st_size for f in Path(main).rglob("*") if f.is_file())
    return out
