"""The command line as a user meets it: statements of any length, closed pipes, the SQL shell on a
real terminal (history, Ctrl-C), reports that are not replaced by accident, localise's formats,
help with defaults and examples, quiet and verbose, and a bug reported in one line."""

from __future__ import annotations

import argparse
import contextlib
import os
import pty
import re
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vprscale.cli import COMMANDS, main, parser


def _vprscale(*argv: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vprscale.cli", *argv], capture_output=True, text=True, **kw)


@pytest.fixture(scope="module")
def evaluated(tiny_store, tiny_index, tmp_path_factory) -> Path:
    """A copy of the tiny index with a small evaluation in its eval/ folder."""
    index = tmp_path_factory.mktemp("cli") / "tiny.index"
    shutil.copytree(tiny_index, index)
    assert main(["eval", str(tiny_store), str(index), "--L", "1,20", "--noise", "qm1", "--no-baseline",
                 "--repeats", "1", "--quiet"]) == 0
    return index


def test_a_statement_longer_than_a_file_name_runs(evaluated):
    """The last word is a statement when it names nothing on disk, even past 255 bytes (a path of
    that length makes ``Path.exists`` raise ENAMETOOLONG)."""
    columns = ", ".join(f"b.size + {i} AS x{i}" for i in range(40))
    query = (f"SELECT b.hash, {columns}, count(l.ref_id) AS n FROM buckets b JOIN lists l ON l.hash = b.hash "
             "GROUP BY ALL ORDER BY n DESC, b.hash LIMIT 2")
    assert len(query) > 600
    done = _vprscale("sql", str(evaluated), query, "--csv")
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith('"hash","x0"') and len(lines) == 3


@pytest.mark.slow
def test_a_long_statements_csv_is_the_result_alone(evaluated):
    """A statement that runs for seconds (DuckDB would draw its progress bar after 2 s, on standard
    output) writes its CSV and nothing else there."""
    done = _vprscale("sql", str(evaluated), "SELECT count(*) AS n FROM range(600000000) t(i) WHERE hash(i) % 7 = 0",
                     "--csv")
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[0] == '"n"' and done.stdout.splitlines()[1].isdigit()
    assert len(done.stdout.splitlines()) == 2


@pytest.mark.parametrize("argv", [["methods"], ["occupancy", "{index}"], ["results", "{index}"],
                                  ["results", "{index}", "--queries", "--csv"], ["verify", "{index}"]])
def test_a_closed_pipe_ends_quietly(evaluated, argv):
    """``vprscale … | head -1``: exit 0 and nothing on stderr, as git and ripgrep do."""
    argv = [a.format(index=evaluated) for a in argv]
    cmd = f"{sys.executable} -m vprscale.cli {' '.join(argv)} | head -c 1; echo \" ${{PIPESTATUS[0]}}\" >&2"
    done = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True)
    # what is left besides the exit status: nothing (a first run in a new checkout may say that it
    # compiles numba's kernels, as every command's first run does: not part of what is tested here)
    said = [x.strip() for x in done.stderr.strip().splitlines() if not x.startswith("compiling numba kernels")]
    assert said == ["0"], done.stderr


class _Terminal:
    """The master side of a pseudo-terminal: ``expect`` reads until a marker and keeps what came
    after it for the next ``expect``; ``seen`` is everything read."""

    def __init__(self, fd: int) -> None:
        self.fd, self.pending, self.seen = fd, b"", b""

    def _read(self, left: float) -> bytes | None:
        """What the child wrote next (b"" once it closed the terminal; None: nothing yet)."""
        if not select.select([self.fd], [], [], left)[0]:
            return None
        try:
            chunk = os.read(self.fd, 65536)
        except OSError:  # the child closed the terminal
            chunk = b""
        self.pending += chunk
        self.seen += chunk
        return chunk

    def expect(self, marker: bytes, seconds: float = 60.0) -> None:
        deadline = time.monotonic() + seconds
        while marker not in self.pending:
            left = deadline - time.monotonic()
            assert left > 0, f"no {marker!r} in {self.seen[-2000:]!r}"
            assert self._read(left) != b"", f"the terminal closed before {marker!r}: {self.seen[-2000:]!r}"
        self.pending = self.pending.split(marker, 1)[1]

    def closed(self, seconds: float = 30.0) -> None:
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            if self._read(left) == b"":
                return
        raise AssertionError(f"the terminal is still open: {self.seen[-2000:]!r}")


