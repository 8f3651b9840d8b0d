"""``vprscale run --dry-run``'s estimates (vprscale/jobs/estimates.py): from the stage's own last
run, else a like stage's scaled by the places each reads, else none, never a constant."""

from __future__ import annotations

import json

import pytest

from vprscale.jobs.estimates import estimate, places, read_measurements, save_costs, totals


def _summary(started: str, *stages: dict) -> dict:
    return {"name": "p", "started": started, "stages": list(stages)}


def _stage(name: str, kind: str, params: dict, seconds: float, peak: int, disk: int, n: int | None) -> dict:
    return {"name": name, "kind": kind, "params": params, "places": n, "status": "ran", "seconds": seconds,
            "outputs": {"peak_rss_bytes": peak, "bytes_on_disk": disk}}


@pytest.fixture
def history(tmp_path):
    runs = tmp_path / "out" / "runs"
    runs.mkdir(parents=True)
    (runs / "20261201T100000Z.json").write_text(json.dumps(_summary(
        "20261201T100000Z", _stage("build-1M", "build", {"scale": "1M"}, 100.0, 800, 1_000, 1_000_000),
        _stage("eval-1M", "eval", {"store": "build-1M", "L": [1, 50]}, 60.0, 2_000, 50, 1_000_000))))
    (runs / "20261202T100000Z.json").write_text(json.dumps(_summary(
        "20261202T100000Z", _stage("build-1M", "build", {"scale": "1M"}, 90.0, 700, 1_000, 1_000_000),
        {"name": "eval-1M", "kind": "eval", "params": {"store": "build-1M", "L": [1, 50]}, "status": "skipped",
         "seconds": 0.0})))
    (runs / "broken.json").write_text("{not json")
    return tmp_path


def test_a_stage_is_estimated_by_its_own_last_run(history):
    measured = read_measurements(history / "out", history / "p.toml")
    e = estimate("build-1M", "build", {"scale": "1M"}, 1_000_000, measured)
    assert (e.seconds, e.peak_bytes, e.disk_bytes) == (90.0, 700, 1_000)  # the later run; a skip measures nothing
    assert e.basis == "measured in the run of 2026-12-02 10:00 UTC"
    e = estimate("eval-1M", "eval", {"store": "build-1M", "L": [1, 50]}, 1_000_000, measured)
    assert (e.seconds, e.peak_bytes) == (60.0, 2_000)


def test_another_scale_is_scaled_by_its_places_and_a_build_streams(history):
    measured = read_measurements(history / "out", history / "p.toml")
    build = estimate("build-10M", "build", {"scale": "10M"}, 10_000_000, measured)
    assert (build.seconds, build.peak_bytes, build.disk_bytes) == (900.0, 700, 10_000)  # memory: chunks
    assert build.basis == "scaled from build-1M ×10"
    ev = estimate("eval-10M", "eval", {"store": "build-10M", "L": [1, 50]}, 10_000_000, measured)
    assert (ev.seconds, ev.peak_bytes, ev.disk_bytes) == (600.0, 20_000, 500)
    other = estimate("eval-10M", "eval", {"store": "build-10M", "L": [1, 50, 100]}, 10_000_000, measured)
    assert other.seconds is None and other.basis == "unmeasured"  # other parameters: nothing to go on
    assert estimate("build-x", "build", {"scale": "10M"}, None, measured).seconds is None


def test_totals_sum_the_running_stages_time_and_take_their_largest_peak(history):
    measured = read_measurements(history / "out", history / "p.toml")
    a = estimate("build-1M", "build", {"scale": "1M"}, 1_000_000, measured)
    b = estimate("eval-1M", "eval", {"store": "build-1M", "L": [1, 50]}, 1_000_000, measured)
    c = estimate("eval-x", "eval", {"store": "build-1M", "L": [7]}, 1_000_000, measured)
    assert totals([b, c], [a, b, c]) == {"seconds": 60.0, "peak_bytes": 2_000, "disk_bytes": 1_050, "unmeasured": 1}


