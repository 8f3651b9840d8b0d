"""The ``vprscale`` command line. User errors print one line and exit with status 2.

Each command is a module of this package (``add`` declares its arguments, ``run`` does the
work), so a pipeline stage's fingerprint counts the command it runs, not every command:
changing ``vprscale sql`` re-runs no build (docs/architecture.md).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from vprscale.cli import (
    bench,
    build,
    encode,
    eval,
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
from vprscale.cli.common import EXIT_FAILURE, EXIT_USAGE, check_outputs, disk_full, shared_flags
from vprscale.core.errors import InputError, JobFailed
from vprscale.core.provenance import set_command

COMMANDS = (synth, build, index, encode, eval, report, results, methods, verify, run, bench, sql, localise,
            occupancy)  # in the order --help lists them


def _version() -> str:
    from vprscale import __version__

    return f"vprscale {__version__}"


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(prog="vprscale", description=__doc__.split("\n\n")[0])
    top.add_argument("--version", action="version", version=_version())
    sub = top.add_subparsers(dest="command", required=True)
    cluster, summary = shared_flags()
    for command in COMMANDS:
        command.add(sub, cluster, summary)
    return top


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser().parse_args(argv)
    set_command(["vprscale", *argv])
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        check_outputs(args)
        return func(args)
    except InputError as exc:
        print(f"vprscale {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except JobFailed as exc:
        print(f"vprscale {args.command}: failed: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    except OSError as exc:
        if not disk_full(exc, args):
            raise
        # Outputs are published whole, so nothing half-written is visible; checkpoints stay for the re-run.
        where = f" writing {exc.filename}" if exc.filename else ""
        print(f"vprscale {args.command}: error: the disk is full{where}; free space and run the same command "
              "again (finished work is kept and resumed)", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
