"""Dataset recipes (paper Table I), one TOML file per scale under ``datasets/`` (installed as the
package data ``vprscale.recipes``)."""

from __future__ import annotations

import os
import re
import tomllib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from vprscale.core.blocks import BLOCK
from vprscale.core.errors import InputError

_FIELDS: dict[str, type | tuple[type, ...]] = {
    "scale": str, "deep1b_rows_read": int, "deep1b_rows_kept": int, "fas_ref_rows": (int, str),
    "fas_query_rows": (int, str), "query_stride": int, "window": int, "dim": int, "seed": int,
    "chunk_rows": int,
}
MAX_CHUNK_ROWS = 1 << 21  # 768 MiB of 96-d float32 per array and task
_OPTIONAL: dict[str, tuple[str, ...]] = {"layout": ("full", "compact")}
_OPTIONAL_INT = ("shard_chunks",)


def recipe_dir() -> Path:
    """``$VPRSCALE_DATASETS``, else the recipes installed with vprscale (the checkout's ``datasets/``
    in an editable install, a folder of the package in a wheel)."""
    env = os.environ.get("VPRSCALE_DATASETS")
    return Path(env) if env else shipped("vprscale.recipes")


CHECKOUT_FOLDERS = {"vprscale.recipes": "datasets", "vprscale.pipelines": "pipelines"}  # as pyproject maps them


def shipped(package: str) -> Path:
    """The folder of TOML files that ships as ``package`` (recipes, pipelines): installs unpack
    package data onto disk, so it is a plain directory. Where vprscale is imported from a source
    checkout that shadows an installed copy (pytest run in the checkout), the package does not
    exist and the checkout's own folder is it."""
    from importlib.resources import files

    try:
        return Path(str(files(package)))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[2] / CHECKOUT_FOLDERS[package]


