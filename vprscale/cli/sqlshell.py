"""``vprscale sql INDEX`` without a statement: an interactive shell over the sandbox, as DuckDB's and
psql's shells behave.

Line editing and a history kept across sessions (GNU readline, where Python has it), statements
ending with ``;`` (an empty line continues or does nothing; Ctrl-D or ``.quit`` leaves), Ctrl-C
cancelling the line being typed or the statement running (the sandbox stays up), the engine's
whole error text with its context lines, and results cut to a row and column limit
(``.maxrows``, ``.maxwidth``).
"""

from __future__ import annotations

import os
import shutil
import sys
from collections.abc import Callable
from pathlib import Path

from vprscale.core.errors import InputError
from vprscale.evaluation.sql import Sandbox, format_table
from vprscale.evaluation.sqlchild import views

MAX_ROWS = 40  # DuckDB's shell shows 40 rows by default
HISTORY_LINES = 2000
HELP = """.help            this text
.tables          the views and what they hold
.maxrows N       rows shown of a result (0: all; default 40)
.maxwidth N      characters a result may take (0: no limit; default: the terminal's width)
.quit            leave (or Ctrl-D)
Statements end with ';' and may span lines. Ctrl-C cancels the line or the running statement."""


def history_file() -> Path:
    """``$VPRSCALE_SQL_HISTORY``, else ``$XDG_STATE_HOME/vprscale/sql_history`` (``~/.local/state``)."""
    env = os.environ.get("VPRSCALE_SQL_HISTORY")
    if env:
        return Path(env)
    state = Path(os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state")
    return state / "vprscale" / "sql_history"


def _line_editing() -> Callable[[], None]:
    """Readline's editing and history where Python has it; returns what saves the history."""
    try:
        import readline
    except ImportError:  # a Python built without readline: plain input(), no history
        return lambda: None
    path = history_file()
    try:
        readline.read_history_file(path)
    except OSError:
        pass
    readline.set_history_length(HISTORY_LINES)

    def save() -> None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            readline.write_history_file(path)
        except OSError:  # an unwritable home: the session's history is simply not kept
            pass

    return save


class Shell:
    def __init__(self, box: Sandbox, roots: list[Path], timeout: float) -> None:
        self.box, self.roots, self.timeout = box, roots, timeout
        self.max_rows: int | None = MAX_ROWS
        self.max_width: int | None = shutil.get_terminal_size().columns

    def command(self, line: str) -> bool:
        """A dot command; False when it asks to leave."""
        word, _, arg = line.strip().partition(" ")
        if word in (".quit", ".exit", "\\q"):
            return False
        if word in (".maxrows", ".maxwidth") and arg.strip().isdigit():
            value = int(arg) or None
            if word == ".maxrows":
                self.max_rows = value
            else:
                self.max_width = value
        elif word == ".tables":
            for name, files in views(self.roots).items():
                print(f"{name:<10} {', '.join(map(str, files))}")
                try:  # the view's columns, from an empty result of it (the names are ours, not typed)
                    schema = self.box.query(f"SELECT * FROM {name} LIMIT 0", self.timeout).schema
                except InputError as exc:
                    print(f"{'':<10} (its columns cannot be read: {exc})")
                    continue
                print(f"{'':<10} " + ", ".join(f"{f.name} {f.type}" for f in schema))
        else:
            print(HELP if word == ".help" else f"unknown command {word}; .help lists them", file=sys.stderr)
        return True

    def run(self, query: str) -> None:
        try:
            table = self.box.query(query, self.timeout)
        except KeyboardInterrupt:
            self.box.cancel()
            print("cancelled", file=sys.stderr)
            return
        except InputError as exc:  # a QueryError also has the engine's context lines
            detail = getattr(exc, "detail", "")
            print(f"error: {exc}" + (f"\n{detail}" if detail else ""), file=sys.stderr)
            return
        print(format_table(table, "table", self.max_rows, self.max_width), end="")

    def loop(self) -> int:
        buf: list[str] = []
        while True:
            try:
                line = input("sql> " if not buf else "...> ")
            except EOFError:
                print(file=sys.stderr)
                return 0
            except KeyboardInterrupt:  # the line (and any statement being typed) is dropped
                print("^C", file=sys.stderr)
                buf = []
                continue
            if not buf and line.lstrip().startswith((".", "\\")):
                if not self.command(line):
                    return 0
                continue
            if not line.strip() and not buf:
                continue
            buf.append(line)
            if line.rstrip().endswith(";"):
                query, buf = "\n".join(buf), []
                _one_history_entry(query)
                self.run(query)


def _one_history_entry(statement: str) -> None:
    """A statement typed over several lines comes back from the history as one entry (readline
    keeps each line apart: the up arrow would bring back a lone ``;``)."""
    lines = statement.count("\n") + 1
    try:
        import readline
    except ImportError:
        return
    if lines < 2 or readline.get_current_history_length() < lines:
        return
    for _ in range(lines):
        readline.remove_history_item(readline.get_current_history_length() - 1)
    readline.add_history(" ".join(part.strip() for part in statement.splitlines()))


def shell(paths: list[str], timeout: float = 30.0, memory_limit: str = "2GB", threads: int = 2) -> int:
    """The interactive console over an index and evaluation folders (see the module's text)."""
    roots = [Path(p).resolve() for p in paths]
    box = Sandbox(paths, memory_limit, threads)
    save = _line_editing()
    try:
        print(f"vprscale sql on {', '.join(map(str, roots))}: views {', '.join(views(roots))}. End statements with "
              "';'; .help for help, Ctrl-D to leave.", file=sys.stderr)
        return Shell(box, roots, timeout).loop()
    finally:
        save()
        box.close()
