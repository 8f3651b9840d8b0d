"""An adversary mutates published outputs (bytes, files, manifests, symbolic links); every reader
either refuses in one line with exit 2 or answers exactly as it did before (hypothesis)."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vprscale.cli import main

MUTATIONS = ("flip", "truncate", "append", "delete", "link", "drop_manifest", "manifest_size", "manifest_crc")


def _run(argv: list[str], *roots: Path) -> tuple[int, str, str]:
    """Exit status, standard output and standard error of one command, paths under ``roots`` (the
    copy read, and the original its evaluation names) as ``ROOT``."""
    out, err = io.TextIOWrapper(io.BytesIO(), encoding="utf-8"), io.StringIO()  # localise writes CSV bytes
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    out.flush()
    text = out.buffer.getvalue().decode()
    for root in roots:
        text = text.replace(str(root), "ROOT")
    return code, text, err.getvalue()


def _readers(root: Path) -> dict[str, list[str]]:
    """What reads the store, the index and its evaluation: each output reached by more than one."""
    store, index = root / "s.zarr", root / "i.index"
    return {"verify store": ["verify", str(store)], "verify index": ["verify", str(index)],
            "occupancy": ["occupancy", str(index), "--json"],
            "sql": ["sql", str(index), "SELECT count(*) AS n, sum(size) AS s FROM buckets", "--csv"],
            "results": ["results", str(index), "--csv", "--all-columns"],
            "localise": ["localise", str(index), str(store / "query_qm1"), "--L", "5", "-q"]}


@pytest.fixture(scope="module")
def published(tiny_store, tiny_index, tmp_path_factory) -> tuple[Path, dict[str, tuple[int, str]]]:
    """A store, an index and its evaluation side by side, and every reader's answer on them."""
    root = tmp_path_factory.mktemp("mutations")
    shutil.copytree(tiny_store, root / "s.zarr")
    shutil.copytree(tiny_index, root / "i.index")
    assert main(["eval", str(root / "s.zarr"), str(root / "i.index"), "--L", "1,5", "--z", "97", "--noise", "qm1",
                 "--repeats", "1", "-q"]) == 0
    before = {}
    for name, argv in _readers(root).items():
        code, out, _ = _run(argv, root)
        assert code == 0, name
        before[name] = out
    return root, before


def _files(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file() and not p.name.startswith("."))


def _mutate(root: Path, rel: str, how: str, at: float, outside: Path) -> None:
    path = root / rel
    data = path.read_bytes()
    pos = min(len(data) - 1, int(at * len(data))) if data else 0
    if how == "flip" and data:
        path.write_bytes(data[:pos] + bytes([data[pos] ^ 0x5A]) + data[pos + 1:])
    elif how == "truncate":
        path.write_bytes(data[:pos])
    elif how == "append":
        path.write_bytes(data + b"\0" * 8)
    elif how == "delete":
        path.unlink()
    elif how == "link":  # the same bytes, from outside the output
        copy = outside / rel.replace("/", "_")
        copy.write_bytes(data)
        path.unlink()
        path.symlink_to(copy)
    elif how == "drop_manifest":
        (root / "manifest.json").unlink(missing_ok=True)
    else:  # the manifest's entry of the file edited to match a forgery (or a wrong one's)
        try:
            manifest = json.loads((root / "manifest.json").read_text())
            entry = manifest["files"].get(rel) or manifest["files"][sorted(manifest["files"])[0]]
            if how == "manifest_size":
                entry["bytes"] += 1
            else:
                entry["crc32c"] = f"{int(entry['crc32c'], 16) ^ 1:08x}"
        except (OSError, ValueError, KeyError, TypeError, IndexError, AttributeError):
            return  # an earlier step left no manifest to edit
        (root / "manifest.json").write_text(json.dumps(manifest))


OUTPUTS = {"store": "s.zarr", "index": "i.index", "evaluation": "i.index/eval"}


@pytest.mark.slow
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                  HealthCheck.too_slow])
@given(data=st.data(), output=st.sampled_from(sorted(OUTPUTS)),
       steps=st.lists(st.tuples(st.sampled_from(MUTATIONS), st.floats(0.0, 1.0)), min_size=1, max_size=3))
def test_every_reader_refuses_a_mutated_output_or_answers_as_before(published, data, output, steps):
    """One to three mutations of one output, so that a forger may also remove or edit what would
    catch the others (its manifest)."""
    source, before = published
    with tempfile.TemporaryDirectory() as tmp:
        root, outside = Path(tmp) / "root", Path(tmp) / "outside"
        shutil.copytree(source, root, symlinks=True)
        outside.mkdir()
        target = root / OUTPUTS[output]
        done = []
        for how, at in steps:
            files = [f for f in _files(target) if not (target / f).is_symlink()
                     and (output != "index" or not f.startswith("eval/"))]
            rel = data.draw(st.sampled_from(files), label="file")
            _mutate(target, rel, how, at, outside)
            done.append((rel, how))
        for name, argv in _readers(root).items():
            code, out, err = _run(argv, root, source)
            assert "Traceback" not in err, (name, output, done, err)
            if code == 0:
                assert out == before[name], (name, output, done)
            else:
                assert code == 2, (name, output, done, code, err)
                assert err.strip().splitlines()[-1].startswith("vprscale "), (name, output, done, err)
