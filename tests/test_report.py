"""Report generation on a small hand-made results table."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vprscale.cli import main
from vprscale.core.manifest import write_manifest
from vprscale.evaluation.accounting import time_cell
from vprscale.evaluation.report import write_report

from .conftest import CHROMIUM, chromium


def _publish(folder, summary):
    """An evaluation's summary and, as publishing writes last, its manifest."""
    (folder / "eval.json").write_text(json.dumps(summary))
    write_manifest(folder)


def _results(tmp_path):
    rows = []
    for noise in ("qm1", "qm2"):
        for method, mode, L, d in (("coarsehash", None, 1, 15), ("coarsehash", "paper", 50, 15),
                                   ("coarsehash", "aligned", 50, 15), ("baseline", None, 50, 1)):
            for part in ("all", "deep1b", "fas"):
                for r in range(21):
                    rows.append({"noise": noise, "method": method, "mode": mode, "L": L, "d": d, "K": 2,
                                 "part": part, "radius": r, "recall": min(1.0, 0.03 * r + (0.5 if mode else 0.0)),
                                 "recall_in_list": 0.9 if L == 1 and method == "coarsehash" else None,
                                 "n_queries": 100, "nr_mean": 70.0, "nr_median": 68.0, "nr_p95": 90.0,
                                 "us_per_query": 5.0 if method == "coarsehash" else 500.0,
                                 "us_per_frame": 1.0 if method == "coarsehash" else None,
                                 "ops_per_query": 5e4 if method == "coarsehash" else 6e7,
                                 "index": str(tmp_path / "i.index"), "scale": "20K", "store": "s",
                                 "store_identity": "x"})
    (tmp_path / "ev").mkdir()
    pd.DataFrame(rows).to_parquet(tmp_path / "ev" / "results.parquet")
    _publish(tmp_path / "ev", {})
    idx = tmp_path / "i.index"
    idx.mkdir()
    storage = {p: {"paper": 8 * v, "packed": 4 * v, "disk": 5 * v} for p, v in
               (("P1", 20000), ("P2", 30), ("P3", 1440), ("P4", 96))}
    storage["total"] = {k: sum(s[k] for s in storage.values()) for k in ("paper", "packed", "disk")}
    (idx / "index.json").write_text(json.dumps({
        "kind": "coarsehash-index", "complete": True, "d": 15, "k": 2, "n_ref": 20000, "storage": storage,
        "store": {"scale": "20K", "rescale": True, "built": {"wall_s": 12.0, "peak_rss_bytes": 2**30}},
        "wall_s": 3.0, "peak_rss_bytes": 2**29}))
    comp = pd.DataFrame({"component": np.repeat(np.arange(1, 16), 2), "cluster": np.tile([0, 1], 15),
                         "centre": 0.0, "refs": 10, "share": np.tile([0.4, 0.6], 15), "variance": 1.0})
    comp.to_parquet(idx / "components.parquet")
    return tmp_path / "ev"


def test_report_writes_every_figure_and_the_right_numbers(tmp_path):
    rep = write_report([_results(tmp_path)], tmp_path / "rep")
    for name in ("fig3_recall", "fig4b_single_frame", "fig4c_storage", "fig4d_balance"):
        for ext in ("png", "pdf"):
            assert (tmp_path / "rep" / f"{name}.{ext}").stat().st_size > 1000
    text = (tmp_path / "rep" / "report.md").read_text()
    # R@5 of paper mode L = 50: 0.03·5 + 0.5 = 65 %; R@20: 100 %.
    assert "| 20K | QM1 | 50 | CoarseHash paper | hashing | 100 | 50.0 | 65.0 | 80.0 | 100.0 |" in text
    assert "| 20K | 50 | 50,000 | 60,000,000 | 1,200× | 5.00 | 1.00 | 500.00 | 100× |" in text
    assert "| 20K | 15 | 12.0 | 1.00 | 3.0 | 0.50 | – | – |" in text
    assert "| 20K | 15 | 20,000 | 0.160 |" in text
    assert "37,400" in text and len(rep["figures"]) == 8


