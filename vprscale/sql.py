"""``vprscale sql``: a read-only, sandboxed DuckDB console over an index directory.

Views: ``lists(hash, ref_id)``, ``buckets(hash, size, best_id, offset)``,
``model(component, cluster, centre, refs, share, variance)``, and ``results`` /
``queries`` when ``vprscale eval`` output sits in the index's ``eval/`` folder.

The sandbox: exactly one SELECT (or WITH … SELECT) statement; file access limited to the
index directory; external access off and the configuration locked before the user's
statement runs; a timeout that interrupts the query.
"""

from __future__ import annotations

import io
import json
import sys
import threading
from pathlib import Path

import duckdb
import pyarrow.csv as pacsv

from vprscale.errors import InputError
from vprscale.index import load_index_meta


def _views(index: Path) -> dict[str, Path]:
    views = {"lists": index / "lists.parquet", "buckets": index / "buckets.parquet",
             "model": index / "components.parquet"}
    for name in ("results", "queries"):
        f = index / "eval" / f"{name}.parquet"
        if f.is_file():
            views[name] = f
    return views


def connect(index: str | Path) -> duckdb.DuckDBPyConnection:
    """An in-memory connection with the index views, locked down."""
    root = Path(index).resolve()
    load_index_meta(root)
    con = duckdb.connect(":memory:")
    for name, path in _views(root).items():
        con.execute(f"CREATE VIEW {name} AS SELECT * FROM read_parquet('{path.as_posix()}')")
    con.execute(f"SET allowed_directories = ['{root.as_posix()}/']")
    con.execute("SET enable_external_access = false")
    con.execute("SET autoinstall_known_extensions = false")
    con.execute("SET autoload_known_extensions = false")
    con.execute("SET parquet_metadata_cache = true")  # repeated look-ups skip re-reading the footers
    con.execute("SET lock_configuration = true")
    return con


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
    """Run a checked statement with a timeout; returns a pyarrow table."""
    check_statement(con, query)
    timer = threading.Timer(timeout, con.interrupt)
    timer.start()
    try:
        return con.sql(query).to_arrow_table()
    except duckdb.InterruptException:
        raise InputError(f"query: interrupted after the {timeout:g} s timeout") from None
    except duckdb.Error as exc:
        raise InputError(f"query: {str(exc).splitlines()[0]}") from None
    finally:
        timer.cancel()


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


def run_sql(index: str | Path, query: str, fmt: str = "table", timeout: float = 30.0) -> str:
    """One read-only query over an index, formatted as a table, CSV or JSON lines."""
    with connect(index) as con:
        return format_table(query_table(con, query, timeout), fmt)


def shell(index: str | Path, timeout: float = 30.0) -> int:
    """An interactive console: statements end with ';', an empty line or EOF quits."""
    with connect(index) as con:
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