def _reap(pid: int, seconds: float = 20.0) -> int:
    """The child's wait status; a child still running after ``seconds`` is killed first."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            return status
        time.sleep(0.1)
    os.kill(pid, 9)
    return os.waitpid(pid, 0)[1]


@pytest.mark.slow
def test_the_sql_shell_on_a_terminal(evaluated, tmp_path):
    """On a pseudo-terminal: an empty line does not quit, Ctrl-C cancels a running statement and the
    shell goes on, the engine's context lines are shown, history is written, Ctrl-D leaves with 0."""
    history = tmp_path / "history"
    env = {**os.environ, "VPRSCALE_SQL_HISTORY": str(history), "COLUMNS": "100"}
    pid, fd = pty.fork()
    if pid == 0:  # the child: vprscale on the terminal
        os.execve(sys.executable, [sys.executable, "-m", "vprscale.cli", "sql", str(evaluated)], env)
    term = _Terminal(fd)
    try:
        term.expect(b"sql> ")
        os.write(fd, b"\n")
        term.expect(b"sql> ")
        os.write(fd, b"SELECT count(*) AS n FROM lists a, lists b, lists c, lists d;\n")
        time.sleep(1.5)
        os.write(fd, b"\x03")
        term.expect(b"cancelled")
        term.expect(b"sql> ")
        os.write(fd, b"SELECT size,\n  nope FROM buckets;\n")  # a statement over two lines
        term.expect(b"sql> ")
        os.write(fd, b"SELECT 6 * 7 AS answer;\n")
        term.expect(b"(1 rows)")
        term.expect(b"sql> ")
        os.write(fd, b".tables\n")
        term.expect(b"sql> ")
        time.sleep(0.5)  # readline has the terminal now: Ctrl-D on an empty line is the end of input
        os.write(fd, b"\x04")
        term.closed()
    finally:
        status = _reap(pid)
        os.close(fd)
    text = term.seen.decode(errors="replace")
    assert os.waitstatus_to_exitcode(status) == 0, text
    assert "Traceback" not in text and "KeyboardInterrupt" not in text
    assert "cancelled" in text and "42" in text
    assert 'Referenced column "nope" not found' in text and "Candidate bindings" in text  # the context line
    assert "LINE 2:   nope FROM buckets;" in text and "          ^^^^" in text  # the line, a caret under it
    assert re.search(r"hash \w+, size \w+, offset \w+", text)  # .tables: each view's columns and types
    assert re.search(r"hash \w+, ref_id \w+, best \w+", text)
    kept = history.read_text().splitlines()
    assert "SELECT size, nope FROM buckets;" in kept and ";" not in kept and "SELECT 6 * 7 AS answer;" in kept


def test_report_is_not_replaced_without_force_and_is_kept_with_it(evaluated, tmp_path, capsys):
    out = tmp_path / "rep"
    assert main(["report", str(evaluated / "eval"), "--out", str(out), "--quiet"]) == 0
    first = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()
    assert main(["report", str(evaluated / "eval"), "--out", str(out)]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"vprscale report: error: --out {out}: already holds a report; --force replaces it and keeps it beside, "
        "in rep.previous/"]
    assert {p.name: p.read_bytes() for p in out.iterdir()} == first
    assert main(["report", str(evaluated / "eval"), "--out", str(out), "--force", "--quiet"]) == 0
    assert {p.name: p.read_bytes() for p in (tmp_path / "rep.previous").iterdir()} == first
    assert (out / "report.md").is_file()
    assert not any(p.name.startswith(".rep.partial") for p in tmp_path.iterdir())
    # every later --force keeps every earlier copy: rep.previous the latest, rep.previous.1, .2 … before it
    second = {p.name: p.read_bytes() for p in out.iterdir()}
    for _ in range(2):
        assert main(["report", str(evaluated / "eval"), "--out", str(out), "--force", "--quiet"]) == 0
    assert {p.name: p.read_bytes() for p in (tmp_path / "rep.previous.1").iterdir()} == first
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("rep.")) == [
        "rep.previous", "rep.previous.1", "rep.previous.2"]
    assert {p.name for p in (tmp_path / "rep.previous.2").iterdir()} == set(second)


