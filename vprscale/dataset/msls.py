"""Mapillary Street-Level Sequences (MSLS) as it is laid out on disk, read for a store.

MSLS (mapillary/mapillary_sls) keeps each city under ``ROOT/train_val/<city>`` (or
``ROOT/test/<city>``, without positions), with a ``database`` and a ``query`` folder, each
holding:

- ``seq_info.csv``: one row per image, in sequence order: ``key``, ``frame_number``,
  ``sequence_key``. This order is the store's row order: a window is rows next to each other;
- ``postprocessed.csv`` (train_val): ``easting``, ``northing`` in metres (UTM), ``night``,
  ``view_direction``, … one row per image, in the same order;
- ``raw.csv`` (train_val): ``pano``, whether the image is a panorama (left out as a window's
  centre, as MSLS's evaluation leaves them out);
- ``subtask_index.csv``: ``all``, ``s2w``, ``w2s``, ``o2n``, ``n2o``, ``d2n``, ``n2d``, whether the
  image belongs to each subtask (summer to winter, old to new, day to night, …).

Each side of the chosen cities is read here into arrays, one row per image, the cities one
after another: keys, sequence ids (numbered over all cities), frame numbers, the city, the
panorama flag, the subtasks as bits and the positions. Nothing else of vprscale reads this
layout.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.errors import InputError

SIDES = ("database", "query")
SUBTASKS = ("all", "s2w", "w2s", "o2n", "n2o", "d2n", "n2d")  # bit i of a row's subtask byte
SPLITS = ("train_val", "test")


@dataclass
class Side:
    """One side (``database`` or ``query``) of the chosen cities, a row per image in MSLS's order."""

    key: Any  # pyarrow string array: the image keys, as MSLS names them
    sequence: np.ndarray  # int64: the sequence (``sequence_key``), numbered over every city
    frame: np.ndarray  # int64: ``frame_number``
    city: np.ndarray  # uint16: index into the cities
    pano: np.ndarray  # bool: a panorama (never a window's centre)
    subtask: np.ndarray  # uint8: bit i set when the image belongs to SUBTASKS[i]
    pos: np.ndarray | None  # float64 (n, 2): easting, northing; None for test cities

    def __len__(self) -> int:
        return len(self.sequence)


def city_folder(root: Path, city: str) -> Path:
    """Where a city lives: ``ROOT/train_val/<city>`` or ``ROOT/test/<city>``."""
    for split in SPLITS:
        if (root / split / city).is_dir():
            return root / split / city
    raise InputError(f"--cities {city}: no {city} folder under {root}/train_val or {root}/test")


def parse_cities(text: str) -> list[str]:
    """``--cities cph,sf``: the names, each once."""
    cities = [c.strip() for c in text.split(",") if c.strip()]
    if not cities:
        raise InputError("--cities: give one or more city names, e.g. --cities cph,sf")
    if len(set(cities)) != len(cities):
        raise InputError(f"--cities {text}: a city is named twice")
    return cities


