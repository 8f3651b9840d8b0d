"""The ``vprscale`` command line. User errors print one line and exit with status 2; a bug in
vprscale itself prints one line and exits with status 1 (``--verbose`` adds its traceback); a job
stopped at a checkpoint by a time budget exits with 75 (more to do); a reader that closes the pipe
(``| head``) ends the command quietly with status 0.

Each command is a module of this package (``add`` declares its arguments, ``run`` does the
work), so a pipeline stage's fingerprint counts the command it runs, not every command:
changing ``vprscale sql`` re-runs no build (docs/architecture.md).
"""

from __future__ import annotations

import argparse
import difflib
import logging
import os
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Sequence

from vprscale.cli import (
    bench,
    build,
    encode,
    eval,
    fetch,
    index,
    localise,
    methods,
    occupancy,
    report,
    results,
    run,
    sql,
    synth,
    verify,
)
from vprscale.cli.common import EXIT_FAILURE, EXIT_USAGE, HelpFormatter, check_outputs, disk_full, shared_flags
from vprscale.cli.examples import epilog
from vprscale.core.deadline import EXIT_MORE, BudgetSpent
from vprscale.core.errors import CLUSTER, InputError, Interrupted, JobFailed, QueryError, raised_by
from vprscale.core.objects import storage_failure
from vprscale.core.plaintext import terminal
from vprscale.core.provenance import set_command

COMMANDS = (fetch, synth, build, index, encode, eval, report, results, methods, verify, run, bench, sql, localise,
            occupancy)  # in the order --help lists them


def _version() -> str:
    from vprscale import __version__

    return f"vprscale {__version__}"


DESCRIPTION = """Out-of-core dataset engineering and evaluation for billion-scale visual place recognition:
build the paper's datasets (or your own), index them with CoarseHash, evaluate sequence matching
beside FAISS compact codes, and explore the results in SQL."""


def _verbosity(p: argparse.ArgumentParser) -> None:
    quiet = p.add_mutually_exclusive_group()
    quiet.add_argument("-q", "--quiet", dest="verbosity", action="store_const", const=logging.WARNING,
                       default=argparse.SUPPRESS, help="only warnings and errors on stderr (no progress)")
    quiet.add_argument("-v", "--verbose", dest="verbosity", action="store_const", const=logging.DEBUG,
                       default=argparse.SUPPRESS, help="also debugging detail on stderr, and the traceback of a bug")


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(prog="vprscale", description=DESCRIPTION, formatter_class=HelpFormatter,
                                  epilog="a fresh machine: vprscale run quickstart (a few minutes on 2 cores); "
                                         "vprscale COMMAND --help for each command")
    top.add_argument("--version", action="version", version=_version())
    _verbosity(top)
    sub = top.add_subparsers(dest="command", required=True, metavar="COMMAND")
    cluster, summary = shared_flags()
    for command in COMMANDS:
        command.add(sub, cluster, summary)
    for name, p in sub.choices.items():
        p.formatter_class, p.epilog = HelpFormatter, epilog(name)
        _verbosity(p)
    return top