def test_saved_costs_estimate_a_machine_with_no_history(history, tmp_path):
    """The costs file beside a pipeline holds each stage's last figures; a fresh output directory
    is estimated from it."""
    stages = [("build-1M", "build", {"scale": "1M"}), ("eval-1M", "eval", {"store": "build-1M", "L": [1, 50]}),
              ("never", "index", {"store": "build-1M"})]
    path = save_costs(history / "p.toml", history / "out", stages, {"cpu": "AMD EPYC", "cores": 2})
    assert path == history / "p.costs.json"
    saved = json.loads(path.read_text())
    assert saved["machine"] == {"cpu": "AMD EPYC", "cores": 2}
    assert [(s["name"], s["seconds"]) for s in saved["stages"]] == [("build-1M", 90.0), ("eval-1M", 60.0)]
    fresh = read_measurements(tmp_path / "empty", history / "p.toml")
    e = estimate("eval-1M", "eval", {"store": "build-1M", "L": [1, 50]}, 1_000_000, fresh)
    assert (e.seconds, e.basis) == (60.0, "measured on the reference machine")


def test_saved_costs_keep_the_figures_of_stages_this_output_never_ran(history, tmp_path):
    """A ladder started again in an empty output (a new machine) refreshes what it measures and
    keeps the costs file's figures of the stages it has not reached, as they were written."""
    stages = [("build-1M", "build", {"scale": "1M"}), ("eval-1M", "eval", {"store": "build-1M", "L": [1, 50]})]
    path = save_costs(history / "p.toml", history / "out", stages, {"cpu": "AMD EPYC", "cores": 2})
    before = {s["name"]: s for s in json.loads(path.read_text())["stages"]}
    runs = tmp_path / "new" / "runs"
    runs.mkdir(parents=True)
    (runs / "20261206T050000Z.json").write_text(json.dumps(_summary(
        "20261206T050000Z", _stage("build-1M", "build", {"scale": "1M"}, 80.0, 600, 1_000, 1_000_000))))
    save_costs(history / "p.toml", tmp_path / "new", stages, {"cpu": "AMD EPYC", "cores": 2})
    after = {s["name"]: s for s in json.loads(path.read_text())["stages"]}
    assert (after["build-1M"]["seconds"], after["build-1M"]["measured"]) == (80.0, "20261206T050000Z")
    assert after["eval-1M"] == before["eval-1M"] and before["eval-1M"]["measured"] == "20261201T100000Z"
    path.write_text("[not a costs file")
    save_costs(history / "p.toml", tmp_path / "new", stages, {"cpu": "AMD EPYC", "cores": 2})
    assert [s["name"] for s in json.loads(path.read_text())["stages"]] == ["build-1M"]


def test_places_follow_the_stages_to_their_build():
    stages = {"b": ("build", {"scale": "1M"}), "i": ("index", {"store": "b"}), "e": ("eval", {"store": "b",
                                                                                             "index": "i"}),
              "r": ("report", {"results": ["e"]})}
    assert places(*reversed(stages["e"]), stages) == places(*reversed(stages["b"]), stages) == 1_000_000
    assert places({"scale": "1M"}, "build", stages) == 1_000_000
    assert places({"results": ["e"]}, "report", stages) is None
    assert places({"store": "elsewhere"}, "eval", stages) is None


def test_a_stage_on_a_compact_store_is_not_scaled_from_one_on_a_full_store(tmp_path):
    """A compact store (100M and up) is built, indexed and encoded by other jobs than a full one:
    its disk is 12 bytes a place, not 1.15 KB; scaling across layouts would say a terabyte."""
    runs = tmp_path / "out" / "runs"
    runs.mkdir(parents=True)
    full = {**_stage("build-1M", "build", {"scale": "1M"}, 15.0, 800, 1_200_000_000, 1_000_000), "layout": "full"}
    compact = {**_stage("build-100M", "build", {"scale": "100M"}, 460.0, 900, 1_300_000_000, 100_000_000),
               "layout": "compact"}
    (runs / "20261201T100000Z.json").write_text(json.dumps(_summary("20261201T100000Z", full)))
    measured = read_measurements(tmp_path / "out", tmp_path / "p.toml")
    assert estimate("build-1B", "build", {"scale": "1B"}, 1_000_000_000, measured, "compact").seconds is None
    assert estimate("build-10M", "build", {"scale": "10M"}, 10_000_000, measured, "full").seconds == 150.0
    (runs / "20261202T100000Z.json").write_text(json.dumps(_summary("20261202T100000Z", compact)))
    measured = read_measurements(tmp_path / "out", tmp_path / "p.toml")
    e = estimate("build-1B", "build", {"scale": "1B"}, 1_000_000_000, measured, "compact")
    assert (e.seconds, e.disk_bytes, e.basis) == (4600.0, 13_000_000_000, "scaled from build-100M ×10")
