"""``vprscale sql``: a read-only, sandboxed DuckDB console over an index directory.

Views: ``lists(hash, ref_id)``, ``buckets(hash, size, best_id, offset)``,
``model(component, cluster, centre, refs, share, variance)``, and ``results`` /
``queries`` when ``vprscale eval`` output sits in the index's ``eval/`` folder.

The sandbox: the views are Arrow datasets handed to DuckDB by this process, so DuckDB
itself needs no file access at all and has it switched off (no path is ever written into
SQL); its only allowed directory is a fresh, empty spill directory of its own (DuckDB
would otherwise allow ``<cwd>/.tmp``), removed afterwards; memory, threads and spill size
are capped; exactly one SELECT (or WITH … SELECT) statement runs, after the configuration
is locked; and a timeout interrupts it, and abandons it if it does not stop.
"""

from __future__ import annotations

import io
import json
import shutil
import sys
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import duckdb
import pyarrow.csv as pacsv
import pyarrow.dataset as pads

from vprscale.core.errors import InputError
from vprscale.method.indexfile import load_index_meta

GRACE_S = 5.0  # how long an interrupted query may take to stop before it is abandoned


def _views(index: Path) -> dict[str, Path]:
    views = {"lists": index / "lists.parquet", "buckets": index / "buckets.parquet",
             "model": index / "components.parquet"}
    for name in ("results", "queries"):
        f = index / "eval" / f"{name}.parquet"
        if f.is_file():
            views[name] = f
    return views


@contextmanager
def connect(index: str | Path, memory_limit: str = "2GB", threads: int = 2,
            spill_limit: str = "2GB") -> Iterator[duckdb.DuckDBPyConnection]:
    """An in-memory connection with the index views, locked down (see the module's docstring)."""
    root = Path(index).resolve()
    load_index_meta(root)
    spill = tempfile.mkdtemp(prefix="vprscale-sql-")
    con = duckdb.connect(":memory:")
    try:
        for name, path in _views(root).items():
            try:
                con.register(name, pads.dataset(path, format="parquet"))
            except (OSError, ValueError) as exc:  # pyarrow's errors for missing or damaged files
                raise InputError(f"{path}: cannot be read as Parquet ({str(exc).splitlines()[0]})") from None
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
        shutil.rmtree(spill, ignore_errors=True)


def check_statement(con: duckdb.DuckDBPyConnection, query: str) -> None:
    """Refuse anything but a single SELECT statement."""
    try:
        statements = con.extract_statements(query)
    except duckdb.Error as exc:
        raise InputError(f"query: cannot parse: {exc}") from None
    if len(statements) != 1:
        raise InputError(f"query: exactly one statement is allowed, got {len(statements)}")
    kind = statements[0].type
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


def format_table(table, fmt: str) -> str:
    if fmt == "csv":
        buf = io.BytesIO()
        pacsv.write_csv(table, buf)
        return buf.getvalue().decode()
    if fmt == "json":
        return "".join(json.dumps(row, default=str) + "\n" for row in table.to_pylist())
    cols = table.column_names
    rows = [[str(v) for v in row.values()] for row in table.to_pylist()]
    widths = [max([len(c)] + [len(r[i]) for r in rows]) for i, c in enumerate(cols)]
    line = "  ".join(c.rjust(w) for c, w in zip(cols, widths, strict=True))
    body = ["  ".join(v.rjust(w) for v, w in zip(r, widths, strict=True)) for r in rows]
    return "\n".join([line, "  ".join("-" * w for w in widths), *body, f"({len(rows)} rows)"]) + "\n"


def run_sql(index: str | Path, query: str, fmt: str = "table", timeout: float = 30.0, memory_limit: str = "2GB",
            threads: int = 2) -> str:
    """One read-only query over an index, formatted as a table, CSV or JSON lines."""
    with connect(index, memory_limit, threads) as con:
        return format_table(query_table(con, query, timeout), fmt)


def shell(index: str | Path, timeout: float = 30.0, memory_limit: str = "2GB", threads: int = 2) -> int:
    """An interactive console: statements end with ';', an empty line or EOF quits."""
    with connect(index, memory_limit, threads) as con:
        print(f"vprscale sql on {index}: views {', '.join(_views(Path(index).resolve()))}; end with ';'",
              file=sys.stderr)
        buf: list[str] = []
        while True:
            try:
                line = input("sql> " if not buf else "...> ")
            except EOFError:
                return 0
            if not line.strip() and not buf:
                return 0
            buf.append(line)
            if line.rstrip().endswith(";"):
                query, buf = "\n".join(buf), []
                try:
                    print(format_table(query_table(con, query, timeout), "table"), end="")
                except InputError as exc:
                    print(f"error: {exc}", file=sys.stderr)