def _parse(top: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace:
    """The command line parsed; a flag the command does not know is said by the command's own
    usage, with the flag it most likely meant (``--noises``: did you mean ``--noise``?)."""
    args, extra = top.parse_known_args(argv)
    if extra:
        command = next(a for a in top._actions if isinstance(a, argparse._SubParsersAction)).choices[args.command]
        known = [o for a in command._actions for o in a.option_strings if o.startswith("--")]
        hints = []
        for flag in (e for e in extra if e.startswith("-")):
            near = difflib.get_close_matches(flag.split("=", 1)[0], known, n=1, cutoff=0.75)
            if near:
                hints.append(f"{flag.split('=', 1)[0]}: did you mean {near[0]}?")
        command.error(f"unrecognized arguments: {' '.join(extra)}" + (f" ({'; '.join(hints)})" if hints else ""))
    return args


class _Stderr(logging.StreamHandler):
    """A handler writing to whatever ``sys.stderr`` is when a record is emitted (a test's capture,
    a pipeline's redirection), never to a stream that has since been closed; a message is text,
    its control characters shown (a name from a file cannot move the cursor or retitle the terminal)."""

    def format(self, record: logging.LogRecord) -> str:
        return terminal(super().format(record))

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def configure_logging(level: int) -> None:
    """The library logs under ``vprscale`` and stays silent unless asked; the command line shows
    INFO (progress) on stderr, WARNING and up with ``--quiet``, DEBUG with ``--verbose``."""
    log = logging.getLogger("vprscale")
    handler = _Stderr()
    handler.setFormatter(logging.Formatter("%(message)s"))
    log.handlers[:] = [h for h in log.handlers if isinstance(h, logging.NullHandler)] + [handler]
    log.setLevel(level)
    log.propagate = False


def _closed_pipe() -> int:
    """The reader went away (``vprscale results … | head``): end quietly, as git and ripgrep do.
    stdout is pointed at /dev/null so that the interpreter's last flush cannot fail again."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    return 0


LIGHT = ("methods", "verify", "sql", "results")  # commands that run no kernel (and should not import numba)
PRINTS_ITS_PRODUCT = ("results", "sql", "occupancy", "methods")  # what they make is standard output (localise too,
# without --out)


def _closed_streams(args: argparse.Namespace) -> str | None:
    """Standard streams the caller closed (``>&-``, ``2>&-``): an error message when the command's
    product is standard output, else None with each closed stream pointed at /dev/null (a job's
    files are still written; only its messages go nowhere, and its exit status still tells)."""
    if sys.stderr is None:
        sys.stderr = open(os.devnull, "w")  # noqa: SIM115 - for the rest of the process
    if sys.stdout is None:
        if args.command in PRINTS_ITS_PRODUCT or (args.command == "localise" and not args.out):
            return "standard output is closed: nowhere to write what this command prints (redirect it" + (
                ", or give --out)" if args.command == "localise" else ")")
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - for the rest of the process
    return None


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parse(parser(), argv)
    closed = _closed_streams(args)
    if closed:
        print(f"vprscale {args.command}: error: {closed}", file=sys.stderr)
        return EXIT_USAGE
    level = getattr(args, "verbosity", logging.INFO)
    configure_logging(level)
    if args.command not in LIGHT:
        from vprscale.core.compiling import announce_compiling

        announce_compiling()
    set_command(["vprscale", *argv])
    if threading.current_thread() is threading.main_thread():  # a batch scheduler's time limit sends SIGTERM
        signal.signal(signal.SIGTERM, _terminated)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        check_outputs(args)
        status = func(args)
        sys.stdout.flush()
        return status
    except BrokenPipeError:
        return _closed_pipe()
    except InputError as exc:
        print(f"vprscale {args.command}: error: {terminal(exc)}", file=sys.stderr)
        if isinstance(exc, QueryError) and exc.detail:  # the SQL engine's hint, the statement's line and a caret
            print(terminal(exc.detail), file=sys.stderr)
        return EXIT_USAGE
    except BudgetSpent as exc:  # not a failure: the job stopped at a checkpoint, as vprscale run --budget asked
        print(f"vprscale {args.command}: stopped at a checkpoint, the time budget spent ({terminal(exc)}); the same "
              "command continues from it", file=sys.stderr)
        return EXIT_MORE
    except JobFailed as exc:
        print(f"vprscale {args.command}: failed: {terminal(exc)}", file=sys.stderr)
        return EXIT_FAILURE
    except OSError as exc:
        if storage_failure(exc):
            return _storage_failed(args, exc)
        if raised_by(exc, CLUSTER):
            return _cluster_failed(args, exc)
        if not disk_full(exc, args):  # the system's failure, not the input's: one line, exit 1, work kept
            if level <= logging.DEBUG:
                traceback.print_exception(exc, file=sys.stderr)
            print(f"vprscale {args.command}: failed: {terminal(exc)}; finished work is kept and resumed by the same "
                  "command", file=sys.stderr)
            return EXIT_FAILURE
        # Outputs are published whole, so nothing half-written is visible; checkpoints stay for the re-run.
        where = f" writing {terminal(exc.filename)}" if exc.filename else ""
        print(f"vprscale {args.command}: error: the disk is full{where}; free space and run the same command "
              "again (finished work is kept and resumed)", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (Interrupted): finished work is kept for the re-run
        print("interrupted", file=sys.stderr)
        return 128 + getattr(exc, "signum", signal.SIGINT)
    except Exception as exc:  # noqa: BLE001 - a bug of ours: one line, not a traceback
        if storage_failure(exc):
            return _storage_failed(args, exc)
        if raised_by(exc, CLUSTER):
            return _cluster_failed(args, exc)
        return _bug(args, exc, level)
    finally:
        set_command([])  # this command's line is not the provenance of what the process makes next


def _terminated(signum: int, frame: object) -> None:
    raise Interrupted(signum)


def _storage_failed(args: argparse.Namespace, exc: BaseException) -> int:
    """Object storage failed under a job (an endpoint gone, a connection dropped past the client's
    retries): one line and exit 2, as a dropped download is; what was marked done stays for the re-run."""
    what = terminal(str(exc).splitlines()[0][:300] if str(exc) else type(exc).__name__)
    print(f"vprscale {args.command}: error: the storage failed: {what}; finished work is kept: run the same "
          "command again to resume", file=sys.stderr)
    return EXIT_USAGE


def _cluster_failed(args: argparse.Namespace, exc: BaseException) -> int:
    """The Dask cluster failed under a job (its scheduler or a worker gone): one line and exit 2, as
    a storage that failed; what was marked done stays for the re-run."""
    what = terminal(str(exc).splitlines()[0][:300] if str(exc) else type(exc).__name__)
    print(f"vprscale {args.command}: error: the Dask cluster failed: {what}; finished work is kept: run the same "
          "command again to resume", file=sys.stderr)
    return EXIT_USAGE


def _bug(args: argparse.Namespace, exc: BaseException, level: int) -> int:
    if level <= logging.DEBUG:
        traceback.print_exception(exc, file=sys.stderr)
    what = terminal(str(exc).splitlines()[0][:300] if str(exc) else "")
    print(f"vprscale {args.command}: internal error: {type(exc).__name__}{': ' + what if what else ''} (a bug in "
          "vprscale; --verbose shows the traceback)", file=sys.stderr)
    return EXIT_FAILURE
