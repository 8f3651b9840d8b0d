"""The SQL console's sandbox against a list of attacks: none may write, read outside, load code,
change the settings, inject through the index path or exhaust the machine."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import pytest

from vprscale.cli import main
from vprscale.core.errors import InputError
from vprscale.evaluation.sql import KILL_AFTER_S, run_sql

SECRET = "s3cr3t-not-for-sql"


@pytest.fixture(scope="module")
def arena(tiny_index, tmp_path_factory) -> dict[str, Path]:
    """An index under a hostile name, a secret file outside it, a sink folder and a working directory."""
    root = tmp_path_factory.mktemp("arena")
    index = root / "x'); COPY (SELECT 42 AS x) TO 'PWNED.csv'; SELECT ('.index"
    shutil.copytree(tiny_index, index)
    secret = root / "secret.csv"
    secret.write_text(f"key\n{SECRET}\n")
    (root / "outside.parquet").write_bytes((tiny_index / "components.parquet").read_bytes())
    cwd = root / "cwd"
    (cwd / ".tmp").mkdir(parents=True)
    (cwd / ".tmp" / "leak.csv").write_text(f"key\n{SECRET}\n")
    sink = root / "sink"
    sink.mkdir()
    return {"index": index, "secret": secret, "outside": root / "outside.parquet", "cwd": cwd, "sink": sink,
            "root": root}


WRITES = [
    "COPY (SELECT 1) TO '{sink}/a.csv'",
    "COPY lists TO '{sink}/b.parquet' (FORMAT parquet)",
    "EXPORT DATABASE '{sink}/db'",
    "CREATE TABLE t AS SELECT 1",
    "CREATE VIEW v AS SELECT 1",
    "CREATE MACRO m(x) AS x",
    "INSERT INTO lists VALUES (1, 2)",
    "UPDATE lists SET ref_id = 0",
    "DELETE FROM lists",
    "DROP VIEW lists",
    "ATTACH '{sink}/x.db' AS x",
    "ATTACH ':memory:' AS m",
    "DETACH memory",
    "SELECT 1; COPY (SELECT 1) TO '{sink}/c.csv'",
    "SELECT * FROM lists; DROP VIEW lists",
    "PRAGMA profile_output='{sink}/p.json'",
    "PRAGMA enable_profiling='json'",
    "CHECKPOINT",
    "VACUUM",
    "CREATE SECRET s (TYPE s3, KEY_ID 'a', SECRET 'b')",
    "SELECT * FROM query('COPY (SELECT 1) TO ''{sink}/q.csv''')",
    "SELECT * FROM query_table('lists'); COPY (SELECT 1) TO '{sink}/d.csv'",
]
READS = [
    "SELECT * FROM read_text('{secret}')",
    "SELECT * FROM read_csv('{secret}')",
    "SELECT * FROM read_csv_auto('{secret}')",
    "SELECT * FROM read_blob('{secret}')",
    "SELECT * FROM read_json('{secret}')",
    "SELECT * FROM read_json_auto('{secret}')",
    "SELECT * FROM read_ndjson_objects('{secret}')",
    "SELECT * FROM sniff_csv('{secret}')",
    "SELECT * FROM read_parquet('{outside}')",
    "SELECT * FROM parquet_metadata('{outside}')",
    "SELECT * FROM parquet_schema('{outside}')",
    "SELECT * FROM '{secret}'",
    "FROM '{secret}'",
    "SELECT * FROM glob('{root}/*')",
    "SELECT * FROM glob('/etc/*')",
    "SELECT * FROM read_text('.tmp/leak.csv')",
    "SELECT * FROM read_csv('.tmp/leak.csv')",
    "SELECT * FROM read_text('/proc/self/environ')",
    "SELECT * FROM read_text('/etc/passwd')",
    "SELECT * FROM read_text('{index}/index.json')",
    "SELECT * FROM read_parquet('{index}/lists.parquet')",
    "SELECT * FROM read_parquet('http://127.0.0.1:9/x.parquet')",
    "SELECT * FROM read_csv('s3://bucket/x.csv')",
    "SELECT * FROM sqlite_scan('{secret}', 't')",
    "SELECT * FROM query('SELECT * FROM read_text(''{secret}'')')",
    "WITH x AS (SELECT * FROM read_text('{secret}')) SELECT * FROM x",
    "SELECT (SELECT content FROM read_text('{secret}')) AS c",
    "SELECT * FROM lists UNION ALL SELECT 0, 0 FROM read_text('{secret}')",
]
CODE_AND_SETTINGS = [
    "INSTALL httpfs",
    "LOAD httpfs",
    "INSTALL 'json'",
    "LOAD '{sink}/evil.duckdb_extension'",
    "FORCE INSTALL httpfs FROM '{sink}'",
    "SET enable_external_access = true",
    "SET lock_configuration = false",
    "RESET lock_configuration",
    "SET memory_limit = '100GB'",
    "SET allowed_directories = ['/']",
    "SET allowed_paths = ['{secret}']",
    "SET temp_directory = '{sink}'",
    "SET GLOBAL enable_external_access = true",
    "PRAGMA memory_limit = '100GB'",
    "SET threads = 64",
    "SET autoload_known_extensions = true",
    "USE memory",
    "CALL enable_logging()",
]
EXHAUSTION = [
    "SELECT count(*) FROM range(1000000000000)",
    "SELECT count(*) FROM lists a, lists b, lists c",
    "WITH RECURSIVE r(i) AS (SELECT 1 UNION ALL SELECT i + 1 FROM r) SELECT count(*) FROM r",
    "SELECT list(range) FROM range(4000000000)",
    "SELECT string_agg(repeat('x', 1000), '') FROM range(100000000)",
    "SELECT * FROM range(3000000000) ORDER BY random() LIMIT 1",
]
ATTACKS = WRITES + READS + CODE_AND_SETTINGS + EXHAUSTION


def _left_behind(arena: dict[str, Path]) -> list[Path]:
    found = list(arena["sink"].iterdir()) + list(arena["cwd"].glob("PWNED*")) + list(arena["root"].glob("PWNED*"))
    return found + [p for p in Path.cwd().glob("PWNED*")]


def test_the_list_is_long_enough():
    assert len(ATTACKS) >= 60 and len(set(ATTACKS)) == len(ATTACKS)


@pytest.mark.parametrize("attack", ATTACKS)
def test_attack_fails(attack, arena, monkeypatch):
    monkeypatch.chdir(arena["cwd"])
    sql = attack.format(**{k: str(v).replace("'", "''") for k, v in arena.items()})
    t0 = time.perf_counter()
    with pytest.raises(InputError):
        out = run_sql(arena["index"], sql, fmt="csv", timeout=1.0, memory_limit="300MB", threads=1)
        assert SECRET not in out  # reached only if no error: a leak fails here, a quiet success below
    assert time.perf_counter() - t0 < 1.0 + KILL_AFTER_S + 2.0  # the timeout holds
    assert not _left_behind(arena)


def test_hostile_index_name_is_only_a_name(arena, monkeypatch, capsys):
    """The directory name would inject a COPY if it were pasted into SQL; it is not."""
    monkeypatch.chdir(arena["cwd"])
    out = run_sql(arena["index"], "SELECT count(*) AS n FROM buckets", fmt="csv")
    assert out.splitlines()[1].isdigit() and not _left_behind(arena)
    quoted = arena["root"] / "bob's.index"
    shutil.copytree(arena["index"], quoted)
    assert main(["sql", str(quoted), "SELECT count(*) FROM lists", "--csv"]) == 0
    with pytest.raises(SystemExit) as exc:
        main(["sql", str(quoted), "SELECT 1", "--timeout", "-1"])
    assert exc.value.code == 2
    assert "--timeout" in capsys.readouterr().err


def test_legitimate_queries_still_work(arena):
    out = run_sql(arena["index"], "WITH b AS (SELECT size FROM buckets) SELECT max(size) AS m FROM b", fmt="json")
    assert '"m"' in out


@pytest.mark.parametrize("query", ["SELECT list_sort(range(400000000))[1]", "SELECT len(range(1500000000))"])
def test_the_operating_system_holds_the_caps(arena, query):
    """Each query runs in a child process under an address-space cap and a hard timeout: it ends
    within the timeout + 2 s with one line, and its spill directory goes with it."""
    from vprscale.evaluation.sql import Sandbox

    box = Sandbox(arena["index"], "2GB", 2)
    try:
        t0 = time.perf_counter()
        with pytest.raises(InputError, match="timeout|memory limit|Out of Memory"):
            box.query(query, 5.0)
        assert time.perf_counter() - t0 < 5.0 + 2.0
        assert box.query("SELECT count(*) AS n FROM buckets", 5.0).num_rows == 1  # a fresh child answers
    finally:
        box.close()
    assert not Path(box.spill).exists()


def test_a_killed_console_leaves_no_spill_directory(arena):
    import os
    import signal
    import subprocess
    import sys
    import tempfile

    base = Path(tempfile.gettempdir()) / f"vprscale-sql-{os.getuid()}"
    proc = subprocess.Popen([sys.executable, "-m", "vprscale.cli", "sql", str(arena["index"]),
                             "SELECT count(*) FROM range(1000000000000)", "--timeout", "120"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while not list(base.glob(f"{proc.pid}-*")) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert list(base.glob(f"{proc.pid}-*")), "the console never made its spill directory"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    run_sql(arena["index"], "SELECT 1 AS one", fmt="csv")  # the next console removes what the killed one left
    assert not list(base.glob(f"{proc.pid}-*"))


@pytest.mark.parametrize("planted", ["link", "others"])
def test_a_planted_spill_base_removes_nothing(arena, tmp_path, planted):
    """On a shared temporary folder someone plants ``vprscale-sql-<uid>`` as a link to a folder of
    yours, or as a folder anyone may write in, holding ``<digits>-…`` folders of no live process:
    a console uses a private folder of its own instead and removes none of them."""
    import os
    import subprocess
    import sys

    tmpdir, victim = tmp_path / "tmp", tmp_path / "victim"
    (victim / "999999999-work").mkdir(parents=True)
    (victim / "999999999-work" / "thesis.tex").write_text("years of work")
    tmpdir.mkdir()
    kept = []
    for base in (tmpdir / f"vprscale-sql-{os.getuid()}", tmpdir / "vprscale-sql"):  # this one's, and older ones'
        if planted == "link":
            base.symlink_to(victim)
            kept.append(victim / "999999999-work" / "thesis.tex")
        else:
            (base / "999999999-work").mkdir(parents=True)
            base.chmod(0o777)
            kept.append(base / "999999999-work")
    done = subprocess.run([sys.executable, "-m", "vprscale.cli", "sql", str(arena["index"]), "SELECT 1 AS one",
                           "--csv"], capture_output=True, text=True, env={**os.environ, "TMPDIR": str(tmpdir)})
    assert done.returncode == 0 and done.stdout.split() == ['"one"', "1"], done.stderr
    assert all(k.exists() for k in kept)


def test_a_long_tmpdir_still_runs_a_console(arena, tmp_path):
    """The sandbox's forkserver listens on a Unix socket under $TMPDIR, whose path may hold 107
    bytes: a console under a long $TMPDIR answers all the same."""
    import os
    import subprocess
    import sys

    tmpdir = tmp_path / ("t" * 90)
    tmpdir.mkdir()
    done = subprocess.run([sys.executable, "-m", "vprscale.cli", "sql", str(arena["index"]), "SELECT 1 AS one",
                           "--csv"], capture_output=True, text=True, env={**os.environ, "TMPDIR": str(tmpdir)})
    assert done.returncode == 0 and done.stdout.split() == ['"one"', "1"], done.stderr