def _csv(path: Path, need: tuple[str, ...], optional: tuple[str, ...] = ()) -> Any:
    """The columns ``need`` (and those of ``optional`` it has) of one of MSLS's CSV files, and
    no others: MSLS's own have a dozen, and a city's millions of rows of them would be held."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    if not path.is_file():
        raise InputError(f"{path}: missing (MSLS keeps it beside every database and query folder)")
    try:
        names = pacsv.open_csv(path).schema.names
        missing = [c for c in need if c not in names]
        if missing:
            raise InputError(f"{path}: no {', '.join(missing)} column (it has {', '.join(names)})")
        keep = [c for c in (*need, *optional) if c in names]
        table = pacsv.read_csv(path, convert_options=pacsv.ConvertOptions(include_columns=keep))
    except (OSError, pa.ArrowInvalid) as exc:
        raise InputError(f"{path}: cannot be read as CSV ({str(exc).splitlines()[0]})") from None
    for name in need:
        if table[name].null_count:
            row = int(np.flatnonzero(np.asarray(table[name].is_null()))[0])
            raise InputError(f"{path}: row {row:,} has no {name}")
    return table


def _ints(path: Path, column: Any, name: str) -> np.ndarray:
    values = column.to_numpy(zero_copy_only=False)
    if not np.issubdtype(values.dtype, np.integer):
        raise InputError(f"{path}: {name} must be integers, not {values.dtype}")
    return values.astype(np.int64)


def _flags(path: Path, column: Any, name: str) -> np.ndarray:
    values = column.to_numpy(zero_copy_only=False)
    if values.dtype != bool:
        raise InputError(f"{path}: {name} must be True or False, not {values.dtype}")
    return values


def read_side(root: Path, cities: list[str], side: str) -> Side:
    """One side of the chosen cities (see the module's docstring); a missing file or column, rows
    that disagree between the files, or a key twice: one line naming the file."""
    import pyarrow as pa
    import pyarrow.compute as pc

    keys, seqs, frames, city_ids, panos, subtasks, positions = [], [], [], [], [], [], []
    for c, city in enumerate(cities):
        folder = city_folder(root, city) / side
        info = _csv(folder / "seq_info.csv", ("key", "frame_number", "sequence_key"))
        n = info.num_rows
        sub = _csv(folder / "subtask_index.csv", ("all",), SUBTASKS[1:])
        if sub.num_rows != n:
            raise InputError(f"{folder / 'subtask_index.csv'}: {sub.num_rows:,} rows, seq_info.csv has {n:,}")
        bits = np.zeros(n, np.uint8)
        for i, name in enumerate(SUBTASKS):
            if name in sub.column_names:
                bits |= _flags(folder / "subtask_index.csv", sub[name], name).astype(np.uint8) << i
        has_positions = folder.parent.parent.name == "train_val"
        if c and has_positions != bool(positions):
            raise InputError(f"--cities {','.join(cities)}: test cities (no positions) with train_val cities; "
                             "build them apart")
        pos, pano = None, np.zeros(n, bool)
        if has_positions:
            post = _csv(folder / "postprocessed.csv", ("easting", "northing"), ("key",))
            raw = _csv(folder / "raw.csv", ("pano",))
            for name, table in (("postprocessed.csv", post), ("raw.csv", raw)):
                if table.num_rows != n:
                    raise InputError(f"{folder / name}: {table.num_rows:,} rows, seq_info.csv has {n:,}")
            same = (np.asarray(pc.equal(post["key"].cast(pa.string()), info["key"].cast(pa.string())))
                    if "key" in post.column_names else None)
            if same is not None and not same.all():
                row = int(np.flatnonzero(~same)[0])
                raise InputError(f"{folder / 'postprocessed.csv'}: row {row:,} is not seq_info.csv's image")
            pos = np.stack([post["easting"].to_numpy(zero_copy_only=False),
                            post["northing"].to_numpy(zero_copy_only=False)], axis=1).astype(np.float64)
            if not np.isfinite(pos).all():
                row = int(np.flatnonzero(~np.isfinite(pos).all(axis=1))[0])
                raise InputError(f"{folder / 'postprocessed.csv'}: row {row:,} has no finite easting/northing")
            pano = _flags(folder / "raw.csv", raw["pano"], "pano")
        keys.append(info["key"].cast(pa.string()))
        seqs.append(info["sequence_key"].cast(pa.string()))
        frames.append(_ints(folder / "seq_info.csv", info["frame_number"], "frame_number"))
        city_ids.append(np.full(n, c, np.uint16))
        panos.append(pano)
        subtasks.append(bits)
        if pos is not None:
            positions.append(pos)
    key = pa.chunked_array([k for part in keys for k in part.chunks], pa.string()).combine_chunks()
    if len(pc.unique(key)) != len(key):
        counts = pc.value_counts(key)
        twice = next(v["values"] for v in counts.to_pylist() if v["counts"] > 1)
        raise InputError(f"{root}: image key {twice!r} is in the {side} twice")
    seq_keys = pa.chunked_array([k for part in seqs for k in part.chunks], pa.string()).combine_chunks()
    sequence = np.asarray(pc.index_in(seq_keys, pc.unique(seq_keys)), np.int64)
    return Side(key=key, sequence=sequence, frame=np.concatenate(frames), city=np.concatenate(city_ids),
                pano=np.concatenate(panos), subtask=np.concatenate(subtasks),
                pos=np.concatenate(positions) if positions else None)


def key_rows(side_keys: Any, file_keys: Any, where: str) -> np.ndarray:
    """Row of ``file_keys`` (the descriptors' keys) holding each image of ``side_keys``; a key
    missing there, or there twice, is one line naming ``where``."""
    import pyarrow as pa
    import pyarrow.compute as pc

    file_keys = file_keys.cast(pa.string())
    if len(pc.unique(file_keys)) != len(file_keys):
        counts = pc.value_counts(file_keys)
        twice = next(v["values"] for v in counts.to_pylist() if v["counts"] > 1)
        raise InputError(f"{where}: key {twice!r} is there twice")
    rows = pc.index_in(side_keys, value_set=file_keys)
    if rows.null_count:
        first = int(np.flatnonzero(np.asarray(rows.is_null()))[0])
        raise InputError(f"{where}: no descriptor for image {side_keys[first].as_py()!r} (and "
                         f"{rows.null_count - 1:,} more)" if rows.null_count > 1 else
                         f"{where}: no descriptor for image {side_keys[first].as_py()!r}")
    return np.asarray(rows, np.int64)