@dataclass(frozen=True)
class Recipe:
    """How one localisation dataset is made (docs/dataset.md)."""

    scale: str
    deep1b_rows_read: int
    deep1b_rows_kept: int
    fas_ref_rows: int | str
    fas_query_rows: int | str
    query_stride: int
    window: int
    dim: int
    seed: int
    chunk_rows: int
    layout: str = "full"  # "compact" keeps only what the index and the evaluation read (100M and up)
    # chunks per zarr shard (one object or file holding that many chunks, written whole by one task);
    # 1: unsharded, a file per chunk (the raw fast path of local stores)
    shard_chunks: int = 1

    @property
    def shard_rows(self) -> int:
        """Rows of one stored shard: what one writing task writes whole."""
        return self.chunk_rows * self.shard_chunks

    def fas_rows(self, which: str, available: int) -> int:
        """Rows of the FAS reference or query traverse kept ("all" or a count)."""
        want = self.fas_ref_rows if which == "ref" else self.fas_query_rows
        return available if want == "all" else int(want)

    def as_dict(self) -> dict[str, Any]:
        """The recipe as a store records it; ``shard_chunks`` only when sharded, so a store built
        before sharding existed keeps its identity."""
        d = asdict(self)
        if d["shard_chunks"] == 1:
            del d["shard_chunks"]
        return d

    @classmethod
    def from_dict(cls, data: dict[str, Any], origin: str) -> Recipe:
        for key, kind in _FIELDS.items():
            if key not in data:
                raise InputError(f"{origin}: missing key '{key}'")
            if not isinstance(data[key], kind) or isinstance(data[key], bool):
                raise InputError(f"{origin}: key '{key}' has the wrong type ({type(data[key]).__name__})")
        unknown = set(data) - set(_FIELDS) - set(_OPTIONAL) - set(_OPTIONAL_INT)
        if unknown:
            raise InputError(f"{origin}: unknown key(s) {sorted(unknown)}")
        for key, choices in _OPTIONAL.items():
            if key in data and data[key] not in choices:
                raise InputError(f"{origin}: key '{key}' must be one of {', '.join(choices)}, got {data[key]!r}")
        for key in _OPTIONAL_INT:
            if key in data and (not isinstance(data[key], int) or isinstance(data[key], bool) or data[key] < 1):
                raise InputError(f"{origin}: key '{key}' must be a positive whole number, got {data[key]!r}")
        r = cls(**{k: data[k] for k in _FIELDS}, **{k: data[k] for k in (*_OPTIONAL, *_OPTIONAL_INT) if k in data})
        for key in ("fas_ref_rows", "fas_query_rows"):
            v = getattr(r, key)
            if isinstance(v, str) and v != "all" or isinstance(v, int) and v <= 0:
                raise InputError(f"{origin}: key '{key}' must be a positive count or \"all\", got {v!r}")
        if not 0 < r.deep1b_rows_kept <= r.deep1b_rows_read:
            raise InputError(f"{origin}: deep1b_rows_kept must be in [1, deep1b_rows_read]")
        if r.window < 2 or r.window % 2:
            raise InputError(f"{origin}: window must be an even number ≥ 2, got {r.window}")
        if r.chunk_rows <= 0 or r.chunk_rows % BLOCK:
            raise InputError(f"{origin}: chunk_rows must be a positive multiple of {BLOCK}")
        if r.query_stride <= 0:
            raise InputError(f"{origin}: query_stride must be positive")
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}", r.scale) or ".." in r.scale:
            raise InputError(f"{origin}: key 'scale' must be a plain name (letters, digits, _ . -), got {r.scale!r}: "
                             "it names the store inside --out")
        if not 0 <= r.seed < 2**63:
            raise InputError(f"{origin}: key 'seed' must be in [0, 2^63), got {r.seed}")
        if r.chunk_rows > MAX_CHUNK_ROWS:
            raise InputError(f"{origin}: chunk_rows {r.chunk_rows:,} is more than {MAX_CHUNK_ROWS:,} "
                             f"(a chunk of {r.chunk_rows * r.dim * 4 / 2**30:,.0f} GiB per array and task)")
        if r.dim <= 0:
            raise InputError(f"{origin}: dim must be positive")
        if r.shard_rows > MAX_CHUNK_ROWS:
            raise InputError(f"{origin}: a shard of {r.shard_chunks} chunks of {r.chunk_rows:,} rows is more than "
                             f"{MAX_CHUNK_ROWS:,} rows (one task writes a shard whole)")
        return r


def known_scales() -> list[str]:
    return sorted(p.stem for p in recipe_dir().glob("*.toml"))


def recipe_path(scale: str) -> Path:
    """The file of a named scale (``20K``, ``1M``, …), or ``scale`` itself if it is a TOML path."""
    path = Path(scale)
    if not path.suffix == ".toml":
        named = {name.lower(): name for name in known_scales()}  # 1m, 20k: the same scales as 1M, 20K
        path = recipe_dir() / f"{named.get(scale.lower(), scale)}.toml"
        if not path.is_file():
            raise InputError(f"--scale {scale}: unknown scale; known: {', '.join(known_scales())}")
    elif not path.is_file():
        raise InputError(f"{path}: no such recipe file")
    return path


def load_recipe(scale: str) -> Recipe:
    """The recipe of a named scale (``20K``, ``1M``, …) or of a TOML file path."""
    path = recipe_path(scale)
    return Recipe.from_dict(read_toml(path, "recipe"), str(path))


def read_toml(path: Path, kind: str) -> dict[str, Any]:
    """A TOML file's contents; a missing or malformed file is an error naming it."""
    if not path.is_file():
        raise InputError(f"{path}: no such {kind} file")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: not valid TOML: {exc}") from None
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text (byte {exc.start}); TOML files are UTF-8") from None
    except RecursionError:  # the parser recurses once per level of [ or {
        raise InputError(f"{path}: arrays or tables nested too deeply to be a {kind}") from None
