"""``vprscale sql``: a read-only, sandboxed DuckDB console over an index directory.

Views: ``lists(hash, ref_id, best)``, ``buckets(hash, size, offset)``,
``model(component, cluster, centre, refs, share, variance)``, and ``results`` /
``queries`` when ``vprscale eval`` output sits in the index's ``eval/`` folder.

The sandbox: the views are Arrow datasets handed to DuckDB by this process, so DuckDB
itself needs no file access at all and has it switched off (no path is ever written into
SQL); its only allowed directory is a fresh, empty spill directory of its own (DuckDB
would otherwise allow ``<cwd>/.tmp``), removed afterwards; memory, threads and spill size
are capped; exactly one SELECT (or WITH … SELECT) statement runs, after the configuration
is locked; and a timeout interrupts it, and abandons it if it does not stop.

The console's caps hold by the operating system, not only by DuckDB's settings: every query
runs in a child process (:class:`Sandbox`) under an address-space limit, which the parent
also watches (resident memory above ``--memory-limit`` + 1 GB) and kills at the timeout
(+ 1 s), so any statement ends in time with one line, and the spill directory, made and
removed by the parent, is never left behind.
"""

from __future__ import annotations

import io
import json
import multiprocessing
import os
import re
import shutil
import stat
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from vprscale.core.errors import InputError, QueryError
from vprscale.core.plaintext import terminal
from vprscale.evaluation.results import eval_folder
from vprscale.method.indexmeta import load_index_meta


def _flat(table):
    """Nested columns (lists, maps, structs) as JSON text, which CSV can hold."""
    import pyarrow as pa

    columns = []
    for name, col in zip(table.column_names, table.columns, strict=True):
        if pa.types.is_nested(col.type):
            col = pa.array([None if v is None else json.dumps(v, default=str) for v in col.to_pylist()], pa.string())
        columns.append((name, col))
    return pa.table(dict(columns)) if columns else table


MAX_CELL = 40  # characters of a cell shown in a width-limited table (DuckDB's shell cuts long values too)
TABLE_ROWS = 200_000  # rows laid out as an aligned table at most (every cell a Python string); CSV and JSON stream
STREAM_ROWS = 65_536  # rows formatted at a time when CSV or JSON is written out


def write_table(table, fmt: str, out, max_width: int | None = None) -> None:
    """Write a result to the text stream ``out``: CSV and JSON lines a batch of rows at a time (a
    result of tens of millions of rows costs its Arrow table and one batch, not gigabytes of Python
    strings), an aligned table whole, up to ``TABLE_ROWS`` rows."""
    if fmt == "table":
        if table.num_rows > TABLE_ROWS:
            raise InputError(f"the result holds {table.num_rows:,} rows, too many to lay out as a table (at most "
                             f"{TABLE_ROWS:,}): --csv or --json write it row by row, or aggregate or LIMIT it")
        out.write(format_table(table, "table", max_width=max_width))
        return
    for start in range(0, max(table.num_rows, 1), STREAM_ROWS):
        text = format_table(table.slice(start, STREAM_ROWS), fmt)
        out.write(text if start == 0 or fmt != "csv" else text.split("\n", 1)[1])  # one header line


def format_table(table, fmt: str, max_rows: int | None = None, max_width: int | None = None) -> str:
    """A pyarrow table as CSV, JSON lines or an aligned text table.

    The text table can be limited as DuckDB's shell limits it: past ``max_rows`` rows the first
    and last halves are shown around a ``…`` row; past ``max_width`` characters long cells are cut
    and the middle columns give way to a ``…`` column. The footer says how many rows (and columns)
    there are and how many are shown.
    """
    if fmt == "csv":
        import pyarrow.csv as pacsv

        buf = io.BytesIO()
        pacsv.write_csv(_flat(table), buf)
        return terminal(buf.getvalue().decode())  # a value's escape sequence shown, never run
    if fmt == "json":
        return "".join(json.dumps(row, default=str) + "\n" for row in table.to_pylist())
    n_rows, cols = table.num_rows, list(table.column_names)
    cut = max_rows is not None and n_rows > max_rows
    head = (max_rows + 1) // 2 if cut else n_rows
    picked = table.take(list(range(head)) + list(range(n_rows - (max_rows - head), n_rows))) if cut else table
    # a cell is text on a terminal: a name holding an escape sequence shows it, never runs it
    rows = [["NULL" if v is None else terminal(v) for v in r.values()] for r in picked.to_pylist()]
    cols = [terminal(c) for c in cols]
    if cut:
        rows.insert(head, ["…"] * len(cols))
    if max_width is not None:
        rows = [[v if len(v) <= MAX_CELL else v[: MAX_CELL - 1] + "…" for v in r] for r in rows]
    widths = [max([len(c)] + [len(r[i]) for r in rows]) for i, c in enumerate(cols)]
    order = _columns_within(widths, max_width)
    line = "  ".join(_cell(cols, i, widths) for i in order)
    rule = "  ".join("-" if i < 0 else "-" * widths[i] for i in order)
    body = ["  ".join(_cell(r, i, widths) for i in order) for r in rows]
    footer = f"({n_rows:,} rows" + (f", {max_rows:,} shown" if cut else "")
    footer += (f"; {len(cols)} columns, {len(order) - 1} shown" if -1 in order else "") + ")"
    return "\n".join([line, rule, *body, footer]) + "\n"


