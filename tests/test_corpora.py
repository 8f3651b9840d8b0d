"""Other billion-scale corpora as the recipe's large part (docs/dataset.md, "Other corpora"):
``build --base CORPUS:PATH`` and ``fetch CORPUS --rows N``.

The corpus files are written by numpy in big-ann-benchmarks' ``bin`` layout (a header of two
uint32, then the rows), as its own tools write them.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
import zarr

from vprscale.cli import main
from vprscale.cli.fetch import SOURCES as CLI_SOURCES
from vprscale.dataset.fetch import SOURCES
from vprscale.dataset.sources.deep1b import open_deep1b

from .conftest import write_recipe
from .test_fetch import _bytes_server

ROWS = 60_000  # the small recipe's Deep1B rows read


def _sift(n: int) -> np.ndarray:
    """SIFT-like 128-d uint8 rows: non-negative, skewed, correlated along the traverse."""
    rng = np.random.default_rng(7)
    walk = np.cumsum(rng.normal(size=(n, 128)), axis=0) * 0.3
    return np.clip(rng.gamma(2.0, 12.0, size=(n, 128)) + walk - walk.min(axis=0), 0, 255).astype(np.uint8)


def _write_bin(path, rows: np.ndarray) -> None:
    with open(path, "wb") as fh:
        fh.write(struct.pack("<II", *rows.shape))
        fh.write(rows.tobytes())


@pytest.fixture(scope="module")
def bigann(tmp_path_factory, sources):
    """A tiny store built from a 128-d u8bin corpus, and from the same rows as a 128-d fbin and an .npy."""
    root = tmp_path_factory.mktemp("bigann")
    rows = _sift(ROWS)
    _write_bin(root / "base.u8bin", rows)
    _write_bin(root / "base.fbin", rows.astype("<f4"))
    np.save(root / "base.npy", rows)
    recipe = write_recipe(root / "tiny.toml")
    stores = {}
    for name, base in (("u8", "bigann:" + str(root / "base.u8bin")), ("f32", str(root / "base.fbin")),
                       ("npy", "bigann:" + str(root / "base.npy"))):
        assert main(["build", "--scale", str(recipe), "--base", base, "--fas", str(sources["fas"]),
                     "--out", str(root / name), "--workers", "2", "-q"]) == 0
        stores[name] = root / name / "tiny.zarr"
    return stores


@pytest.mark.slow
def test_a_wider_corpus_is_projected_to_the_recipes_width(bigann):
    group = zarr.open_group(bigann["u8"], mode="r")
    assert group["ref"].shape[1] == 96 and group["transforms/deep1b_components"].shape == (96, 128)
    assert group["transforms/deep1b_mean"].shape == (128,)
    source = group.attrs["vprscale"]["sources"]["deep1b"]
    assert source["dim"] == 128 and "u8bin" in str(source)  # the corpus as read, recorded in the store


@pytest.mark.slow
@pytest.mark.parametrize("form", ["f32", "npy"])
def test_the_same_rows_in_another_form_give_the_same_store(bigann, form):
    one, other = (zarr.open_group(bigann[k], mode="r") for k in ("u8", form))
    for name in ("ref", "query_qm1", "query_qm2", "gt"):
        assert np.array_equal(one[name][:], other[name][:]), name


@pytest.mark.slow
def test_a_store_of_another_corpus_is_indexed_and_evaluated(bigann, tmp_path):
    assert main(["index", str(bigann["u8"]), "--out", str(tmp_path / "i"), "-q"]) == 0
    assert main(["eval", str(bigann["u8"]), str(tmp_path / "i"), "--L", "1,9", "--noise", "qm1", "--no-baseline",
                 "--repeats", "1", "--out", str(tmp_path / "e"), "-q"]) == 0


@pytest.mark.parametrize(("base", "says"), [
    ("turing:{u8}", "128-d rows, but turing's are 100-d"),
    ("nope:{u8}", "nope is not a corpus vprscale knows"),
    ("bigann:", "give the bigann file after the colon"),
])
@pytest.mark.slow
def test_a_corpus_that_is_not_what_it_is_said_to_be_is_refused(bigann, tmp_path, capsys, base, says):
    u8 = bigann["u8"].parent.parent / "base.u8bin"
    code = main(["build", "--scale", str(write_recipe(tmp_path / "tiny.toml")), "--base", base.format(u8=u8),
                 "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and says in err and "\n" not in err and not (tmp_path / "o" / "tiny.zarr").exists()


def test_a_narrower_corpus_is_refused(tmp_path, capsys):
    _write_bin(tmp_path / "narrow.fbin", np.ones((ROWS, 64), "<f4"))
    code = main(["build", "--scale", str(write_recipe(tmp_path / "tiny.toml")), "--base", str(tmp_path / "narrow.fbin"),
                 "--out", str(tmp_path / "o")])
    assert code == 2 and "64 dimensions, fewer than the recipe's 96" in capsys.readouterr().err


def test_fetch_crops_another_corpus_base_file(tmp_path, monkeypatch):
    monkeypatch.setattr("vprscale.core.ranged.PART_BYTES", 1 << 16)
    rows = _sift(20_000)
    data = struct.pack("<II", *rows.shape) + rows.tobytes()
    for server in _bytes_server(data):
        assert main(["fetch", "bigann", "--rows", "5K", "--url", server.url, "--out", str(tmp_path), "-q"]) == 0
    got = (tmp_path / "bigann.base.5K.u8bin").read_bytes()
    assert got == struct.pack("<II", 5_000, 128) + rows[:5_000].tobytes()  # big-ann-benchmarks' crop
    src = open_deep1b(tmp_path / "bigann.base.5K.u8bin")  # its manifest checked as it opens
    assert (src.n_rows, src.dim) == (5_000, 128)
    np.testing.assert_array_equal(src.read(0, 5_000), rows[:5_000].astype(np.float32))


def test_fetch_refuses_a_file_of_another_width(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("vprscale.core.ranged.PART_BYTES", 1 << 16)
    data = struct.pack("<II", 1_000, 100) + bytes(100_000)
    for server in _bytes_server(data):
        code = main(["fetch", "bigann", "--rows", "1K", "--url", server.url, "--out", str(tmp_path)])
    assert code == 2 and "100-d rows, but bigann's are 128-d" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_the_command_line_offers_every_source_fetch_knows():
    assert set(CLI_SOURCES) == set(SOURCES)


@pytest.mark.slow
def test_a_pipeline_build_stage_takes_a_corpus_by_one_key(bigann, tmp_path):
    from vprscale.core.digests import DigestCache
    from vprscale.jobs.pipeline import _inputs, load_pipeline, stage_command

    u8 = bigann["u8"].parent.parent / "base.u8bin"
    path = tmp_path / "p.toml"
    path.write_text(f'name = "p"\nout = "{tmp_path / "out"}"\n[[stages]]\nname = "b"\nkind = "build"\n'
                    f'scale = "20K"\nbase = "bigann:{u8}"\n')
    pipe = load_pipeline(path)
    cmd = stage_command(pipe, pipe.stages[0], {}, None)
    assert cmd[cmd.index("--base") + 1] == f"bigann:{u8}" and "--deep1b" not in cmd
    found = _inputs(pipe.stages[0], DigestCache(tmp_path / "digests.json"))
    assert found["base"]["dim"] == 128  # the file's fingerprint: a changed corpus file reruns the stage
