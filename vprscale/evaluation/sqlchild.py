"""The SQL console's child side: the locked-down DuckDB connection and the loop that answers
queries in the sandbox process (:class:`vprscale.evaluation.sql.Sandbox`).

Kept apart, with nothing but DuckDB and Arrow to import, so that a sandbox process starts in
a fraction of a second. The index was checked by the parent before the child starts.
"""

from __future__ import annotations

import shutil
import signal
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import duckdb
import pyarrow.dataset as pads

from vprscale.core.errors import InputError

PR_SET_PDEATHSIG = 1
GRACE_S = 5.0  # how long an interrupted query may take to stop before it is abandoned


RUN_TABLES = ("results", "queries")  # views of every evaluation given, one table, a ``run`` column each


def views(paths: list[Path]) -> dict[str, list[Path]]:
    """The Parquet files behind each view: an index gives ``lists``, ``buckets``, ``model`` and
    its ``eval/`` results; an evaluation folder gives ``results`` and ``queries``."""
    found: dict[str, list[Path]] = {}
    for root in paths:
        if (root / "index.json").is_file():
            for name, file in (("lists", "lists.parquet"), ("buckets", "buckets.parquet"),
                               ("model", "components.parquet")):
                found.setdefault(name, []).append(root / file)
            root = root / "eval"
        for name in RUN_TABLES:
            if (root / f"{name}.parquet").is_file():
                found.setdefault(name, []).append(root / f"{name}.parquet")
    return found


def _run_table(files: list[Path]):
    """The rows of several evaluations as one table, each with the folder it came from as ``run``."""
    import pyarrow as pa
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
        for name, files in views(roots).items():
            try:
                if name in RUN_TABLES:
                    con.register(name, _run_table(files))
                else:
                    con.register(name, pads.dataset(files[0], format="parquet"))
            except (OSError, ValueError) as exc:  # pyarrow's errors for missing or damaged files
                raise InputError(f"{files[0]}: cannot be read as Parquet ({str(exc).splitlines()[0]})") from None
        settings = [("temp_directory", spill), ("memory_limit", memory_limit), ("threads", threads),
                    ("max_temp_directory_size", spill_limit), ("enable_external_access", False),
                    ("autoinstall_known_extensions", False), ("autoload_known_extensions", False),
                    ("allow_community_extensions", False), ("lock_configuration", True)]
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
        raise InputError(f"query: stopped at the {timeout:g} s timeout")
    if isinstance(exc, duckdb.Error):
        raise InputError(f"query: {str(exc).splitlines()[0]}") from None
    if exc is not None:
        raise exc
    return box["table"]


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

    import pyarrow as pa

    try:
        with connect(index, memory_limit, threads, spill_dir=spill) as con:
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
                except InputError as exc:
                    pipe.send(("input", str(exc)))
                except (MemoryError, duckdb.OutOfMemoryException):
                    pipe.send(("input", f"query: stopped at the memory limit ({memory_limit} + 1 GB)"))
                except (duckdb.Error, pa.ArrowException) as exc:  # anything DuckDB or Arrow refuses is the query's
                    pipe.send(("input", f"query: {str(exc).splitlines()[0][:300]}"))
    except InputError as exc:
        pipe.send(("input", str(exc)))
    except (MemoryError, duckdb.OutOfMemoryException):
        pipe.send(("input", f"query: stopped at the memory limit ({memory_limit} + 1 GB)"))


