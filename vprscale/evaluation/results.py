"""Every evaluation as one table: ``vprscale.load_results`` and ``vprscale results``.

An evaluation folder (``INDEX/eval`` or an ``eval --out`` folder) holds ``results.parquet``
and ``queries.parquet``; any number of them load as one pandas DataFrame, each row with the
folder it came from (``run``) and the commit and time its provenance records, so runs of
different code or days sit side by side and can be told apart.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vprscale.core.errors import InputError
from vprscale.core.manifest import check_manifest, remake
from vprscale.core.provenance import PARQUET_KEY

if TYPE_CHECKING:  # pandas is imported by what returns a DataFrame, not by ``vprscale results``
    import pandas as pd

# what ``vprscale eval`` publishes in an evaluation folder: a folder holding any of them is one
# (checked whole, and refused when incomplete), not a folder of other files
PUBLISHED = ("eval.json", "manifest.json", "results.parquet", "queries.parquet", "results_m.parquet")


def eval_folder(path: str | Path, full: bool = False) -> Path:
    """The evaluation folder a path names (itself, an index's ``eval/``, or the folder of its
    ``results.parquet``), checked against its manifest (every checksum with ``full``): what every
    reader of results opens."""
    p = Path(path)
    folder = p / "eval" if (p / "index.json").is_file() else p.parent if p.name == "results.parquet" else p
    if not (folder / "results.parquet").is_file():
        raise InputError(f"{path}: no evaluation here (no results.parquet); run vprscale eval first")
    summary = folder / "eval.json"
    try:
        record = json.loads(summary.read_text())
    except FileNotFoundError:
        raise InputError(f"{folder}: not a published evaluation (no eval.json beside results.parquet); "
                         "vprscale reads the folders vprscale eval writes") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{summary}: not readable JSON ({exc})") from None
    if not isinstance(record, dict):
        raise InputError(f"{summary}: not an evaluation's summary (a JSON object)")
    for name in ("results.parquet", "queries.parquet", "eval.json"):
        if (folder / name).is_symlink():
            raise InputError(f"{folder / name}: a symbolic link; vprscale reads nothing from outside a published "
                             "evaluation through one")
    indexes = " ".join(map(str, record.get("indexes") or ["INDEX"]))
    usual = f"vprscale eval {record.get('store', 'STORE')} {indexes} --out {folder}"
    check_manifest(folder, full=full, remake=remake(record, f"{usual} --force", published=_published(folder)))
    return folder


def _published(folder: Path) -> bool:
    """Whether the results' own Parquet metadata carries vprscale's provenance: written by a vprscale
    that publishes a manifest, so one missing is a deletion, whatever eval.json still says."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        return PARQUET_KEY in (pq.read_metadata(folder / "results.parquet").metadata or {})
    except (OSError, pa.ArrowInvalid):
        return False


def load_tables(*paths: str | Path, queries: bool = False,
                metres: bool = False) -> list[tuple[Any, Path, dict[str, Any]]]:
    """``(pyarrow table, evaluation folder, provenance record)`` of every evaluation given: its
    recall table, per-query rows (``queries``) or recall within radii in metres (``metres``)."""
    import pyarrow.parquet as pq  # here: eval_folder serves commands that never read Parquet in this process

    if not paths:
        raise InputError("results: give at least one evaluation folder or index")
    found = []
    for path in paths:
        file = eval_folder(path) / ("queries.parquet" if queries else "results_m.parquet" if metres else
                                    "results.parquet")
        if metres and not file.is_file():
            raise InputError(f"{file.parent}: no recall in metres here (results_m.parquet); evaluate a store with "
                             "positions with eval --radius-m")
        try:
            table = pq.read_table(file)
        except (OSError, ValueError) as exc:
            raise InputError(f"{file}: not a readable Parquet file ({str(exc).splitlines()[0]})") from None
        found.append((table, file.parent.resolve(), json.loads((table.schema.metadata or {}).get(PARQUET_KEY, b"{}"))))
    return found


def load_results(*paths: str | Path, queries: bool = False) -> pd.DataFrame:
    """The results (or, with ``queries``, the per-query rows) of every evaluation given, as one
    DataFrame with ``run`` (the folder), ``commit`` and ``run_time`` (from its provenance)."""
    import pandas as pd

    frames = [table.to_pandas().assign(run=str(folder), commit=record.get("commit"), run_time=record.get("time"))
              for table, folder, record in load_tables(*paths, queries=queries)]
    return pd.concat(frames, ignore_index=True)


RECIPE_NOISES = ("qm1", "qm2")  # the query sets of recipe-built stores, shown first


def noise_order(noises: Any) -> list[str]:
    """The query sets present, the recipe's QM1 and QM2 first, then the others by name."""
    found = set(noises)
    return [n for n in RECIPE_NOISES if n in found] + sorted(found - set(RECIPE_NOISES))


def main_noise(res: pd.DataFrame) -> str:
    """The query set the report's single-noise tables and figures use: QM1, else the first present."""
    order = noise_order(res.noise)
    return order[0] if order else RECIPE_NOISES[0]
