"""The SQL console's child side: the locked-down DuckDB connection and the loop that answers
queries in the sandbox process (:class:`vprscale.evaluation.sql.Sandbox`).

Kept apart, with nothing but DuckDB, Arrow and numpy to import, so that a sandbox process
starts in a fraction of a second. The index was checked by the parent before the child starts.

An index's lists are not stored twice: ``buckets.parquet`` holds one row per occupied
address (its hash, list size and offset), and the ``lists`` view unnests each bucket's ids
read from the engine's own bit-packed ``ids.npy`` (:class:`PackedIds`, through the
``vprs_list`` and ``vprs_best`` functions). A filter on ``hash`` still prunes the buckets'
row groups before any id is read.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import duckdb
import numpy as np
import pyarrow as pa
import pyarrow.dataset as pads

from vprscale.core.errors import InputError, QueryError

PR_SET_PDEATHSIG = 1
GRACE_S = 5.0  # how long an interrupted query may take to stop before it is abandoned


RUN_TABLES = ("results", "queries", "results_m")  # views of every evaluation given, one table, a ``run`` column each


INDEX_VIEWS = ("lists", "buckets", "model")
SPAN_READ = 1 << 23  # bytes of ids read in one call when a batch of buckets lies close together


class PackedIds:
    """The ids of an index's ``ids.npy`` (bit-packed, :mod:`vprscale.method.succinct`), read by
    ``pread``: a memory map of a billion places' ids would count whole against the sandbox's
    address-space cap."""

    def __init__(self, path: Path, bits: int, n: int) -> None:
        with open(path, "rb") as fh:
            major, _ = np.lib.format.read_magic(fh)
            reader = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
            reader(fh)
            self.data = fh.tell()
        self.fd = os.open(path, os.O_RDONLY)
        self.bits, self.n = bits, n

    def _words(self, first: int, last: int) -> np.ndarray:
        """Words ``first … last`` (inclusive) of the packed array."""
        raw = os.pread(self.fd, 8 * (last - first + 1), self.data + 8 * first)
        return np.frombuffer(raw, np.uint64)

    def take(self, q: np.ndarray) -> np.ndarray:
        """Ids at positions ``q`` (ascending within runs; any order works)."""
        if len(q) == 0:
            return np.zeros(0, np.uint64)
        bit = q.astype(np.uint64) * np.uint64(self.bits)
        word = (bit >> np.uint64(6)).astype(np.int64)
        lo, hi = int(word.min()), int(word.max()) + 1
        if 8 * (hi - lo) <= max(SPAN_READ, 64 * len(q)):
            words = self._words(lo, hi)
            at = word - lo
        else:  # scattered buckets: each position's two words on their own
            words = np.concatenate([self._words(w, w + 1) for w in word.tolist()])
            at = np.arange(0, 2 * len(q), 2)
        shift = bit & np.uint64(63)
        value = words[at] >> shift
        carry = shift + np.uint64(self.bits) > np.uint64(64)
        value[carry] |= words[at[carry] + 1] << (np.uint64(64) - shift[carry])
        if self.bits < 64:
            value &= np.uint64((1 << self.bits) - 1)
        return value

    def lists(self, offset: pa.Array, size: pa.Array) -> pa.Array:
        """The ids of buckets ``(offset, size)``, one list each (``vprs_list``)."""
        off = np.asarray(offset.to_numpy(zero_copy_only=False), np.int64)
        n = np.asarray(size.to_numpy(zero_copy_only=False), np.int64)
        self._check(off, n)
        ends = np.cumsum(n)
        q = np.repeat(off - (ends - n), n) + np.arange(int(ends[-1]) if len(ends) else 0)
        values = pa.array(self.take(q), pa.uint64() if self.bits > 32 else pa.uint32())
        return pa.ListArray.from_arrays(pa.array(np.r_[0, ends], pa.int64()), values)

    def best(self, offset: pa.Array) -> pa.Array:
        """Each bucket's single best id, its list's first (``vprs_best``)."""
        off = np.asarray(offset.to_numpy(zero_copy_only=False), np.int64)
        self._check(off, np.ones_like(off))
        return pa.array(self.take(off), pa.uint64() if self.bits > 32 else pa.uint32())

    def _check(self, off: np.ndarray, n: np.ndarray) -> None:
        if len(off) and (off.min() < 0 or n.min() < 0 or (off + n).max() > self.n):
            raise ValueError(f"a bucket's offset and size lie outside the index's {self.n:,} ids")


def _index_views(con: duckdb.DuckDBPyConnection, root: Path) -> None:
    """``buckets``, ``lists`` and ``model`` of one index: the buckets table (``_buckets``), the
    functions that read its ids and the views over them."""
    meta = json.loads((root / "index.json").read_text())
    try:
        con.register("_buckets", pads.dataset(root / "buckets.parquet", format="parquet"))
        con.register("model", pads.dataset(root / "components.parquet", format="parquet"))
        ids = PackedIds(root / "ids.npy", int(meta["layout"]["id_bits"]), int(meta["n_ref"]))
    except (OSError, ValueError) as exc:  # pyarrow's and numpy's errors for missing or damaged files
        raise InputError(f"{root}: an index file cannot be read ({str(exc).splitlines()[0]})") from None
    id_type = "UINTEGER" if ids.bits <= 32 else "UBIGINT"
    con.create_function("vprs_list", ids.lists, ["UBIGINT", "UINTEGER"], f"{id_type}[]", type="arrow")
    con.create_function("vprs_best", ids.best, ["UBIGINT"], id_type, type="arrow")
    con.execute('CREATE VIEW buckets AS SELECT hash, size, vprs_best("offset") AS best_id, "offset" FROM _buckets')
    con.execute('CREATE VIEW lists AS SELECT hash, unnest(vprs_list("offset", size)) AS ref_id FROM _buckets')


def views(paths: list[Path]) -> dict[str, list[Path]]:
    """What stands behind each view: an index gives ``lists``, ``buckets``, ``model`` (its
    folder) and its ``eval/`` results; an evaluation folder gives ``results`` and ``queries``
    (their Parquet files)."""
    found: dict[str, list[Path]] = {}
    for root in paths:
        if (root / "index.json").is_file():
            for name in INDEX_VIEWS:
                found.setdefault(name, []).append(root)
            root = root / "eval"
        for name in RUN_TABLES:
            if (root / f"{name}.parquet").is_file():
                found.setdefault(name, []).append(root / f"{name}.parquet")
    return found


def _run_table(files: list[Path]):
    """The rows of several evaluations as one table, each with the folder it came from as ``run``."""
    import pyarrow.parquet as pq

    tables = [pq.read_table(f).append_column("run", pa.array([str(f.parent)] * pq.read_metadata(f).num_rows,
                                                             pa.string())) for f in files]
    return pa.concat_tables(tables, promote_options="permissive")


@contextmanager
def connect(paths: str | Path | list, memory_limit: str = "2GB", threads: int = 2, spill_limit: str = "2GB",
            spill_dir: str | None = None) -> Iterator[duckdb.DuckDBPyConnection]:
    """An in-memory connection with the views of an index and/or evaluation folders, locked down
    (see the module's docstring); in this process, without the OS caps of the parent's sandbox
    (benchmarks use it)."""
    roots = [Path(p).resolve() for p in (paths if isinstance(paths, list) else [paths])]
    spill = spill_dir or tempfile.mkdtemp(prefix="vprscale-sql-")
    con = duckdb.connect(":memory:")
    try:
        found = views(roots)
        for name in RUN_TABLES:
            if name in found:
                try:
                    con.register(name, _run_table(found[name]))
                except (OSError, ValueError) as exc:  # pyarrow's errors for missing or damaged files
                    raise InputError(f"{found[name][0]}: cannot be read as Parquet "
                                     f"({str(exc).splitlines()[0]})") from None
        if "lists" in found:
            _index_views(con, found["lists"][0])
        settings = [("temp_directory", spill), ("memory_limit", memory_limit), ("threads", threads),
                    ("max_temp_directory_size", spill_limit), ("enable_external_access", False),
                    ("autoinstall_known_extensions", False), ("autoload_known_extensions", False),
                    ("allow_community_extensions", False),
                    # DuckDB draws its progress bar on standard output, where a result (CSV, JSON) goes
                    ("enable_progress_bar", False), ("lock_configuration", True)]
        for name, value in settings:  # the names are ours; the values go in as bound parameters
            try:
                con.execute(f"SET {name} = ?", [value])
            except duckdb.Error as exc:
                raise InputError(f"--{name.replace('_', '-')} {value}: {str(exc).splitlines()[0]}") from None
        yield con
    finally:
        con.close()
        if spill_dir is None:
            shutil.rmtree(spill, ignore_errors=True)


def check_statement(con: duckdb.DuckDBPyConnection, query: str) -> None:
    """Refuse anything but a single SELECT statement."""
    try:
        statements = con.extract_statements(query)
    except duckdb.Error as exc:
        raise InputError(f"query: cannot parse: {exc}") from None
    if len(statements) != 1:
        raise InputError(f"query: exactly one statement is allowed, got {len(statements)}")
    try:
        kind = statements[0].type
    except ValueError:  # a statement type newer than the Python binding knows (UPDATE EXTENSIONS …)
        raise InputError("query: only SELECT statements are allowed") from None
    if kind != duckdb.StatementType.SELECT:
        raise InputError(f"query: only SELECT statements are allowed, got {kind.name}")


class Cancel:
    """Ctrl-C in the shell: the terminal's SIGINT reaches this process too (and the parent sends
    one), and interrupts the running statement instead of ending the process with a traceback."""

    def __init__(self) -> None:
        self.con: duckdb.DuckDBPyConnection | None = None
        self.asked = False

    def __call__(self, signum: int, frame: object) -> None:
        self.asked = True
        if self.con is not None:
            self.con.interrupt()


_cancel = Cancel()


def query_table(con: duckdb.DuckDBPyConnection, query: str, timeout: float):
    """Run a checked statement with a timeout; returns a pyarrow table.

    The statement runs on a daemon thread; at the timeout it is interrupted, and if it has
    not stopped ``GRACE_S`` later it is abandoned (the error is raised and the process may
    exit while DuckDB still unwinds).
    """
    if not timeout > 0:
        raise InputError(f"--timeout {timeout}: must be a positive number of seconds")
    check_statement(con, query)
    box: dict = {}
    _cancel.asked = False

    def run() -> None:
        try:
            box["table"] = con.sql(query).to_arrow_table()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
            box["error"] = exc

    worker = threading.Thread(target=run, daemon=True)
    worker.start()
    worker.join(timeout)
    if worker.is_alive():
        con.interrupt()
        worker.join(GRACE_S)
        raise InputError(f"query: stopped at the {timeout:g} s timeout")
    exc = box.get("error")
    if isinstance(exc, duckdb.InterruptException):
        raise InputError("query: cancelled" if _cancel.asked else f"query: stopped at the {timeout:g} s timeout")
    if isinstance(exc, duckdb.Error):
        raise QueryError(f"query: {with_place(str(exc).strip(), query)}") from None
    if exc is not None:
        raise exc
    return box["table"]


# Errors DuckDB words without a place in the statement, and the name in them that has one
_NAMED = re.compile(r'(?:Referenced column "([^"]+)" not found|Table with name (\S+) does not exist|'
                    r'Scalar Function with name (\S+) does not exist|Referenced table "([^"]+)" not found)')


def with_place(message: str, query: str) -> str:
    """``message`` with the line of ``query`` it is about and a caret under the place, as DuckDB's
    parser errors have (its binder and catalog errors name a column, table or function only)."""
    if "\nLINE " in message:
        return message
    found = _NAMED.search(message)
    name = found and next(g for g in found.groups() if g)
    at = re.search(rf"(?<![\w\"]){re.escape(name.rstrip('!'))}(?![\w\"])", query, re.I) if name else None
    if at is None:
        return message
    line_no = query.count("\n", 0, at.start())
    line = query.splitlines()[line_no]
    column = at.start() - (query.rfind("\n", 0, at.start()) + 1)
    prefix = f"LINE {line_no + 1}: "
    return f"{message}\n\n{prefix}{line}\n{' ' * (len(prefix) + column)}{'^' * len(at.group())}"


def serve(pipe, index: list[str], memory_limit: str, threads: int, spill: str, cap: int) -> None:
    """The child: connect, cap its own address space, then answer queries until told to stop.

    It dies with the process that started it (Linux's parent-death signal), so a killed
    console leaves no query running.
    """
    import ctypes
    import resource

    try:
        ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):  # not Linux: the parent's kill and the pipe's end still stop it
        pass

    signal.signal(signal.SIGINT, _cancel)
    try:
        with connect(index, memory_limit, threads, spill_dir=spill) as con:
            _cancel.con = con
            size = int(Path("/proc/self/statm").read_text().split()[0]) * resource.getpagesize()
            resource.setrlimit(resource.RLIMIT_AS, (size + cap, size + cap))
            pipe.send(("ready", None))
            while (request := pipe.recv()) is not None:
                query, timeout = request
                try:
                    table = query_table(con, query, timeout)
                    sink = pa.BufferOutputStream()
                    with pa.ipc.new_stream(sink, table.schema) as writer:
                        writer.write_table(table)
                    pipe.send(("ok", sink.getvalue().to_pybytes()))
                except QueryError as exc:
                    pipe.send(("input", "\n".join(filter(None, (str(exc), exc.detail)))))
                except InputError as exc:
                    pipe.send(("input", str(exc)))
                except (MemoryError, duckdb.OutOfMemoryException):
                    pipe.send(("input", f"query: stopped at the memory limit ({memory_limit} + 1 GB)"))
                except (duckdb.Error, pa.ArrowException) as exc:  # anything DuckDB or Arrow refuses is the query's
                    pipe.send(("input", f"query: {str(exc).strip()[:2000]}"))
    except InputError as exc:
        pipe.send(("input", str(exc)))
    except (MemoryError, duckdb.OutOfMemoryException):
        pipe.send(("input", f"query: stopped at the memory limit ({memory_limit} + 1 GB)"))


