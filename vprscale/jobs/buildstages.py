"""A pipeline's build stage in each of the three forms ``vprscale build`` takes: a recipe
(``scale``), your own descriptors (``ref``, ``query``, ``gt``, …; docs/bring-your-own.md) and
MSLS as it is laid out (``msls``, ``cities``, ``descriptors``). The key that names the form
chooses it; every other key is the form's command-line flag (``ref_pos`` is ``--ref-pos``, a
list is the flag repeated), so a stage reads as the command it runs.

What a build of your own data or of MSLS reads besides its keys is every file they name, and
those files are its inputs: each file's SHA-256 (every file of a folder; of MSLS, the chosen
cities' tables, not their images) is part of the stage's fingerprint, so a changed byte re-runs
the build and what reads it, and a missing file is refused before anything runs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from vprscale.core.digests import DigestCache
from vprscale.core.errors import InputError
from vprscale.core.objects import is_url
from vprscale.dataset.msls import SIDES, city_folder
from vprscale.dataset.own import NAME
from vprscale.dataset.sources.rows import open_rows

# the keys of each form, by the key that chooses it
FORMS: dict[str, tuple[str, ...]] = {
    "scale": ("scale", "source", "deep1b", "base", "fas", "fas_dim", "rescale"),
    "ref": ("ref", "query", "gt", "gt_radius_m", "part", "ref_pos", "query_pos", "ref_seq", "query_seq", "stride"),
    "msls": ("msls", "cities", "descriptors", "keys", "gt_radius_m"),
}
_WORDS = {"scale": "from a recipe ('scale')", "ref": "of your own descriptors ('ref')", "msls": "of MSLS ('msls')"}
# the types of the forms' keys (pipeline.SCHEMA's build keys)
KEYS: dict[str, tuple[str, bool]] = {
    "scale": ("str", False), "source": ("stage", False), "deep1b": ("str", False), "base": ("str", False),
    "fas": ("str", False), "fas_dim": ("int", False), "rescale": ("bool", False),
    "ref": ("str", False), "query": ("list[str]", False), "gt": ("list[str]", False), "gt_radius_m": ("float", False),
    "part": ("list[str]", False), "ref_pos": ("str", False), "query_pos": ("list[str]", False),
    "ref_seq": ("str", False), "query_seq": ("list[str]", False), "stride": ("int", False),
    "msls": ("str", False), "cities": ("list[str]", False), "descriptors": ("str", False), "keys": ("str", False),
}
_ROWS = ("ref", "query", "descriptors")  # rows in any --ref form, by path or URL
_FILES = ("gt", "part", "ref_pos", "query_pos", "ref_seq", "query_seq", "keys")  # local files


def form(params: dict[str, Any]) -> str:
    """The key that chooses a build stage's form: ``scale``, ``ref`` or ``msls``."""
    return next(k for k in FORMS if k in params)


def check_build(where: str, params: dict[str, Any]) -> None:
    """One form, only its keys, and the keys its command needs (the types are checked already)."""
    chosen = [k for k in FORMS if k in params]
    if len(chosen) != 1:
        given = f", not {' and '.join(repr(k) for k in chosen)}" if chosen else ""
        raise InputError(f"{where}: give one of 'scale' (a recipe), 'ref' (your own descriptors) or 'msls' "
                         f"(MSLS as it is laid out){given}")
    keys = FORMS[chosen[0]]
    stray = [k for k in params if k not in keys]
    if stray:
        raise InputError(f"{where}: key '{stray[0]}' is not an option of a build {_WORDS[chosen[0]]} "
                         f"(its keys: {', '.join(keys)})")
    positions = {"ref_pos", "query_pos"} <= set(params)  # the truth follows from them where 'gt' is not given
    if chosen[0] == "ref" and not (params.get("query") and (params.get("gt") or positions)):
        raise InputError(f"{where}: your own descriptors need 'query', and 'gt' or 'ref_pos' with 'query_pos'")
    if chosen[0] == "msls" and not (params.get("cities") and params.get("descriptors")):
        raise InputError(f"{where}: an MSLS build needs 'cities' and 'descriptors'")


def check_stores(where: str, builds: list[tuple[str, dict[str, Any]]]) -> None:
    """No two build stages write one store (``<out>/<name>.zarr``): a store of your own descriptors
    or of MSLS is named for its stage, a recipe's for its scale."""
    seen: dict[str, str] = {}
    for stage, params in builds:
        name = params["scale"] + ("" if params.get("rescale", True) else "-norescale") if form(
            params) == "scale" else stage
        if name in seen:
            raise InputError(f"{where}: stages '{seen[name]}' and '{stage}' both write {name}.zarr (a store of your "
                             "own descriptors or of MSLS is named for its stage)")
        seen[name] = stage


def build_command(params: dict[str, Any], stage: str, out: Path) -> list[str]:
    """The ``vprscale build`` arguments of a build of your own descriptors or of MSLS; the store is
    ``<out>/<stage>.zarr``, named for the stage (:func:`check_stores`: no other writes it)."""
    cmd = ["build"]
    for key in FORMS[form(params)]:
        if key not in params:
            continue
        value = params[key]
        flag = "--" + key.replace("_", "-")
        if key == "cities":
            cmd += [flag, ",".join(value)]
        else:
            cmd += [a for v in (value if isinstance(value, list) else [value]) for a in (flag, str(v))]
    return cmd + ["--name", stage, "--out", str(out), "--force"]


def build_inputs(where: str, params: dict[str, Any], digests: DigestCache) -> dict[str, Any]:
    """The content of every file a build of your own descriptors or of MSLS names, by key."""
    found: dict[str, Any] = {}
    for key in (*_ROWS, *_FILES):
        for spec in params[key] if isinstance(params.get(key), list) else [params[key]] if key in params else []:
            found[f"{key}:{spec}"] = _content(f"{where}: key '{key}'", key, spec, digests)
    if "msls" in params:
        root = Path(params["msls"])
        found["msls"] = {f"{city}/{side}/{table.name}": digests.digest(table)
                         for city in params["cities"] for side in SIDES
                         for table in sorted((city_folder(root, city) / side).glob("*.csv"))}
    return found


def _content(where: str, key: str, spec: str, digests: DigestCache) -> Any:
    """A ``[NAME=]PATH`` key's file by content: its digest, every file's of a folder; rows by URL
    by their source's fingerprint (sizes and versions of the objects)."""
    name, sep, rest = spec.partition("=")
    text = rest if sep and NAME.fullmatch(name) else spec
    if is_url(text):
        if key not in _ROWS:
            raise InputError(f"{where}: {text}: give a local file (only rows are read by URL)")
        return open_rows(text).fingerprint()
    path = Path(text)
    if not path.exists() and ":" in text:  # FILE.hdf5:DATASET, FILE.parquet:COLUMN
        path = Path(text.rpartition(":")[0])
    if path.is_file():
        return digests.digest(path)
    if path.is_dir():
        return {str(f.relative_to(path)): digests.digest(f) for f in sorted(path.rglob("*")) if f.is_file()}
    raise InputError(f"{where}: {text}: no such file or folder")
