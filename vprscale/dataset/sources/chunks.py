"""A folder (or object-storage prefix) of chunk files read as one array: which files, in which order.

Shard writers number their files (``emb_0.npy`` … ``emb_12.npy``, ``base_00`` … ``base_36``,
``part-0001.parquet``); the rows are the files' rows one after the other, in name order with
numbers compared as numbers. A chunk that is missing or unreadable would not shorten the array
alone: every row after it, and every ground-truth id that points past it, would name another
row. So a name that cannot be read (a link to nothing, a link loop, a folder where a chunk
should be) and a gap in a numbered run are errors naming it, never skipped.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

from vprscale.core.errors import InputError

_NUMBER = re.compile(r"(\d+)")


def natural_order(path: Path | str) -> list:
    """Name order with numbers compared as numbers (``emb_2`` before ``emb_10``), as shard writers number them."""
    return [int(part) if part.isdigit() else part for part in _NUMBER.split(Path(path).name)]


def check_numbering(where: str, names: list[str]) -> None:
    """Refuse a numbered run of chunk names (one template, the last number counting up) with a
    gap, naming the first name missing. Names of different templates are a set, not a run."""
    if len(names) < 2:
        return
    parts = [_NUMBER.split(name) for name in names]
    template = {tuple(p[0::2]) for p in parts}
    if len(template) != 1 or len(parts[0]) < 3:
        return
    fixed = {tuple(p[1:-2:2]) for p in parts}  # every number but the last: the same in every name
    if len(fixed) != 1:
        return
    numbers = [int(p[-2]) for p in parts]
    for a, b, name in zip(numbers, numbers[1:], names, strict=False):
        if b != a + 1:
            head = _NUMBER.split(name)
            width = len(head[-2])
            missing = "".join(head[:-2]) + f"{a + 1:0{width}d}" + head[-1]
            raise InputError(f"{where}: chunk {missing} is missing (the chunks go from {names[0]} to {names[-1]}); "
                             "every row after it would be read as another row")


def local_chunks(folder: Path, suffix: str = "", what: str = "chunk files") -> list[Path]:
    """The chunk files of ``folder`` whose names end in ``suffix`` (hidden names left out), in
    natural order: each a readable file (a dangling or looping link, or a folder, is an error
    naming it) and, numbered, without a gap."""
    found = sorted((p for p in _listed(folder) if p.name.endswith(suffix) and not p.name.startswith(".")),
                   key=natural_order)
    if not found:
        raise InputError(f"{folder}: the directory holds no {what}")
    for p in found:
        if not p.is_file():
            why = ("a symbolic link to nothing, or a loop of links" if p.is_symlink() and not p.exists()
                   else "not a file")
            raise InputError(f"{p}: {why}, where a chunk of {folder} is expected; remove it or fix it")
    check_numbering(str(folder), [p.name for p in found])
    return found


def _listed(folder: Path) -> Iterable[Path]:
    try:
        return list(folder.iterdir())
    except OSError as exc:
        raise InputError(f"{folder}: cannot be listed ({exc.strerror})") from None