def _columns_within(widths: list[int], max_width: int | None) -> list[int]:
    """The columns shown, by position: all of them, or as many from both ends as fit beside a
    ``…`` column (-1) in ``max_width`` characters."""
    order = list(range(len(widths)))
    if max_width is None or sum(widths) + 2 * (len(widths) - 1) <= max_width or len(widths) <= 2:
        return order
    left, right = [], []
    room = max_width - 3
    for i in range(len(widths)):
        j = i // 2 if i % 2 == 0 else len(widths) - 1 - i // 2
        if j in left or j in right or widths[j] + 2 > room:
            break
        room -= widths[j] + 2
        (left if i % 2 == 0 else right).append(j)
    return sorted(left) + [-1] + sorted(right)


def _cell(values: list[str], i: int, widths: list[int]) -> str:
    return "…" if i < 0 else values[i].rjust(widths[i])


UNITS = {"": 1, "B": 1, "KB": 10**3, "MB": 10**6, "GB": 10**9, "TB": 10**12, "KIB": 2**10, "MIB": 2**20,
         "GIB": 2**30, "TIB": 2**40}
HEADROOM = 1 << 30  # what the process may hold beyond DuckDB's own memory limit
KILL_AFTER_S = 1.0  # beyond the timeout, before the child is killed
WATCH_S = 0.05