def test_report_opens_with_provenance_and_flags_mixed_commits(tmp_path):
    first = _results(tmp_path)
    record = {"vprscale": "0.3.0", "commit": "a" * 40, "dirty": False, "command": "vprscale eval s i",
              "cpu": "Test CPU", "cores": 2, "load_average": [0.1, 0.2, 0.3], "time": "2026-11-30T00:00:00+00:00"}
    _publish(first, {"wall_s": 1.0, "provenance": record})
    text = write_report([first], tmp_path / "one")["report"]
    head = open(text).read().split("## Figures")[0]
    assert "## Provenance" in head and "commit aaaaaaaaaaaa" in head and "Test CPU (2 cores" in head
    assert "different commits" not in head
    second = tmp_path / "ev2"
    second.mkdir()
    res = pd.read_parquet(first / "results.parquet")
    res.assign(scale="1M").to_parquet(second / "results.parquet")
    _publish(second, {"wall_s": 1.0, "provenance": {**record, "commit": "b" * 40, "dirty": True}})
    head = open(write_report([first, second], tmp_path / "two")["report"]).read().split("## Figures")[0]
    assert "**These results come from 2 different commits** (aaaaaaaaaaaa, bbbbbbbbbbbb (dirty tree))" in head


def test_a_report_shows_paths_of_this_machine_relative(tmp_path, monkeypatch):
    """The provenance block shows the working directory's and home's paths relative (a report is
    committed and read elsewhere); the evaluation's own record keeps them whole."""
    monkeypatch.chdir(tmp_path)
    first = _results(tmp_path)
    record = {"vprscale": "0.5.0", "commit": "a" * 40, "dirty": False, "cpu": "Test CPU", "cores": 2,
              "command": f"vprscale eval {tmp_path}/data/s.zarr {Path.home()}/i.index", "load_average": [0, 0, 0],
              "time": "2026-11-30T00:00:00+00:00"}
    _publish(first, {"wall_s": 1.0, "provenance": record})
    head = open(write_report([first], tmp_path / "one")["report"]).read().split("## Figures")[0]
    assert str(tmp_path) not in head and str(Path.home()) + "/" not in head
    assert "`vprscale eval data/s.zarr ~/i.index`" in head and "- results ev:" in head
    assert str(tmp_path) not in (tmp_path / "one" / "recall_table.csv").read_text()


@pytest.fixture(scope="module")
def two_noise_report(tiny_store, tiny_index, tmp_path_factory):
    """A report of CoarseHash, the baseline and one FAISS code on both noise levels, with radii
    in metres on the FAS part (the recipe's store keeps its poses)."""
    tmp = tmp_path_factory.mktemp("html")
    assert main(["eval", str(tiny_store), str(tiny_index), "--L", "1,5", "--z", "97", "--noise", "qm1,qm2",
                 "--compare", "PQ4np", "--repeats", "1", "--radius-m", "5,25", "--out", str(tmp / "e")]) == 0
    assert main(["report", str(tmp / "e"), "--out", str(tmp / "r")]) == 0
    return tmp / "e", tmp / "r"


@pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (.ci/run installs it)")
def test_report_html_draws_every_figure_of_every_noise_level_in_a_browser(two_noise_report, tmp_path):
    """report.html, opened by headless Chromium from the file alone (every host unresolvable):
    no error in
    the page or its console, every figure drawn (Plotly's points in the page, and pixels of
    the methods' colours in a screenshot), each figure's table holding points of both noise
    levels, and the embedded rows the results' rows over all queries; the figure in metres from
    the rows in metres."""
    import json as _json

    from PIL import Image

    from vprscale.evaluation.htmlreport import FIGURES, METRES_FIGURE

    evaluation, report = two_noise_report
    page = report / "report.html"
    text = page.read_text()
    loaded = chromium("--dump-dom", page.as_uri() + "#noise=all&L=all")  # every row, as the address asks
    assert ":CONSOLE" not in loaded.stderr, loaded.stderr
    dom = loaded.stdout
    assert 'data-drawn="yes"' in dom and '<pre id="page-errors" hidden=""></pre>' in dom
    for fig, *_ in (*FIGURES, METRES_FIGURE):
        block = dom.split(f'id="{fig}"', 1)[1].split('class="figure"', 1)[0]
        assert int(re.search(r'data-points="(\d+)"', block).group(1)) > 0
        assert block.count('class="point"') > 0  # Plotly drew the points
        table = dom.split(f'id="{fig}-table"', 1)[1].split("</table>", 1)[0]
        assert 'data-noise="qm1"' in table and 'data-noise="qm2"' in table
    rows = _json.loads(text.split('<script id="rows" type="application/json">', 1)[1].split("</script>", 1)[0])
    res = pd.read_parquet(evaluation / "results.parquet")
    assert len(rows) == int((res.part == "all").sum()) and {r["noise"] for r in rows} == {"qm1", "qm2"}
    rows_m = _json.loads(text.split('<script id="rows-m" type="application/json">', 1)[1].split("</script>", 1)[0])
    res_m = pd.read_parquet(evaluation / "results_m.parquet")
    assert len(rows_m) == len(res_m) > 0 and {r["radius_m"] for r in rows_m} == {5, 25}
    opened = chromium("--dump-dom", page.as_uri()).stdout  # the opening view: one noise level, a legend
    table = opened.split('id="fig-radius-table"', 1)[1].split("</table>", 1)[0]
    assert 'data-noise="qm1"' in table and 'data-noise="qm2"' not in table
    assert opened.split('id="fig-qps"', 1)[1].split('id="fig-bytes"', 1)[0].count('class="legend"') == 1
    asked = chromium("--dump-dom", page.as_uri() + "#noise=qm2").stdout.split('id="fig-radius-table"', 1)[1]
    assert 'data-noise="qm2"' in asked.split("</table>", 1)[0] and 'data-noise="qm1"' not in asked.split("</table>")[0]
    chromium("--window-size=1300,2600", f"--screenshot={tmp_path / 'shot.png'}", page.as_uri() + "#noise=all&L=all")
    shot = np.asarray(Image.open(tmp_path / "shot.png").convert("RGB")).reshape(-1, 3).astype(int)
    colours = _json.loads(re.search(r"var COLOURS = (\{.*?\}), SYMBOLS", text).group(1))
    assert set(colours) == {"CoarseHash", "baseline", "PQ4np"}
    for method, colour in colours.items():  # each method's points and lines are on the screen
        rgb = np.array([int(colour[i : i + 2], 16) for i in (1, 3, 5)])
        assert (np.abs(shot - rgb).max(axis=1) <= 12).sum() > 200, method