def test_report_refuses_a_folder_of_other_files(evaluated, tmp_path):
    mine = tmp_path / "notes"
    mine.mkdir()
    (mine / "report.md").write_text("my own notes\n")
    done = _vprscale("report", str(evaluated / "eval"), "--out", str(mine), "--force")
    assert done.returncode == 2 and "holds files that are not a vprscale report" in done.stderr
    assert (mine / "report.md").read_text() == "my own notes\n"


def test_localise_writes_the_format_its_out_names(evaluated, tiny_store, tmp_path):
    queries = str(tiny_store / "query_qm1")
    assert main(["localise", str(evaluated), queries, "--L", "20", "--out", str(tmp_path / "m.parquet"), "-q"]) == 0
    assert main(["localise", str(evaluated), queries, "--L", "20", "--out", str(tmp_path / "m.csv"), "-q"]) == 0
    table = pd.read_parquet(tmp_path / "m.parquet")
    assert {c: str(t) for c, t in table.dtypes.items()} == {"frame": "Int64", "centre": "Int64", "match": "Int64",
                                                             "n_r": "Int64", "score": "float64"}
    assert table.match.isna().sum() == 19 and table.match.iloc[19:].notna().all()
    assert table.score.iloc[19:].notna().all() and table.score.iloc[19:].nunique() > 10
    csv = pd.read_csv(tmp_path / "m.csv", dtype={c: "Int64" for c in ("frame", "centre", "match", "n_r")})
    pd.testing.assert_frame_equal(csv, table, check_exact=False, rtol=1e-15)
    stdout = _vprscale("localise", str(evaluated), queries, "--L", "20", "-q")
    assert stdout.returncode == 0 and stdout.stdout == (tmp_path / "m.csv").read_text()
    wrong = _vprscale("localise", str(evaluated), queries, "--out", str(tmp_path / "m.txt"))
    assert wrong.returncode == 2 and "name a .parquet or .csv file" in wrong.stderr
    assert not (tmp_path / "m.txt").exists()


def test_results_show_method_parameters_and_recall(evaluated):
    done = _vprscale("results", str(evaluated), "--where", "radius = 20 AND part = 'all'")
    header = done.stdout.splitlines()[0].split()
    assert header[:9] == ["scale", "noise", "method", "family", "params", "mode", "L", "part", "radius"]
    assert "recall" in header and "recall_at_20" in header and "/" not in done.stdout.splitlines()[2]
    # the two recalls' meanings, said under the table: a radius is not a candidate count
    legend = done.stdout.splitlines()[-1]
    assert "recall: the match within radius frames" in legend and "recall_at_20: Recall@N" in legend


def test_every_command_has_help_with_defaults_and_an_example():
    top = parser()
    sub = next(a for a in top._actions if a.dest == "command")
    assert set(sub.choices) == {c.__name__.rsplit(".", 1)[-1] for c in COMMANDS}
    for name, p in sub.choices.items():
        text = p.format_help()
        assert "examples:\n  vprscale " + name in text, name
        formatter = p.formatter_class(prog=name)
        for action in p._actions:
            if action.option_strings and action.default not in (None, False, [], "==SUPPRESS==") and \
                    action.dest not in ("help", "version") and not isinstance(action, argparse._StoreConstAction):
                assert "default" in (formatter._get_help_string(action) or ""), f"{name} --{action.dest}: no default"
    assert "(default: 1,50,100)" in sub.choices["eval"].format_help().replace("\n", " ").replace("  ", " ")


