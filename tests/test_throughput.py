"""Throughput in the field's units (rows a second per core, GB a second) beside the wall time."""

from __future__ import annotations

import re

import numpy as np

from vprscale.cli import main
from vprscale.core.throughput import throughput
from vprscale.dataset.sources.fas import open_fas


def test_rows_and_bytes_a_second_per_core():
    assert throughput(1_000_000, 4 * 10**9, 10.0, 4) == (
        "1,000,000 rows (4.00 GB) in 10.0 s: 100,000 rows/s, 25,000 rows/s per core on 4 cores, 0.400 GB/s")
    assert "per connection on 1 connection," in throughput(10, 10, 1.0, 1, per="connection")


def test_a_build_says_what_it_read_in_the_fields_units(recipe, sources, tmp_path, capsys):
    assert main(["build", "--scale", str(recipe), "--out", str(tmp_path), "--deep1b", str(sources["fbin"]),
                 "--fas", str(sources["fas"]), "--workers", "2"]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.strip().startswith("read "))
    fas = open_fas(sources["fas"])
    rows = 60_000 + fas.ref.n_rows + fas.query.n_rows  # the recipe's Deep1B rows read, and every FAS row
    nbytes = 4 * (60_000 * 96 + (fas.ref.n_rows + fas.query.n_rows) * fas.ref.dim)
    got = re.search(r"read ([\d,]+) rows \(([\d.]+) GB\) in ([\d.,]+) s: ([\d,]+) rows/s, ([\d,]+) rows/s per core "
                    r"on 2 cores, ([\d.]+) GB/s", line)
    assert got is not None, line
    assert int(got[1].replace(",", "")) == rows and got[2] == f"{nbytes / 1e9:.2f}"
    per_s = int(got[4].replace(",", ""))
    assert np.isclose(int(got[5].replace(",", "")), per_s / 2, atol=1)


def test_bench_build_reads_a_corpus_by_url(recipe, sources, tmp_path, capsys):
    """The I/O floor re-reads the local inputs only; a corpus read by URL is timed as the build reads it."""
    from .test_fetch import _bytes_server

    for server in _bytes_server(sources["fbin"].read_bytes()):
        assert main(["bench", "build", str(recipe), "--deep1b", server.url, "--fas", str(sources["fas"]),
                     "--out", str(tmp_path / "b"), "--workers", "2"]) == 0
    said = capsys.readouterr().out
    assert "rows/s per core on 2 cores" in said and "I/O floor: read" in said