HOSTILE = ("<img src=x onerror=\"document.body.dataset.pwned='img'\">",
           "</script><script>document.body.dataset.pwned='script'</script>",
           "\x1b]0;title\x07|`tick`|&amp;")


def test_every_label_is_text_in_the_report_and_its_page(two_noise_report, tmp_path):
    """A method's name or parameters can be anything a plug-in or an evaluation folder says: in
    report.md they are escaped text (no HTML, no broken table, no control characters); in
    report.html no value can close a script element or become markup, and, opened in Chromium,
    none runs, while each is shown as the text it is."""
    evaluation = tmp_path / "e"
    shutil.copytree(two_noise_report[0], evaluation)
    res = pd.read_parquet(evaluation / "results.parquet")
    faiss = res[res.method == "faiss:PQ4np"]
    extra = [faiss.assign(**{where: name}, bytes_per_place=faiss.bytes_per_place + 3 * j + i + 1)
             for j, where in enumerate(("method", "params")) for i, name in enumerate(HOSTILE)]
    extra[1] = extra[1].assign(recall=1.0)  # the best compared method: named in report.md's summary lines
    pd.concat([res, *extra]).to_parquet(evaluation / "results.parquet")
    write_manifest(evaluation)
    report = tmp_path / "rep"
    write_report([evaluation], report)
    text = (report / "report.md").read_text()
    assert not re.search(r"(?<!\\)<(img|script|/script)", text) and "\x1b" not in text  # every tag escaped
    tables = re.findall(r"(?m)(?:^\|.*\n)+", text)  # each table's lines: as many cells in each as in its header
    assert any("title" in t for t in tables)
    for table in tables:
        assert len({len(re.split(r"(?<!\\)\|", line)) for line in table.splitlines()}) == 1, table
    page = (report / "report.html").read_text()
    body = page.split("</style>", 1)[1]  # after plotly.js, which holds its own markup strings
    assert "<img src=x" not in body and "</script><script>document" not in body and "\x1b" not in body
    if CHROMIUM is None:
        return
    dom = chromium("--dump-dom", (report / "report.html").as_uri()).stdout
    assert 'data-drawn="yes"' in dom and "data-pwned" not in dom and 'src="x"' not in dom  # no element made
    assert "&lt;img src=x onerror=" in dom  # shown as text, in the figures' tables


