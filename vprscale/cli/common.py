"""What every command shares: exit statuses, argument types, the ``--summary`` file, the
flags of the cluster, and the checks that refuse an output before any work."""

from __future__ import annotations

import argparse
import errno
import json
import os
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path

from vprscale.core.errors import InputError
from vprscale.core.objects import is_url, public, redact
from vprscale.dataset.corpora import parse_base

EXIT_USAGE = 2  # bad input
EXIT_FAILURE = 1  # vprscale itself failed
MAX_FAS_DIM = 16_384  # a synthetic FAS row of more features is drawn in memory, a chunk at a time
OUTPUT_FLAGS = ("out", "summary")  # the flags that name what a command writes


def positive_int(text: str) -> int:
    try:
        value = int(text.replace("_", "").replace(",", ""))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be positive")
    return value


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"{text!r} must be a positive, finite number")
    return value


def bounded_int(upper: int, why: str) -> Callable[[str], int]:
    """A positive whole number of at most ``upper`` (``why`` says where the bound comes from)."""
    def parse(text: str) -> int:
        value = positive_int(text)
        if value > upper:
            raise argparse.ArgumentTypeError(f"{text!r} is more than {upper:,} ({why})")
        return value
    return parse


def csv_of(kind: type) -> Callable[[str], list]:
    """A comma-separated list of ``kind`` values."""
    def parse(text: str) -> list:
        try:
            return [kind(v) for v in text.split(",") if v.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list") from None
    return parse


SUMMARY_MARK = "summary_of"  # the key that says a JSON file is a summary vprscale wrote (and may write again)


def write_summary(args: argparse.Namespace, data: dict) -> None:
    """``--summary FILE``: the command's summary as JSON (what pipelines read back), written whole;
    it replaces only a summary of an earlier run (:func:`check_outputs` refused anything else)."""
    if getattr(args, "summary", None):
        path = Path(args.summary)
        tmp = path.with_name(f".{path.name}.tmp")
        record = {SUMMARY_MARK: f"vprscale {args.command}", **redact(data)}  # no URL's password or signature
        tmp.write_text(json.dumps(record, indent=1, default=str))
        tmp.replace(path)


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Every option's default in its help (unless the help already says it), and the examples of the
    epilog kept as written."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        default = action.default
        if (not action.option_strings or "default" in text.lower() or default in (None, False, [], argparse.SUPPRESS)
                or isinstance(action, argparse._VersionAction | argparse._StoreConstAction)):
            return action.help
        shown = ",".join(map(str, default)) if isinstance(default, list | tuple) else str(default)
        return f"{text} (default: {shown.replace('%', '%%')})".lstrip()


def shared_flags() -> tuple[argparse.ArgumentParser, argparse.ArgumentParser]:
    """The flags several commands share, declared once: (cluster, summary)."""
    cluster = argparse.ArgumentParser(add_help=False)
    cluster.add_argument("--scheduler", metavar="ADDRESS",
                         help="address of a Dask distributed scheduler (tcp://host:8786); default: none, the "
                              "work runs on threads of this process")
    cluster.add_argument("--workers", type=positive_int, default=os.cpu_count() or 1,
                         help="threads of this process for Dask and for the numba kernels (default: all cores)")
    summary = argparse.ArgumentParser(add_help=False)
    summary.add_argument("--summary", metavar="FILE", help="also write the command's summary as JSON to FILE")
    return cluster, summary


def _flag_paths(args: argparse.Namespace, names: Sequence[str]) -> list[tuple[str, Path]]:
    found = []
    for name in names:
        value = getattr(args, name, None)
        for v in value if isinstance(value, list) else [value]:
            if name == "query" and isinstance(v, str):  # NAME=PATH
                v = v.partition("=")[2]
            if name == "base" and isinstance(v, str):  # [CORPUS:]PATH
                v = parse_base(v)[1]
            if isinstance(v, str) and v and not is_url(v) and (name != "scale" or Path(v).suffix == ".toml"):
                found.append((name, Path(v)))
    return found


def _flag_urls(args: argparse.Namespace, names: Sequence[str]) -> list[tuple[str, str]]:
    """The flags among ``names`` given as URLs (object storage, HTTP), as given."""
    values = [(name, getattr(args, name, None)) for name in names]
    return [(name, v.rstrip("/")) for name, value in values for v in (value if isinstance(value, list) else [value])
            if is_url(v)]


def local_output(spec: str) -> Path:
    """An output a command reads from local files (an index is memory-mapped): its path, or for a
    URL its verified copy in the cache (fetched once; again only when it was re-published)."""
    if not is_url(spec):
        return Path(spec)
    from vprscale.core.localcopy import local_copy
    from vprscale.core.objects import Remote

    return local_copy(Remote(spec))


def _resolved(path: Path, flag: str) -> Path:
    """``path`` with its symbolic links followed, or an error naming the flag where they loop."""
    try:
        return path.resolve()
    except (RuntimeError, OSError):  # Python 3.11-3.12 say a loop with RuntimeError, 3.13 with OSError
        raise InputError(f"--{flag} {path}: a loop of symbolic links, which leads to no file") from None


def _owner(path: Path, flag: str) -> Path | None:
    """The vprscale store or index that ``path`` lies inside (symlinks followed), if any."""
    for parent in _resolved(path, flag).parents:
        if (parent / "index.json").is_file() or (parent / "zarr.json").is_file():
            return parent
    return None


def _check_not_over_inputs(args: argparse.Namespace) -> None:
    """No output flag may name one of the command's inputs, lie inside one, or lie inside a
    store or index the command does not own (paths resolved, symlinks followed)."""
    inputs = _flag_paths(args, getattr(args, "input_flags", ()))
    for out_flag, out in _flag_paths(args, OUTPUT_FLAGS):
        target = _resolved(out, out_flag)
        for in_flag, src in inputs:
            where = _resolved(src, in_flag)
            if target == where or where in target.parents:
                raise InputError(f"--{out_flag} {out}: would write {'over' if target == where else 'into'} the "
                                 f"input {src} (--{in_flag})")
        owner = _owner(out, out_flag)
        own_eval = (args.command == "eval" and out_flag == "out" and getattr(args, "index", None)
                    and target == (Path(args.index) / "eval").resolve())
        if owner is not None and not own_eval:
            raise InputError(f"--{out_flag} {out}: lies inside {owner}, a vprscale store or index this command does "
                             "not own; write elsewhere")
    for out_flag, out in _flag_urls(args, OUTPUT_FLAGS):
        for in_flag, src in _flag_urls(args, getattr(args, "input_flags", ())):
            if out == src or out.startswith(src + "/"):
                raise InputError(f"--{out_flag} {public(out)}: would write {'over' if out == src else 'into'} the "
                                 f"input {public(src)} (--{in_flag})")


def _our_summary(path: Path) -> bool:
    """Whether ``path`` is a regular file holding a summary vprscale wrote (an earlier run's)."""
    try:
        record = json.loads(path.read_text()) if path.is_file() and not path.is_symlink() else None
    except (OSError, ValueError):
        return False
    return isinstance(record, dict) and str(record.get(SUMMARY_MARK, "")).startswith("vprscale ")


def check_outputs(args: argparse.Namespace) -> None:
    """Refuse unusable output paths before any work (a bad --summary must not fail after publishing)."""
    _check_not_over_inputs(args)
    summary = getattr(args, "summary", None)
    if summary:
        path = Path(summary)
        if path.is_dir():
            raise InputError(f"--summary {summary}: is a directory; give a file name")
        if not path.parent.is_dir():
            raise InputError(f"--summary {summary}: the folder {path.parent} does not exist")
    out = getattr(args, "out", None)
    if out and not is_url(out) and getattr(args, "out_is_dir", False) and Path(out).exists() and not Path(out).is_dir():
        raise InputError(f"--out {out}: is a file, not a directory")
    for flag, path in _flag_paths(args, OUTPUT_FLAGS):
        if str(path) != "-":  # standard output
            _check_writable_beside(flag, path)
    summary = Path(args.summary) if getattr(args, "summary", None) else None
    if summary is not None and (summary.exists() or summary.is_symlink()) and not _our_summary(summary):
        raise InputError(f"--summary {summary}: exists and is not a summary vprscale wrote; not replaced "
                         "(give a new file, or remove it)")


def _check_writable_beside(flag: str, path: Path) -> None:
    """Refuse, before any work, an output whose folder cannot be written: every output is made
    beside its final path (a hidden work copy, a lock) and renamed into place, so the folder that
    holds it, or the nearest one that exists, must take new files (a read-only filesystem, an
    immutable folder and missing permissions all say no to ``access``, even for root)."""
    folder = path.absolute().parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise InputError(f"--{flag} {path}: cannot create the output directory: {folder} is a file")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"--{flag} {path}: the folder {folder} is not writable (read-only, or not yours); "
                         "nothing was written")


def disk_full(exc: OSError, args: argparse.Namespace) -> bool:
    """Whether an I/O error is a full disk: ENOSPC/EDQUOT, or (numpy's short writes carry no errno)
    the output's filesystem has less than a mebibyte left."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    out = getattr(args, "out", None)
    if not out or is_url(out):
        return False
    path = Path(out).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free < 1 << 20
