"""A FAISS method's stored encoding of a store's references: the one on-disk format of the
compact-code comparison (written by ``vprscale encode``, read by ``vprscale eval --compare``).

An encoding lives beside its store, ``<store>.faiss/<method>/`` (``data/paper/1B.faiss/
IVF4096_PQ3/`` for ``data/paper/1B.zarr``), because it depends on the store's references
only, not on a CoarseHash index:

- ``trained.faiss``: the trained, empty FAISS index (``faiss.write_index``);
- ``codes.npy``: every reference's standalone FAISS code (``sa_code_size`` bytes: for IVF
  the list number, then the code), in id order: for any other method its index and window
  codes are rebuilt from them in one sequential read, so nothing else is stored;
- for residual IVF-PQ methods (``IVF4096,PQ3``, ``OPQ…,IVF…,PQ…``), what an evaluation
  searches and scores at 100M and 1B without holding them in memory: ``searched.faiss``,
  the index populated with every code, whose inverted lists (code and 64-bit id per place:
  11 GB at 1B for ``IVF4096,PQ3``) are FAISS's own on-disk lists in ``lists.ivfdata``
  (``OnDiskInvertedLists``, memory-mapped when read), and the window scores' records
  ``window_places.npy`` (per place its sub-quantiser indices, its list number and the 8-bit
  level of its query-independent distance term: 6 bytes for ``IVF4096,PQ3``), also
  memory-mapped;
- for an HNSW graph, ``graph.faiss``: the graph linked from every row (linking takes a core about
  half an hour at 10M; an evaluation reads it instead), its rows being ``codes.npy``
  (memory-mapped);
- ``encoding.json``: the factory, the store's identity, the number of references and the
  training rows, with the provenance of the run.

The codes of a stored encoding are the bytes an evaluation encoding in its own process
writes (the same training rows, the same blocks), so an evaluation answers the same either way.
"""

from __future__ import annotations

import ctypes
import json
import os
import re
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import faiss
import numpy as np
from faiss.contrib.ondisk import merge_ondisk

from vprscale.compared.faisscodes import FaissCodes, graph_rows
from vprscale.core.errors import InputError
from vprscale.core.localcopy import local_copy
from vprscale.core.manifest import check_manifest, remake
from vprscale.core.mapped import allocated_memmap
from vprscale.core.objects import Remote

# 2: residual IVF-PQ encodings hold their on-disk inverted lists and window arrays; 3: one window record per place
ENCODING_FORMAT = 3
LOAD_ROWS = 1 << 20  # codes added to the FAISS index (or turned into window records) at a time
SHARD_ROWS = 1 << 26  # places in one in-memory shard of the inverted lists before the on-disk merge (0.7 GB)
SEARCHED, LISTS, GRAPH = "searched.faiss", "lists.ivfdata", "graph.faiss"
WINDOW = "window_places.npy"


class _Quiet:
    """Standard output pointed at the null device while any thread is inside (encodings are
    loaded side by side): the first in points it there, the last out points it back."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.inside, self.saved, self.null = 0, -1, -1

    def enter(self) -> None:
        with self.lock:
            if self.inside == 0:
                sys.stdout.flush()
                self.saved, self.null = os.dup(1), os.open(os.devnull, os.O_WRONLY)
                os.dup2(self.null, 1)
            self.inside += 1

    def leave(self) -> None:
        with self.lock:
            self.inside -= 1
            if self.inside == 0:
                ctypes.CDLL(None).fflush(None)  # what C's stdio still buffers goes to the null device too
                os.dup2(self.saved, 1)
                os.close(self.saved)
                os.close(self.null)


_QUIET = _Quiet()


@contextmanager
def _faiss_quiet() -> Iterator[None]:
    """Silence FAISS's on-disk lists' bookkeeping ("resizing …", "IO_FLAG_ONDISK_SAME_DIR:
    updating ondisk filename …"): its C++ ``printf``s them to the process's standard output,
    which is the command's own (its table, or a pipeline's log), so standard output is pointed
    at the null device at the file-descriptor level while FAISS merges or opens the lists."""
    _QUIET.enter()
    try:
        yield
    finally:
        _QUIET.leave()


def encodings_dir(store: Path | Remote) -> Path | Remote:
    """Where the encodings of ``store`` live: ``<store without .zarr>.faiss`` beside it."""
    return store.with_name(f"{store.name.removesuffix('.zarr')}.faiss")


def encoding_dir(store: Path | Remote, factory: str) -> Path | Remote:
    """The directory of one FAISS method's encoding of ``store`` (its factory string, file-safe)."""
    return encodings_dir(store) / re.sub(r"[^A-Za-z0-9]+", "_", factory).strip("_")


def write_trained(codes: FaissCodes, out: Path, n_ref: int) -> None:
    """The trained (still empty) index, and an empty code array for ``n_ref`` references."""
    faiss.write_index(codes.index, str(out / "trained.faiss"))
    allocated_memmap(out / "codes.npy", np.uint8, (n_ref, codes.code_bytes))  # tasks map it to write


def read_trained(out: Path, factory: str, dim: int) -> FaissCodes:
    """A FaissCodes on the trained index stored in ``out`` (single-threaded: a task of a pass)."""
    codes = FaissCodes(factory, dim, k=1)
    codes.bind(faiss.read_index(str(out / "trained.faiss")))
    return codes


def describe(factory: str, identity: str, n_ref: int, train_rows: int, record: dict[str, Any]) -> dict[str, Any]:
    """The contents of ``encoding.json``."""
    return {"format": ENCODING_FORMAT, "factory": factory, "store_identity": identity, "n_ref": n_ref,
            "training_rows": train_rows, "provenance": record}