def memory_bytes(text: str) -> int:
    """DuckDB's memory-limit syntax (``2GB``, ``300MB``, ``1.5GiB``) as bytes."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([A-Za-z]*)\s*", str(text))
    if not m or m.group(2).upper() not in UNITS or float(m.group(1)) <= 0:
        raise InputError(f"--memory-limit {text}: not a size such as 2GB or 300MB")
    return int(float(m.group(1)) * UNITS[m.group(2).upper()])


def check_sources(paths: list[Path]) -> None:
    """Each path is a complete index or evaluation folder (checked against its manifest); one index at most."""
    indexes = 0
    for p in paths:
        if (p / "index.json").is_file():
            load_index_meta(p)
            if (p / "eval" / "results.parquet").is_file():  # its evaluation, published apart
                eval_folder(p)
            indexes += 1
        elif (p / "results.parquet").is_file():
            eval_folder(p)
        else:
            raise InputError(f"{p}: neither a vprscale index nor an evaluation folder (no index.json or "
                             "results.parquet)")
    if indexes > 1:
        raise InputError("sql: one index at a time (any number of evaluation folders)")


def _spill_dir() -> str:
    """A fresh spill directory for this process, after removing those of processes that are gone
    (a killed console cannot remove its own).

    Their base, ``$TMPDIR/vprscale-sql-<uid>``, is used only when it is this user's own private
    directory (not a link, not another's, nobody else may write in it), and only this user's
    directories in it are ever removed: on a shared ``/tmp`` anyone could plant a link there."""
    import psutil

    base = Path(tempfile.gettempdir()) / f"vprscale-sql-{os.getuid()}"
    try:
        base.mkdir(mode=0o700, exist_ok=True)
        info = os.lstat(base)
    except OSError:
        info = None
    if info is None or not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid() or info.st_mode & 0o022:
        return tempfile.mkdtemp(prefix="vprscale-sql-")  # a base that is not ours: a private folder, nothing removed
    for old in base.iterdir():
        pid = old.name.split("-")[0]
        try:
            mine = stat.S_ISDIR(os.lstat(old).st_mode) and os.lstat(old).st_uid == os.getuid()
        except OSError:
            continue
        if mine and pid.isdigit() and not psutil.pid_exists(int(pid)):
            shutil.rmtree(old, ignore_errors=True)
    return tempfile.mkdtemp(prefix=f"{os.getpid()}-", dir=base)


def _serve(*args: Any) -> None:
    """The child's entry point, by name: the parent never imports DuckDB itself (the forkserver
    has it preloaded), which keeps a one-shot ``vprscale sql`` quick to start."""
    from vprscale.evaluation.sqlchild import serve

    serve(*args)


SOCKET_PATH_MAX = 107  # bytes of a Unix socket's path (sun_path, less its NUL)
SOCKET_NAME = 40  # what multiprocessing adds under its folder: /pymp-XXXXXXXX/listener-XXXXXXXX


@contextmanager
def _socket_room() -> Iterator[None]:
    """Room for the forkserver's Unix socket: multiprocessing makes it in a ``pymp-`` folder under
    ``$TMPDIR``, and a long ``$TMPDIR`` overflows the path a socket may have (Python 3.11 has no
    fallback), so every console would fail; there the folder goes under ``/tmp``."""
    base = tempfile.gettempdir()
    if len(os.fsencode(base)) + SOCKET_NAME <= SOCKET_PATH_MAX or not os.access("/tmp", os.W_OK):
        yield
        return
    before, tempfile.tempdir = tempfile.tempdir, "/tmp"
    try:
        yield
    finally:
        tempfile.tempdir = before


class Sandbox:
    """A child process holding one locked-down connection; each query runs there under OS caps.

    The child limits its own address space (its size after start-up + ``--memory-limit`` +
    1 GB); the parent watches its resident memory against the same bound and its time
    against the timeout, and kills it past either. The spill directory is the parent's.
    """

    def __init__(self, paths: str | Path | list, memory_limit: str = "2GB", threads: int = 2) -> None:
        roots = [Path(p) for p in (paths if isinstance(paths, list) else [paths])]
        check_sources(roots)  # a bad index or evaluation is one line before any child starts
        self.limit_text = memory_limit
        self.cap = memory_bytes(memory_limit) + HEADROOM
        self.args = ([str(p.resolve()) for p in roots], memory_limit, threads)
        self.spill = _spill_dir()
        self.proc = None
        self._start()

    def _start(self) -> None:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["duckdb", "pyarrow", "pyarrow.dataset", "vprscale.evaluation.sqlchild"])
        self.pipe, child = ctx.Pipe()
        self.proc = ctx.Process(target=_serve, args=(child, *self.args, self.spill, self.cap), daemon=True)
        with _socket_room():
            self.proc.start()
        child.close()
        kind, value = self._receive(60.0, "start-up")
        if kind != "ready":
            self.close()
            raise InputError(value)

    def _receive(self, seconds: float, what: str) -> tuple[str, Any]:
        """The child's answer, or an error once it is killed past ``seconds`` or its memory bound."""
        import psutil

        deadline = time.monotonic() + seconds
        child = psutil.Process(self.proc.pid)
        while not self.pipe.poll(WATCH_S):
            try:
                rss = child.memory_info().rss
            except psutil.Error:
                rss = 0
            if not self.proc.is_alive():
                self._kill()
                raise InputError(f"query: the SQL process died during the {what} (exit {self.proc.exitcode}); "
                                 f"a query past the memory limit ({self.limit_text} + 1 GB) ends so")
            if rss > self.cap:
                self._kill()
                raise InputError(f"query: stopped at the memory limit ({self.limit_text} + 1 GB)")
            if time.monotonic() > deadline:
                self._kill()
                raise InputError(f"query: stopped at the {seconds - KILL_AFTER_S:g} s timeout")
        try:
            return self.pipe.recv()
        except EOFError:
            self._kill()
            raise InputError(f"query: the SQL process died during the {what}") from None

    def query(self, query: str, timeout: float):
        """One checked statement's result as a pyarrow table (the child is restarted after a kill)."""
        if not timeout > 0:
            raise InputError(f"--timeout {timeout}: must be a positive number of seconds")
        if self.proc is None:
            self._start()
        self.pipe.send((query, timeout))
        kind, value = self._receive(timeout + KILL_AFTER_S, "query")
        if kind == "input":
            raise QueryError(value)
        import pyarrow as pa

        return pa.ipc.open_stream(value).read_all()

    def cancel(self, grace: float = 5.0) -> None:
        """Interrupt the running statement (Ctrl-C in the shell) and take its answer; a child that
        does not answer within ``grace`` seconds is killed (the next query starts another)."""
        import signal

        if self.proc is None:
            return
        try:
            os.kill(self.proc.pid, signal.SIGINT)
            if self.pipe.poll(grace):
                self.pipe.recv()
                return
        except (OSError, EOFError):
            pass
        self._kill()

    def _kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.join()
            self.proc = None

    def close(self) -> None:
        if self.proc is not None:
            try:
                self.pipe.send(None)
                self.proc.join(5.0)
            except (OSError, ValueError):
                pass
            self._kill()
        shutil.rmtree(self.spill, ignore_errors=True)


@contextmanager
def sandbox(index: str | Path | list, memory_limit: str = "2GB", threads: int = 2) -> Iterator[Sandbox]:
    box = Sandbox(index, memory_limit, threads)
    try:
        yield box
    finally:
        box.close()


def run_sql(index: str | Path | list, query: str, fmt: str = "table", timeout: float = 30.0, memory_limit: str = "2GB",
            threads: int = 2, out=None) -> str | None:
    """One read-only query over an index and/or evaluation folders, formatted as a table, CSV or JSON
    lines: returned as text, or written to the text stream ``out`` (:func:`write_table`)."""
    if not timeout > 0:
        raise InputError(f"--timeout {timeout}: must be a positive number of seconds")
    with sandbox(index, memory_limit, threads) as box:
        table = box.query(query, timeout)
    if out is None:
        return format_table(table, fmt)
    write_table(table, fmt, out)
    return None