def test_quiet_prints_no_progress_and_the_library_prints_nothing(tiny_store, tmp_path):
    done = _vprscale("index", str(tiny_store), "--d", "10", "--out", str(tmp_path / "q.index"), "--quiet")
    assert done.returncode == 0 and done.stderr == ""
    loud = _vprscale("index", str(tiny_store), "--d", "10", "--out", str(tmp_path / "l.index"))
    assert "…" in loud.stderr
    code = (f"import zarr, vprscale; s = zarr.open_group({str(tiny_store)!r}, mode='r'); "
            "vprscale.Index.build(s['ref'][:20000], d=10).match(s['query_qm1'][:500], L=20)")
    lib = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert lib.returncode == 0 and lib.stderr == "" and lib.stdout == ""


def test_a_bug_is_one_line_and_exit_1(evaluated, monkeypatch, capsys):
    import vprscale.cli.verify as verify

    def broken(args):
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(verify, "run", broken)
    assert main(["verify", str(evaluated)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["vprscale verify: internal error: ZeroDivisionError: division by zero (a bug in vprscale; "
                   "--verbose shows the traceback)"]
    assert main(["verify", str(evaluated), "--verbose"]) == 1
    assert "Traceback" in capsys.readouterr().err


def test_an_output_over_an_own_data_input_is_refused(tmp_path, capsys):
    """The own-data flags are inputs too: --summary (or --out) over --ref, a --query file or --gt is
    one line, and the file is left as it was."""
    import numpy as np

    rows = np.random.default_rng(0).normal(size=(300, 8)).astype(np.float32)
    for name in ("ref", "day"):
        np.save(tmp_path / f"{name}.npy", rows)
    np.save(tmp_path / "gt.npy", np.arange(300))
    before = (tmp_path / "day.npy").read_bytes()
    argv = ["build", "--ref", str(tmp_path / "ref.npy"), "--query", f"day={tmp_path / 'day.npy'}", "--gt",
            str(tmp_path / "gt.npy"), "--out", str(tmp_path / "data")]
    assert main([*argv, "--summary", str(tmp_path / "day.npy")]) == 2
    assert capsys.readouterr().err.strip() == (f"vprscale build: error: --summary {tmp_path / 'day.npy'}: would "
                                               f"write over the input {tmp_path / 'day.npy'} (--query)")
    assert (tmp_path / "day.npy").read_bytes() == before
    assert main([*argv, "--summary", str(tmp_path / "gt.npy")]) == 2
    assert "(--gt)" in capsys.readouterr().err


def test_a_method_that_is_not_a_class_is_never_called(evaluated, tiny_store, capsys):
    assert main(["eval", str(tiny_store), str(evaluated), "--method", "os:system", "--L", "1", "--noise", "qm1",
                 "--no-baseline", "--out", str(evaluated.parent / "never")]) == 2
    assert capsys.readouterr().err.strip() == ("vprscale eval: error: --method os:system: os.system is a "
                                               "builtin_function_or_method, not a class (docs/bring-your-own.md)")
    assert not (evaluated.parent / "never").exists()


def test_synth_does_not_write_over_a_dataset_without_force(tmp_path, capsys):
    """``DIR/Deep1B/base.fbin`` is the real dataset's own name: synthetic rows never silently replace it."""
    real = tmp_path / "Deep1B" / "base.fbin"
    real.parent.mkdir(parents=True)
    real.write_bytes(b"the real one")
    argv = ["synth", "--out", str(tmp_path), "--deep1b-rows", "100", "--fas-dim", "16"]
    assert main(argv) == 2
    assert capsys.readouterr().err.strip() == (f"vprscale synth: error: --out {tmp_path}: already holds {real}; "
                                               "--force replaces the synthetic files there (or give another --out)")
    assert real.read_bytes() == b"the real one" and not (tmp_path / "FAS").exists()
    assert main([*argv, "--force", "--quiet"]) == 0
    assert real.stat().st_size == 8 + 4 * 100 * 96
    kept = real.with_name("base.fbin.previous")
    assert kept.read_bytes() == b"the real one"  # what synth did not write is kept beside, not replaced
    ours = {f: f.read_bytes() for f in tmp_path.rglob("*") if f.is_file() and ".previous" not in f.name
            and f.name != ".synth.json"}
    assert main([*argv, "--force", "--quiet"]) == 0  # its own files are replaced: nothing more kept
    assert sorted(p.name for p in tmp_path.rglob("*.previous*")) == ["base.fbin.previous"]
    assert {f: f.read_bytes() for f in ours} == ours


def _snapshot(path: Path) -> dict[str, bytes]:
    """Every file under ``path`` (or ``path`` itself) with its bytes."""
    if path.is_file():
        return {"": path.read_bytes()}
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


# Every command that writes an output, and the output it would write over: (argv, what is there)
REPLACED = {
    "build over a folder of someone's": (["build", "--scale", "20K", "--out", "{tmp}"], "{tmp}/20K.zarr/"),
    "index over an index of other parameters": (["index", "{store}", "--d", "10", "--out", "{index}"], None),
    "index over an unevaluated index of others": (["index", "{store}", "--d", "10", "--out", "{index}"], "no eval"),
    "index over a folder of someone's": (["index", "{store}", "--d", "10", "--out", "{tmp}/x.index"],
                                         "{tmp}/x.index/"),
    "eval over an evaluation": (["eval", "{store}", "{index}", "--L", "1", "--noise", "qm1", "--no-baseline",
                                 "--repeats", "1"], None),
    "eval over a folder of someone's": (["eval", "{store}", "{index}", "--L", "1", "--out", "{tmp}/e"], "{tmp}/e/"),
    "report over a folder of someone's": (["report", "{index}", "--out", "{tmp}/r"], "{tmp}/r/"),
    "localise over a file": (["localise", "{index}", "{store}/query_qm1", "--L", "5", "--out", "{tmp}/m.csv"],
                             "{tmp}/m.csv"),
    "a summary over a file": (["localise", "{index}", "{store}/query_qm1", "--L", "5", "--summary", "{tmp}/s.json"],
                              "{tmp}/s.json"),
    "fetch over a file": (["fetch", "deep1b", "--rows", "1K", "--url", "{url}", "--out", "{tmp}"],
                          "{tmp}/base.1K.fbin"),
}


@pytest.mark.parametrize("case", list(REPLACED))
def test_no_command_replaces_an_output_without_force(case, evaluated, tiny_store, tmp_path, capsys):
    """The one rule for every command that writes: an existing output, or anything of someone's where
    an output would go, is refused in one line (exit 2) unless ``--force`` says replace, and then
    only an output of vprscale's, kept beside; nothing there changes."""
    from .test_fetch import Server, deep_rows

    index = tmp_path / "tiny.index"
    shutil.copytree(evaluated, index)
    argv, theirs = REPLACED[case]
    data = deep_rows(1000)
    server = Server(lambda a, b: data[a:b], len(data))
    fill = {"tmp": str(tmp_path), "store": str(tiny_store), "index": str(index), "url": server.url}
    argv = [a.format(**fill) for a in argv]
    target = Path(theirs.format(**fill)) if theirs and theirs != "no eval" else index
    if theirs == "no eval":
        shutil.rmtree(index / "eval")
    elif theirs and theirs.endswith("/"):
        target.mkdir(parents=True)
        (target / "results.csv").write_text("method,recall\nmine,0.9\n")
    elif theirs:
        target.write_text("mine\n")
    before = _snapshot(target)
    capsys.readouterr()
    try:
        assert main(argv) == 2
    finally:
        server.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"vprscale {argv[0]}: error:"), err
    assert _snapshot(target) == before


def test_localise_replaces_its_output_with_force_and_keeps_it_beside(evaluated, tiny_store, tmp_path):
    out = tmp_path / "m.csv"
    out.write_text("mine\n")
    argv = ["localise", str(evaluated), f"{tiny_store}/query_qm1", "--L", "5", "--out", str(out), "-q"]
    assert main([*argv, "--force"]) == 0
    assert out.read_text().startswith('"frame",') and (tmp_path / "m.csv.previous").read_text() == "mine\n"
    summary = ["--summary", str(tmp_path / "s.json"), "--out", str(tmp_path / "n.csv"), "--force"]
    assert main([*argv[:-3], *summary]) == 0
    assert main([*argv[:-3], *summary]) == 0  # a summary of its own is rewritten


@pytest.mark.slow
@pytest.mark.parametrize(("command", "closes", "status"), [
    ("results {index}", ">&-", 2),
    ("sql {index} 'SELECT 1 AS one'", ">&-", 2),
    ("localise {index} {store}/query_qm1 --L 5", ">&-", 2),
    ("localise {index} {store}/query_qm1 --L 5 --out {tmp}/m.csv", "2>&-", 0),
    ("eval {store} {index} --L 1 --noise qm1 --no-baseline --repeats 1 --out {tmp}/e", "2>&- >&-", 0),
])
def test_closed_standard_streams(command, closes, status, evaluated, tiny_store, tmp_path):
    """A command whose product is standard output, run with it closed, says so in one line (exit 2);
    one whose product is a file writes it whatever streams the caller closed (no message to lose)."""
    line = command.format(index=evaluated, store=tiny_store, tmp=tmp_path)
    done = subprocess.run(["bash", "-c", f"{sys.executable} -m vprscale.cli {line} {closes}"], capture_output=True,
                          text=True)
    assert done.returncode == status, done.stderr
    if status == 2:
        assert done.stderr.strip().splitlines() == [done.stderr.strip()] and "standard output is closed" in done.stderr
    else:
        assert (tmp_path / "m.csv").is_file() or (tmp_path / "e" / "results.parquet").is_file()


def test_a_name_is_text_on_a_terminal(evaluated, tmp_path, capsys):
    """A method's name holding a terminal escape sequence (an evaluation folder someone hands you)
    is shown with its control characters made visible by ``results``, never sent raw."""
    import pyarrow.parquet as pq

    from vprscale.core.manifest import write_manifest

    folder = tmp_path / "eval"
    shutil.copytree(evaluated / "eval", folder)
    table = pq.read_table(folder / "results.parquet").to_pandas()
    table["method"] = "\x1b]0;owned\x07\x1b[2J" + table["method"]
    table.to_parquet(folder / "results.parquet")
    write_manifest(folder)
    capsys.readouterr()
    assert main(["results", str(folder), "--where", "L = 1"]) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out and "\x07" not in out and "\\x1b]0;owned\\x07\\x1b[2J" in out
    assert main(["sql", str(folder), "SELECT DISTINCT method FROM results", "--csv"]) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out and "\x07" not in out and "\\x1b]0;owned\\x07\\x1b[2J" in out


def test_a_name_in_an_error_message_is_text(tmp_path, capsys):
    """An error that names what a file holds (an HDF5 file's datasets) shows their control characters."""
    import h5py

    with h5py.File(tmp_path / "f.hdf5", "w") as f:
        f["\x1b]0;owned\x07\x1b[2J"] = np.zeros((10, 4), np.float32)
    np.save(tmp_path / "gt.npy", np.arange(10))
    capsys.readouterr()
    assert main(["build", "--ref", f"{tmp_path / 'f.hdf5'}:train", "--query", f"q={tmp_path / 'f.hdf5'}:train",
                 "--gt", str(tmp_path / "gt.npy"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "\x1b" not in err and "\x07" not in err and "\\x1b]0;owned" in err


@pytest.mark.slow
def test_a_large_result_streams_as_csv_and_json_and_is_refused_as_a_table(evaluated, capsys):
    """A statement of 150,000 rows: ``--csv`` and ``--json`` write it batch by batch, the same text as
    whole (one header); laid out as an aligned table it is refused in one line (every cell a Python
    string: 30M rows took 15 GB of the parent), pointing at --csv."""
    from vprscale.evaluation.sql import run_sql

    query = "SELECT i, i * 0.5 AS half, 'p' || i AS name FROM range(150000) t(i) ORDER BY i"
    for fmt in ("csv", "json"):
        capsys.readouterr()
        assert main(["sql", str(evaluated), query, f"--{fmt}"]) == 0
        assert capsys.readouterr().out == run_sql(str(evaluated), query, fmt=fmt)
    capsys.readouterr()
    assert main(["sql", str(evaluated), query.replace("150000", "250000")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "250,000 rows" in err and "--csv" in err


def test_one_shot_sql_and_where_show_the_engines_hint_and_caret(evaluated):
    """A mistyped column in one-shot SQL or in ``results --where`` gets what DuckDB's shell shows:
    the candidate bindings, the statement's line and a caret under the name; exit 2."""
    for argv, name in ((["sql", str(evaluated), "SELECT sise FROM buckets"], "sise"),
                       (["results", str(evaluated), "--where", "radious = 20"], "radious")):
        done = _vprscale(*argv)
        assert done.returncode == 2 and "Traceback" not in done.stderr
        err = done.stderr.splitlines()
        assert err[0].startswith(f"vprscale {argv[0]}: error: query: Binder Error: Referenced column")
        assert any(x.startswith("Candidate bindings:") for x in err), done.stderr
        at = next(i for i, x in enumerate(err) if x.startswith("LINE 1:"))
        assert err[at + 1].strip() == "^" * len(name) and err[at + 1].index("^") == err[at].index(name)


@pytest.mark.parametrize("argv, words", [
    (["eval", "s.zarr", "i.index", "--noises", "qm1"], ["vprscale eval: error: unrecognized arguments: --noises qm1",
                                                        "--noises: did you mean --noise?"]),
    (["build", "--scael", "20K"], ["vprscale build: error:", "did you mean --scale?"]),
    (["eval", "NOWHERE.zarr", "i.index"], ["NOWHERE.zarr: no such file or directory"]),
    (["eval", "s.zarr", "i.index", "--compare", "seq-gem:PQ2"],
     ["seq-gem: is no pooling", "seq:FACTORY", "seq-gem3:FACTORY"]),
    (["build", "--ref", "r.npy", "--query", "q=q.npy", "--out", "o"], ["vprscale build: error: --gt missing"]),
])
def test_natural_mistakes_get_a_precise_line(tiny_store, tiny_index, tmp_path, monkeypatch, capsys, argv, words):
    """A misspelt flag is named by the command's own usage with the flag it likely meant; a store
    that is not there is said so; a pooling that does not exist names those that do; the error
    names its command once."""
    monkeypatch.chdir(tmp_path)
    for name, real in (("s.zarr", tiny_store), ("i.index", tiny_index)):
        (tmp_path / name).symlink_to(real)
    with pytest.raises(SystemExit) if any("unrecognized" in w or "did you mean" in w for w in words) \
            else contextlib.nullcontext():
        assert main(argv) == 2
    err = capsys.readouterr().err
    for w in words:
        assert w in err, err
    assert "build: build:" not in err and "Traceback" not in err


def test_a_scale_is_named_in_either_case(tmp_path, capsys):
    assert main(["build", "--scale", "1m", "--out", str(tmp_path), "--dry-run"]) == 0
    assert "1M.zarr" in capsys.readouterr().out


def test_a_build_says_how_many_query_sets_it_stored():
    """Two query sets of 6,000 rows are 2 query sets of 6,000 rows, not "6,000 query rows"."""
    from vprscale.dataset.build import format_summary

    summary = {"store": "data/mine.zarr", "layout": "full", "ref_rows": 60_000, "query_rows": 6_000, "query_sets": 2,
               "stages_s": {}, "wall_s": 1.0, "peak_rss_bytes": 0, "bytes_on_disk": 0}
    assert "60,000 ref rows, 2 query sets of 6,000 rows" in format_summary(summary)
    assert "6,000 query rows" in format_summary({**summary, "query_sets": 1})