def stored_encoding(store: Path | Remote, factory: str, identity: str) -> Path | None:
    """The published encoding of ``factory`` for this store, if there is one; a stale one is refused.
    One beside a store on object storage is read from its verified copy in the cache."""
    out = encoding_dir(store, factory)
    if isinstance(out, Remote):
        if not (out / "encoding.json").is_file():
            return None
        out = local_copy(out)
    meta_file = out / "encoding.json"
    if not meta_file.is_file():
        return None
    try:
        meta = json.loads(meta_file.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{meta_file}: not readable JSON ({exc}); re-run vprscale encode with --force") from None
    if not isinstance(meta, dict) or meta.get("format") != ENCODING_FORMAT or meta.get("factory") != factory:
        raise InputError(f"{out}: not an encoding of {factory} in this version's format; re-run vprscale encode "
                         "with --force")
    if meta.get("store_identity") != identity:
        raise InputError(f"{out}: encodes another store than {store} (rebuilt since?); re-run vprscale encode "
                         "with --force")
    check_manifest(out, remake=remake(meta, f"vprscale encode {store} --compare {factory} --force", published=True))
    return out


def write_searched(out: Path, factory: str, dim: int, done: Callable[[str], bool],
                   mark: Callable[[str], None]) -> None:
    """A residual IVF-PQ encoding's searched index on on-disk lists and its window records, from
    ``codes.npy`` in ``out`` (a work copy), each step marked ``done`` once whole (resumable).

    The lists are built as FAISS builds billion-scale indexes: shards of ``SHARD_ROWS`` places
    added in memory (``add_sa_codes`` with their ids) and written, then merged into one
    on-disk list file (``merge_ondisk``); the shards are removed.
    """
    stored = np.load(out / "codes.npy", mmap_mode="r")
    n_ref = len(stored)
    shards = [out / ".work" / f"shard{i:05d}.faiss" for i in range(-(-n_ref // SHARD_ROWS))]
    for i, shard in enumerate(shards):
        if not done(shard.name):
            lo, hi = i * SHARD_ROWS, min(n_ref, (i + 1) * SHARD_ROWS)
            codes = read_trained(out, factory, dim)
            codes.inner.add_sa_codes(np.ascontiguousarray(stored[lo:hi]), np.arange(lo, hi, dtype=np.int64))
            faiss.write_index(codes.index, str(shard))
            mark(shard.name)
    if not done(SEARCHED):
        (out / LISTS).unlink(missing_ok=True)  # a merge a kill interrupted starts over
        index = read_trained(out, factory, dim).index
        with _faiss_quiet():
            merge_ondisk(index, [str(p) for p in shards], str(out / LISTS))
        faiss.write_index(index, str(out / SEARCHED))
        mark(SEARCHED)
    for shard in shards:
        shard.unlink(missing_ok=True)
    if not done("window"):
        codes = read_trained(out, factory, dim)
        codes.start(0)  # its per-list tables and an empty record array, whose width this takes
        records = allocated_memmap(out / f".{WINDOW}.tmp", np.uint8, (n_ref, codes.codes.shape[1]))
        for i in range(0, n_ref, LOAD_ROWS):
            records[i : i + LOAD_ROWS] = codes.window_records(np.ascontiguousarray(stored[i : i + LOAD_ROWS]))
        records.flush()
        (out / f".{WINDOW}.tmp").replace(out / WINDOW)
        mark("window")


def write_graph(out: Path, factory: str, dim: int, progress: Callable[[int], None] | None = None) -> None:
    """An HNSW encoding's linked graph, from the rows in ``codes.npy`` (what an evaluation
    would link in its own process: the same blocks, on one thread)."""
    stored = np.load(out / "codes.npy", mmap_mode="r")
    codes = read_trained(out, factory, dim)
    codes.start(len(stored))
    for i in range(0, len(stored), LOAD_ROWS):
        codes.add_codes(np.ascontiguousarray(stored[i : i + LOAD_ROWS]))
    codes.finish(progress)
    faiss.write_index(codes.index, str(out / f".{GRAPH}.tmp"))
    (out / f".{GRAPH}.tmp").replace(out / GRAPH)


def load_encoding(out: Path, codes: FaissCodes) -> None:
    """Give ``codes`` (a method not yet trained) the stored index and every reference's code:
    a residual IVF-PQ method its searched index on on-disk lists and its memory-mapped window
    records (nothing read until searched), a graph the linked graph in memory, whose rows the
    window scores read too (3.8 GB at 10M, held once; in memory, not memory-mapped: a graph's
    walk reads them at random, and pages evicted under memory pressure would be read again
    from disk), any other its trained index and codes in memory."""
    if (out / SEARCHED).is_file():
        with _faiss_quiet():  # publishing renamed the directory FAISS wrote the lists' path into
            index = faiss.read_index(str(out / SEARCHED), faiss.IO_FLAG_ONDISK_SAME_DIR)
        codes.attach(index, np.load(out / WINDOW, mmap_mode="r"))
        return
    if (out / GRAPH).is_file():  # the windows read the rows the graph holds (not codes.npy: not twice)
        index = faiss.read_index(str(out / GRAPH))
        codes.attach(index, graph_rows(index))
        return
    codes.bind(faiss.read_index(str(out / "trained.faiss")))
    stored = np.load(out / "codes.npy", mmap_mode="r")
    codes.start(len(stored))
    for i in range(0, len(stored), LOAD_ROWS):
        codes.add_codes(np.ascontiguousarray(stored[i : i + LOAD_ROWS]))
    codes.finish()
