"""What a part of a pipeline keeps (``vprscale run PIPELINE --part NAME``).

A ladder too long for one job runs as parts (:class:`vprscale.jobs.pipeline.Part`), each from
nothing on whatever machine the job lands on; its stores, indexes and encodings are rebuilt,
deterministically, by the part that needs them and need not last. What must last is small, and
is kept beside the pipeline's report, under ``<report out>/parts/<part>/``:

- ``evals/<stage>/``: each evaluation's ``results.parquet`` (and ``results_m.parquet``,
  ``nn.parquet``), the columns of ``queries.parquet`` the report's precision-recall curves read,
  and ``eval.json``;
- ``indexes/<index>/``: each index those results name, as the report reads it: ``index.json``,
  ``components.parquet`` and ``files.json``, the bytes of each of its files;
- ``part.json``: each stage's parameters, fingerprint, code digests (module by module), input
  fingerprints, time, peak memory and disk, the commit and version it ran at, and the part's run:
  its wall time, whether it started from an empty folder, the machine; and, for a part kept
  again, how its result rows compare with those it replaces (``as_kept_before``): a run from
  nothing elsewhere is meant to reproduce them, times aside, and this says whether it did.

No path of the machine is kept: every path is written relative to the directory the pipeline
ran from (the repository's root). The folder is written beside its place and renamed into it
whole, so a part stopped part way keeps nothing, and the part's previous results stand.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from vprscale.core.manifest import write_manifest
from vprscale.evaluation.prcurves import COLUMNS as CURVE_COLUMNS
from vprscale.evaluation.stagerecord import PARTS

TABLES = ("results.parquet", "results_m.parquet", "nn.parquet")
MEASURED = ("us_", "queries_per_s", "timed_")  # a result column a run measures (time), not computes: prefixes
INDEX_FILES = ("index.json", "components.parquet")


def kept_root(report_out: str | Path) -> Path:
    """Where a pipeline's parts keep their results: in its report's folder, which a report
    drawn again keeps them in."""
    return Path(report_out) / PARTS


class _Relative:
    """Rewrites the absolute paths of this machine (under the directory the pipeline ran from)
    as paths relative to it."""

    def __init__(self) -> None:
        self.prefix = str(Path.cwd().resolve()) + os.sep

    def text(self, s: str) -> str:
        return s.replace(self.prefix, "")

    def json(self, value: Any) -> Any:
        if isinstance(value, str):
            return self.text(value)
        if isinstance(value, list):
            return [self.json(v) for v in value]
        if isinstance(value, dict):
            return {self.text(k): self.json(v) for k, v in value.items()}
        return value


def keep_part(part: str, stages: list[dict[str, Any]], evals: dict[str, Path], index_stages: list[Path],
              root: Path, run: dict[str, Any]) -> Path:
    """Write part ``part``'s results under ``root / part`` (published whole); returns the folder.

    ``stages`` are the part's stage records (as the pipeline's state holds them), ``evals`` each
    evaluation stage's output folder by stage name, ``index_stages`` the indexes its index stages
    made (a report may read one no evaluation names: Fig. 4d's), ``run`` the part's run (wall
    time, whether it started from nothing, machine)."""
    rel = _Relative()
    final = root / part
    work = root / f".{part}.partial"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    indexes = {str(p): Path(p).name for p in index_stages}  # an index folder → its name under indexes/
    for name, folder in evals.items():
        dst = work / "evals" / name
        dst.mkdir(parents=True)
        for table in TABLES:
            if (folder / table).is_file():
                _copy_table(folder / table, dst / table, rel, indexes, final)
        if (folder / "queries.parquet").is_file():
            _copy_table(folder / "queries.parquet", dst / "queries.parquet", rel, indexes, final, CURVE_COLUMNS)
        (dst / "eval.json").write_text(json.dumps(rel.json(json.loads((folder / "eval.json").read_text())),
                                                  indent=1))
        write_manifest(dst)  # a kept evaluation checks out as any evaluation does, for the report that reads it
    for folder, kept in indexes.items():
        _keep_index(Path(folder), work / "indexes" / kept, rel)
        write_manifest(work / "indexes" / kept)
    weight = sum(f.stat().st_size for f in work.rglob("*") if f.is_file())
    record = {"part": part, "stages": rel.json(stages), "run": rel.json(run), "kept_bytes": weight}
    if (final / "part.json").is_file():
        record["as_kept_before"] = as_kept_before(work, final)
    (work / "part.json").write_text(json.dumps(record, indent=1, sort_keys=True))
    old = root / f".{part}.previous"
    shutil.rmtree(old, ignore_errors=True)
    if final.exists():
        final.rename(old)
    work.rename(final)
    shutil.rmtree(old, ignore_errors=True)
    return final


def as_kept_before(new: Path, old: Path) -> dict[str, Any]:
    """How the result rows of part folder ``new`` compare with those of ``old``, the one it
    replaces: per evaluation, its rows, how many equal a row kept before in every column the run
    computed (times aside), and the methods of the others; with the run that kept ``old``."""
    try:
        before = json.loads((old / "part.json").read_text()).get("run", {})
    except (OSError, ValueError):
        before = {}
    evals = {}
    for folder in sorted((new / "evals").iterdir()):
        rows = pd.read_parquet(folder / "results.parquet")
        try:
            kept = pd.read_parquet(old / "evals" / folder.name / "results.parquet")
        except (OSError, ValueError):  # not kept before, or unreadable: nothing to compare with
            kept = rows.iloc[:0]
        cols = [c for c in rows.columns if c in kept.columns and not c.startswith(MEASURED)]
        same = np.zeros(len(rows), bool) if not cols else rows[cols].merge(
            kept[cols].drop_duplicates(), on=cols, how="left", indicator=True)["_merge"].eq("both").to_numpy()
        evals[folder.name] = {"rows": len(rows), "same": int(same.sum()),
                              "differing": {str(k): int(v) for k, v in rows.method[~same].value_counts().items()}}
    return {"run": {k: before.get(k) for k in ("commit", "started", "cpu")}, "evals": evals}


def reproduction_lines(record: dict[str, Any]) -> list[str]:
    """``eval-1M: 6,426 of 6,426 result rows as kept before (times aside)``, one line an evaluation
    of a part kept again (none for a part kept the first time)."""
    found = record.get("as_kept_before")
    if not found:
        return []
    lines = []
    for name, e in found["evals"].items():
        line = f"{name}: {e['same']:,} of {e['rows']:,} result rows as kept before (times aside)"
        if e["differing"]:
            line += "; differing: " + ", ".join(f"{m} {n:,}" for m, n in e["differing"].items())
        lines.append(line)
    return lines


def _copy_table(src: Path, dst: Path, rel: _Relative, indexes: dict[str, str], final: Path,
                columns: tuple[str, ...] | None = None) -> None:
    """A results table with its paths made relative: an ``index`` column names the kept copy of
    the index (``<final>/indexes/<name>``), registered in ``indexes``; a ``store`` column and the
    provenance in the file's metadata lose this machine's prefix."""
    names = pq.read_schema(src).names
    table = pq.read_table(src, columns=[c for c in columns if c in names] if columns else None)
    for i, field in enumerate(table.schema):
        if field.name == "index":
            paths = table.column(i).to_pylist()
            for p in {p for p in paths if p}:
                indexes.setdefault(p, Path(p).name)
            kept = [None if p is None else rel.text(str(final / "indexes" / indexes[p])) for p in paths]
            table = table.set_column(i, field.name, pa.array(kept, pa.string()))
        elif field.name == "store" and pa.types.is_string(field.type):
            table = table.set_column(i, field.name, pa.array([None if v is None else rel.text(v)
                                                              for v in table.column(i).to_pylist()], pa.string()))
    meta = {k: rel.text(v.decode()).encode() for k, v in (table.schema.metadata or {}).items()}
    pq.write_table(table.replace_schema_metadata(meta), dst, compression="zstd")


def _keep_index(src: Path, dst: Path, rel: _Relative) -> None:
    """What the report reads of an index: its metadata, its components, and its files' bytes."""
    dst.mkdir(parents=True)
    if (src / "index.json").is_file():
        (dst / "index.json").write_text(json.dumps(rel.json(json.loads((src / "index.json").read_text())), indent=1))
    if (src / "components.parquet").is_file():
        shutil.copyfile(src / "components.parquet", dst / "components.parquet")
    sizes = {str(f.relative_to(src)): f.stat().st_size for f in sorted(src.rglob("*"))
             if f.is_file() and f.relative_to(src).parts[0] != "eval" and ".previous" not in str(f.relative_to(src))}
    (dst / "files.json").write_text(json.dumps(sizes, indent=1, sort_keys=True))  # what report.KEPT_SIZES reads


def kept_stages(root: Path) -> dict[str, tuple[dict[str, Any], dict[str, Any]]]:
    """What every kept part holds, by stage name: ``(record, outputs)``, the stage's record as
    its part kept it and where its kept results are (an evaluation's folder, an index's copy)."""
    found: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {}
    for record_file in sorted(root.glob("*/part.json")):
        folder = record_file.parent
        for stage in json.loads(record_file.read_text())["stages"]:
            outputs = dict(stage.get("outputs") or {})
            if (folder / "evals" / stage["name"]).is_dir():
                outputs["eval"] = str(folder / "evals" / stage["name"])
            if outputs.get("index") and (folder / "indexes" / Path(outputs["index"]).name).is_dir():
                outputs["index"] = str(folder / "indexes" / Path(outputs["index"]).name)
            found.setdefault(stage["name"], (stage, outputs))
    return found
