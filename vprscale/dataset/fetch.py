"""``vprscale fetch``: the real sources, or as much of them as a scale reads (docs/dataset.md).

Deep1B's ``base.1B.fbin`` is 384 GB; the 10M rung reads its first 10M rows, 3.8 GB. So the
first ``8 + 4·d·N`` bytes are fetched by ranges (:mod:`vprscale.core.ranged`: several at once,
resumable, each part checked) and the header's row count rewritten for N, as big-ann-benchmarks
crops the file; ``--format fvecs`` writes the same rows as fvecs. The remote file's size is
checked against its own header before a byte is kept, and the result is published whole with a
manifest beside it (``<file>.manifest.json``: bytes, CRC32C, source, rows): what arrived is
what was asked for, and a later reader can tell.

The default URLs are big-ann-benchmarks' (Deep1B) and none for FAS100K, whose direct file link
sits on its Mendeley Data page; ``--url`` or the environment (``VPRSCALE_DEEP1B_URL``,
``VPRSCALE_DEEP1B_QUERIES_URL``, ``VPRSCALE_FAS100K_URL``) name a mirror.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import struct
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from vprscale.core.errors import InputError
from vprscale.core.manifest import crc32c_of
from vprscale.core.objects import public
from vprscale.core.publish import check_writable, exclusive, keep_beside
from vprscale.core.ranged import Plan, download, finish, probe, read_range
from vprscale.dataset.corpora import CORPORA, check_corpus
from vprscale.dataset.sources.binfile import bin_type
from vprscale.dataset.sources.fetched import manifest_path

log = logging.getLogger(__name__)

DEEP1B = "https://storage.yandexcloud.net/yandex-research/ann-datasets/DEEP/base.1B.fbin"
DEEP1B_QUERIES = "https://storage.yandexcloud.net/yandex-research/ann-datasets/DEEP/query.public.10K.fbin"
FAS100K_PAGE = "https://data.mendeley.com/datasets/zh5g5wbcj9/1"
SOURCES = {  # what fetch knows: its default URL and the environment variable that overrides it
    "deep1b": (DEEP1B, "VPRSCALE_DEEP1B_URL"),
    "deep1b-queries": (DEEP1B_QUERIES, "VPRSCALE_DEEP1B_QUERIES_URL"),
    "fas100k": (None, "VPRSCALE_FAS100K_URL"),
    # the other corpora a recipe takes (--base): their base files, cropped to --rows as Deep1B's
    **{c.name: (c.url, f"VPRSCALE_{c.name.upper()}_URL") for c in CORPORA.values() if c.name != "deep1b"},
}
BASES = set(CORPORA)  # sources whose base file --rows crops (Deep1B's among them)
MAX_DIM = 1 << 16
CONVERT_ROWS = 1 << 18  # rows converted to fvecs at a time
SUFFIXES = {"": 1, "K": 10**3, "M": 10**6, "B": 10**9}


def parse_rows(text: str) -> int:
    """A row count: ``10000000``, ``10M``, ``1B``, ``20K`` (the scales' names mean the rows they read)."""
    m = re.fullmatch(r"\s*([0-9]+)\s*([KkMmBb]?)\s*", str(text))
    if not m or int(m.group(1)) == 0:
        raise InputError(f"--rows {text}: give a number of rows, such as 10000000 or 10M, 1B, 20K")
    return int(m.group(1)) * SUFFIXES[m.group(2).upper()]


def label(rows: int) -> str:
    """``10M`` for 10,000,000 rows: the name a cropped file carries (big-ann-benchmarks' ``base.10M.fbin``)."""
    for suffix, unit in (("B", 10**9), ("M", 10**6), ("K", 10**3)):
        if rows % unit == 0:
            return f"{rows // unit}{suffix}"
    return str(rows)


@dataclass
class FetchRequest:
    """What ``vprscale fetch`` was asked for."""

    source: str  # deep1b, deep1b-queries, fas100k, or another corpus's base file (bigann, text2image, …)
    out: Path
    rows: int | None = None  # a corpus's base file: the first rows (None: all)
    format: str = "fbin"  # a float32 base file: fbin or fvecs
    url: str | None = None  # None: the environment's, else the default
    connections: int = 4
    force: bool = False
    quiet: bool = False


def source_url(req: FetchRequest) -> str:
    default, variable = SOURCES[req.source]
    url = req.url or os.environ.get(variable) or default
    if url is None:
        page = CORPORA[req.source].terms if req.source in CORPORA else FAS100K_PAGE
        raise InputError(f"fetch {req.source}: no default URL; its file's link is on {page} (licence as "
                         f"stated there): give it with --url, or set {variable}")
    scheme = url.split(":", 1)[0].lower()
    if scheme not in ("http", "https"):
        raise InputError(f"--url {public(url)}: fetch reads http:// or https:// URLs")
    return url


def fetch(req: FetchRequest) -> dict[str, Any]:
    """Fetch one source into ``req.out``; returns the summary (and writes the manifest beside the file)."""
    if req.source not in SOURCES:
        raise InputError(f"fetch {req.source}: choose from {', '.join(SOURCES)}")
    if req.source not in BASES and req.rows is not None:
        raise InputError(f"fetch {req.source}: --rows crops a corpus's base file ({', '.join(sorted(BASES))})")
    if req.format != "fbin" and (req.source not in BASES or CORPORA[req.source].suffix != "fbin"):
        raise InputError(f"fetch {req.source}: --format fvecs rewrites float32 base files (deep1b, text2image, "
                         "turing)")
    url = source_url(req)
    check_writable(req.out)
    if req.source == "fas100k":
        size, version = probe(url)
        name, header, rows = "FAS_uniSam5_all.npz", None, None
    else:
        suffix = CORPORA[req.source].suffix if req.source in CORPORA else "fbin"
        rows, dim, size, header, version = _bin_plan(url, req.rows if req.source in BASES else None, suffix)
        base = {"deep1b": "base", "deep1b-queries": "query.public"}.get(req.source, f"{req.source}.base")
        name = f"{base}.{label(rows)}.{'fvecs' if req.format == 'fvecs' else suffix}"
        check_corpus(CORPORA.get(req.source), public(url), dim)
    out = req.out / name
    fetched = out if req.format == "fbin" else req.out / f"{base}.{label(rows)}.fbin"
    need = size * (2 if req.format == "fvecs" else 1)  # fvecs is written beside the fetched rows, then they go
    free = shutil.disk_usage(req.out).free + _held(fetched.with_name(f".{fetched.name}.partial"))
    if need > free:
        raise InputError(f"--out {req.out}: {name} needs {need / 2**30:,.1f} GiB and the disk there has "
                         f"{free / 2**30:,.1f} GiB free (--rows fetches the first rows only)")
    with exclusive(out):
        if out.exists() and not req.force:
            raise InputError(f"--out {req.out}: already holds {name}; --force fetches it again and keeps the old "
                             f"one beside, as {name}.previous")
        plan = Plan(url, fetched, size, version)
        work = download(plan, req.connections, req.quiet)
        if header is not None:
            with open(work, "r+b") as fh:
                fh.write(header)  # the crop's own row count, as big-ann-benchmarks' crop writes it
        if req.source == "fas100k":
            try:
                _check_fas(work, url)
            except InputError:
                work.unlink()  # not the file asked for: nothing of it is worth resuming
                out.with_name(f".{out.name}.parts.json").unlink(missing_ok=True)
                raise
        if req.format == "fvecs":
            work = _to_fvecs(work, out, rows, dim)
        manifest_file = manifest_path(out)
        for old in (out, manifest_file):
            if old.exists():
                keep_beside(old)
        manifest = _manifest(work, name, url, rows, req)
        _write_json(manifest_file, manifest)  # first: a file is never seen complete without it
        finish(plan, work, out)
    return {"file": str(out), **manifest}


def _held(partial: Path) -> int:
    """Disk space a resumable download already holds (its work file is sparse: only what arrived)."""
    try:
        return partial.lstat().st_blocks * 512 if partial.is_file() and not partial.is_symlink() else 0
    except OSError:
        return 0


def _bin_plan(url: str, rows: int | None, suffix: str = "fbin") -> tuple[int, int, int, bytes, str]:
    """``(rows, dim, bytes to fetch, the crop's header, the remote version)`` of a ``bin`` file
    (``.fbin``, ``.u8bin``, ``.i8bin``) at ``url``, its size checked against its header (a file
    cut short, or a header that lies, is refused here)."""
    values = bin_type(f"x.{suffix}")
    size, version = probe(url)
    n, dim = struct.unpack("<II", read_range(url, 0, 8, version))
    if n == 0 or not 0 < dim <= MAX_DIM:
        raise InputError(f"{public(url)}: not an .{suffix} file (its header says {n:,} rows of {dim:,} dimensions)")
    if size != 8 + values.itemsize * dim * n:
        raise InputError(f"{public(url)}: {size:,} bytes, but its header says {n:,} rows of {dim} {values.name}, "
                         f"{8 + values.itemsize * dim * n:,} bytes: a truncated or foreign file")
    rows = n if rows is None else rows
    if rows > n:
        raise InputError(f"--rows {rows:,}: {public(url)} holds {n:,} rows")
    return rows, dim, 8 + values.itemsize * dim * rows, struct.pack("<II", rows, dim), version


def _check_fas(work: Path, url: str) -> None:
    """The fetched FAS100K file opens as one (arrays, shapes, truth), or is refused."""
    from vprscale.dataset.sources.fas import open_fas

    try:
        open_fas(work)
    except InputError as exc:
        raise InputError(f"{public(url)}: not an FAS100K .npz ({str(exc).split(': ', 1)[-1]})") from None


def _to_fvecs(fbin: Path, out: Path, rows: int, dim: int) -> Path:
    """The rows of a fetched ``.fbin`` as fvecs (each row its dimension, then its floats), beside ``out``."""
    work = out.with_name(f".{out.name}.partial")
    src = np.memmap(fbin, dtype="<f4", mode="r", offset=8, shape=(rows, dim))
    with open(work, "wb") as fh:
        for a in range(0, rows, CONVERT_ROWS):
            block = np.asarray(src[a : a + CONVERT_ROWS])
            rec = np.empty((len(block), dim + 1), "<f4")
            rec[:, 0] = np.array([dim], "<i4").view("<f4")[0]
            rec[:, 1:] = block
            fh.write(rec.tobytes())
    del src
    fbin.unlink()
    return work


def _manifest(path: Path, name: str, url: str, rows: int | None, req: FetchRequest) -> dict[str, Any]:
    return {"file": name, "bytes": path.stat().st_size, "crc32c": crc32c_of(path), "source": public(url),
            "rows": rows, "format": req.format if req.source in BASES else None,
            "fetched": datetime.now(UTC).isoformat(timespec="seconds")}


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)