def test_the_headline_ratio_is_against_the_fastest_point_of_the_same_recall():
    """The summary's speed-up is quoted against the fastest compared point that reaches CoarseHash's
    recall (its interval's lower end), not against the compared point of highest recall, which a
    larger k of the same code reaches for one query more at twice the time; the point that finds
    most is named apart, with its own time and no ratio."""
    from vprscale.evaluation.comparison import _words

    def point(method, params, recall, us, lo=None, hi=None):
        return {"scale": "20K", "noise": "qm2", "L": 100, "method": method, "mode": "aligned", "d": 15,
                "params": params, "recall": recall, "recall_lo": lo if lo is not None else recall - 0.002,
                "recall_hi": hi if hi is not None else min(1.0, recall + 0.002), "us_per_query": us,
                "bytes_per_place": 2.0, "run": "r"}

    points = pd.DataFrame([
        point("coarsehash", None, 0.998, 5.9, lo=0.996),
        point("faiss:ITQ16,LSH", "k=12", 0.9986, 545.4),   # the highest recall: one query in 1,696 more
        point("faiss:ITQ16,LSH", "k=4", 0.998, 238.9),     # CoarseHash's recall
        point("faiss:PQ2", "k=4", 0.997, 118.4),           # within CoarseHash's interval, and fastest
        point("faiss:PQ2", "k=1", 0.90, 20.0),             # fast, but short of it
    ])
    (line,) = _words(points, ["20K"])
    assert "fastest compared point at the same recall" in line and "PQ2 k=4 (aligned)" in line
    assert "answers 20× faster" in line and "92×" not in line
    assert "finds most, ITQ16,LSH k=12 (aligned), finds 99.9 % in 545.4 µs." in line
    (line,) = _words(points[(points.method == "coarsehash") | (points.recall < 0.99)], ["20K"])  # none reaches it
    assert "No compared point reaches it" in line and "faster" not in line


@pytest.mark.slow
def test_times_are_set_against_each_other_from_the_run_that_measured_both(tiny_store, tiny_index, tmp_path):
    """A point two runs evaluated (CoarseHash alone, then again beside the baseline and a code, as
    a d sweep and a scale's evaluations in two parts do) is shown once, and its speed-ups are
    quoted from the run that measured both points: CoarseHash's time in the compute table and in
    the summary is that run's, and no ratio is left out for coming from different runs."""
    alone, beside = tmp_path / "alone", tmp_path / "beside"
    common = ["eval", str(tiny_store), str(tiny_index), "--L", "1,5", "--noise", "qm1", "--repeats", "1", "-q"]
    assert main([*common, "--no-baseline", "--out", str(alone)]) == 0
    assert main([*common, "--compare", "PQ4np", "--out", str(beside)]) == 0
    write_report([alone, beside], tmp_path / "r")  # the first given keeps its rows of the shared points
    text = (tmp_path / "r" / "report.md").read_text()
    assert "different run" not in text
    res = pd.read_parquet(beside / "results.parquet")
    ours = res[(res.method == "coarsehash") & (res.part == "all") & (res.noise == "qm1")]
    compute = text.split("## Compute per query", 1)[1].split("\n## ", 1)[0]
    for L in (1, 5):
        row = ours[(ours.L == L) & (ours.radius == 0) & ours["mode"].fillna("paper").eq("paper")].iloc[0]
        line = next(x for x in compute.splitlines() if x.startswith(f"| {row.scale} | {L} |"))
        assert f"| {time_cell(row)} |" in line and line.rstrip(" |").endswith("×"), line
    summary = [x for x in text.splitlines() if x.startswith(f"- {ours.scale.iloc[0]}, QM1, L = ")]
    assert summary and all("faster" in x or "slower" in x or "No compared point" in x for x in summary)
    for x in summary:
        L = int(x.split("L = ", 1)[1].split(":", 1)[0])
        shown = float(re.search(r"CoarseHash \w+ finds [\d.]+ % in ([\d.,]+) µs", x).group(1).replace(",", ""))
        assert shown in {round(u, 1) for u in ours[(ours.L == L) & (ours.radius == 20)].us_per_query}, x


def test_report_html_holds_the_whole_report(two_noise_report):
    """Every figure of report.md is in report.html (embedded, named as in report.md), every table
    of it too, and the provenance reads as text (no raw ``**`` Markdown); in Chromium each figure
    loads and the interactive figures open with their legends."""
    report = two_noise_report[1]
    text, page = (report / "report.md").read_text(), (report / "report.html").read_text()
    figures = re.findall(r"^!\[[^\]]*\]\(([^)]+)\.png\)$", text, re.M)
    assert len(figures) >= 10
    embedded = re.findall(r'<figure class="static" data-name="([^"]+)"><img alt="[^"]*" src="data:image/png;base64,',
                          page)
    assert embedded == figures
    tables = re.findall(r"(?m)^\|.*\n\|---", text)
    assert page.count('<table class="static">') == len(tables) > 5
    provenance = page.split('<ul id="provenance">', 1)[1].split("</ul>", 1)[0]
    assert "**" not in provenance and "<code>" in provenance
    if CHROMIUM is None:
        return
    dom = chromium("--dump-dom", report.joinpath("report.html").as_uri()).stdout
    assert 'data-drawn="yes"' in dom and dom.count('<figure class="static"') == len(figures)
    assert dom.count('class="legend"') >= 3  # each interactive figure's legend, on first view
