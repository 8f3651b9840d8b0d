"""The SQL console's child side: the locked-down DuckDB connection and the loop that answers
queries in the sandbox process (:class:`vprscale.evaluation.sql.Sandbox`).

Kept apart, with nothing but DuckDB, Arrow and numpy to import, so that a sandbox process
starts in a fraction of a second. The index was checked by the parent before the child starts.

An index's views are its own Parquet tables, read as they are (``lists.parquet``,
``buckets.parquet``, ``components.parquet``): what the console shows is what the DuckDB CLI,
Polars or Spark read from the same files. A filter on ``hash`` prunes their row groups.
"""

from __future__ import annotations

import re
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import duckdb
import pyarrow as pa
import pyarrow.dataset as pads

from vprscale.core.errors import InputError, QueryError

PR_SET_PDEATHSIG = 1
GRACE_S = 5.0  # how long an interrupted query may take to stop before it is abandoned


# views of every evaluation given, one table each, with a ``run`` column
RUN_TABLES = ("results", "queries", "results_m", "nn")


INDEX_VIEWS = {"lists": "lists.parquet", "buckets": "buckets.parquet", "model": "components.parquet"}


def _index_views(con: duckdb.DuckDBPyConnection, root: Path) -> None:
    """``lists``, ``buckets`` and ``model`` of one index: its tables as they are."""
    for name, file in INDEX_VIEWS.items():
        try:
            con.register(name, pads.dataset(root / file, format="parquet"))
        except (OSError, ValueError) as exc:  # pyarrow's errors for missing or damaged files
            raise InputError(f"{root / file}: an index table cannot be read ({str(exc).splitlines()[0]})") from None


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


