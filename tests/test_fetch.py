"""``vprscale fetch`` against a real HTTP server on the loopback address that serves byte ranges,
drops connections, ignores ranges and lies about lengths (started and stopped by each test)."""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import google_crc32c
import numpy as np
import pytest

from vprscale.cli import main
from vprscale.dataset.sources.deep1b import open_deep1b

from .test_reliability import fails

DIM = 96


def deep_rows(n: int) -> bytes:
    """A Deep1B-shaped ``.fbin`` of ``n`` rows whose values depend only on their position."""
    values = (np.arange(n * DIM, dtype=np.float64) % 1009 / 7).astype("<f4")
    return struct.pack("<II", n, DIM) + values.tobytes()


@dataclass
class Behaviour:
    """How the served file misbehaves (each a count of requests still to misbehave, or a flag)."""

    drops: int = 0  # close the connection halfway through a range, this many times
    short: int = 0  # promise the whole range, send half of it and close, this many times
    cut_from: int | None = None  # send half of every range that starts at or after this byte, and close
    empty_from: int | None = None  # send none of every range that starts at or after this byte, and close
    ignore_ranges: bool = False  # answer 200 with the whole file
    delay_s: float = 0.0  # pause per 64 KiB sent (a slow link)
    redirect: str | None = None  # answer every GET with a 302 to this URL
    change_after: int | None = None  # after this many requests, serve other bytes under another ETag
    requests: list[str] = field(default_factory=list)
    authorizations: list[str | None] = field(default_factory=list)


class _QuietServer(ThreadingHTTPServer):
    def handle_error(self, request, client_address) -> None:
        """A client that hangs up mid-answer (a fetch cut off on purpose) is no error of the test's."""
        if not isinstance(sys.exc_info()[1], ConnectionError):
            super().handle_error(request, client_address)


class Server:
    """A threaded HTTP/1.0 server of one file (``content(start, stop)`` of ``size`` bytes)."""

    def __init__(self, content: Callable[[int, int], bytes], size: int) -> None:
        self.content, self.size, self.behaviour, self.etag = content, size, Behaviour(), '"v0"'
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:  # quiet: the test reads what it needs
                pass

            def do_GET(self) -> None:  # noqa: N802 - http.server's name
                if self.path.endswith("/missing"):
                    self.send_error(404)
                    return
                b = server.behaviour
                rng = self.headers.get("Range", "")
                b.requests.append(rng)
                b.authorizations.append(self.headers.get("Authorization"))
                if b.redirect:
                    self.send_response(302)
                    self.send_header("Location", b.redirect)
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                if b.change_after is not None and len(b.requests) > b.change_after:
                    data = server.content(0, server.size)
                    server.content, server.etag = (lambda a, z: bytes(reversed(data))[a:z]), '"changed"'
                    b.change_after = None
                if not rng.startswith("bytes=") or b.ignore_ranges:
                    start, stop, status = 0, server.size, 200
                else:
                    first, _, last = rng[6:].partition("-")
                    start, stop, status = int(first), min(server.size, int(last) + 1), 206
                    if start >= server.size:
                        self.send_error(416)
                        return
                cut = stop
                if status == 206 and b.drops > 0 and stop - start > 1:
                    b.drops -= 1
                    cut = start + (stop - start) // 2
                if status == 206 and b.short > 0 and stop - start > 1:
                    b.short -= 1
                    cut = start + (stop - start) // 2
                if status == 206 and b.cut_from is not None and start >= b.cut_from:
                    cut = start + (stop - start) // 2
                if status == 206 and b.empty_from is not None and start >= b.empty_from:
                    cut = start
                self.send_response(status)
                if status == 206:
                    self.send_header("Content-Range", f"bytes {start}-{stop - 1}/{server.size}")
                self.send_header("Content-Length", str(stop - start))
                if server.etag:  # None: a server that names no version
                    self.send_header("ETag", server.etag)
                self.end_headers()
                for a in range(start, cut, 1 << 16):
                    self.wfile.write(server.content(a, min(cut, a + (1 << 16))))
                    if b.delay_s:
                        time.sleep(b.delay_s)
                if cut < stop:
                    self.wfile.flush()
                    self.connection.shutdown(2)  # mid-answer: the client sees a short read

        self.httpd = _QuietServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/DEEP/base.1B.fbin"
        self.thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def _bytes_server(data: bytes) -> Iterator[Server]:
    server = Server(lambda a, b: data[a:b], len(data))
    try:
        yield server
    finally:
        server.close()


@pytest.fixture
def served() -> Iterator[tuple[Server, bytes]]:
    """20,000 rows (7.7 MB) in 30 parts of 256 KiB, retried without a pause."""
    data = deep_rows(20_000)
    yield from ((s, data) for s in _bytes_server(data))


@pytest.fixture(autouse=True)
def small_parts(monkeypatch):
    monkeypatch.setattr("vprscale.core.ranged.PART_BYTES", 1 << 18)
    monkeypatch.setattr("vprscale.core.ranged.BACKOFF_S", 0.0)


def _crc(data: bytes) -> str:
    return google_crc32c.Checksum(data).hexdigest().decode()


def test_the_first_rows_arrive_with_their_header_and_a_manifest_though_connections_drop(served, tmp_path, capsys):
    server, data = served
    server.behaviour.drops = 3
    assert main(["fetch", "deep1b", "--rows", "5K", "--url", server.url, "--out", str(tmp_path), "-q"]) == 0
    got = (tmp_path / "base.5K.fbin").read_bytes()
    said = capsys.readouterr().out  # the field's units: rows and GB a second, per connection
    assert f"fetched 5,000 rows ({len(got) / 1e9:.2f} GB) in " in said
    assert "rows/s per connection on 4 connections" in said
    assert got == struct.pack("<II", 5_000, DIM) + data[8 : 8 + 4 * DIM * 5_000]  # big-ann-benchmarks' crop
    manifest = json.loads((tmp_path / "base.5K.fbin.manifest.json").read_text())
    assert manifest["bytes"] == len(got) and manifest["crc32c"] == _crc(got) and manifest["rows"] == 5_000
    assert manifest["source"] == server.url
    assert server.behaviour.drops == 0 and not list(tmp_path.glob(".*.partial")) and not list(tmp_path.glob(".*.json"))
    src = open_deep1b(tmp_path / "base.5K.fbin")
    assert (src.n_rows, src.dim) == (5_000, DIM)
    assert all(r.startswith("bytes=") for r in server.behaviour.requests)  # nothing but ranges asked for
    asked = sum(int(r[6:].split("-")[1]) - int(r[6:].split("-")[0]) + 1 for r in server.behaviour.requests)
    assert asked < 2 * len(got)  # the needed bytes (and the retried halves), not the 7.7 MB file


def test_fvecs_holds_the_same_rows(served, tmp_path):
    server, data = served
    assert main(["fetch", "deep1b", "--rows", "3000", "--format", "fvecs", "--url", server.url, "--out",
                 str(tmp_path), "-q"]) == 0
    fvecs = open_deep1b(tmp_path / "base.3K.fvecs")
    want = np.frombuffer(data[8 : 8 + 4 * DIM * 3_000], "<f4").reshape(3_000, DIM)
    np.testing.assert_array_equal(fvecs.read(0, 3_000), want)
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.endswith(".lock")) == [
        "base.3K.fvecs", "base.3K.fvecs.manifest.json"]


def test_a_connection_that_keeps_dropping_stops_resumably_and_the_rerun_keeps_what_arrived(served, tmp_path, capsys):
    server, data = served
    argv = ["fetch", "deep1b", "--rows", "20K", "--url", server.url, "--out", str(tmp_path), "--connections", "2"]
    server.behaviour.short = 10**6  # every answer promises the range and sends half of it
    fails(capsys, argv, "run the same command again to resume")
    assert not (tmp_path / "base.20K.fbin").exists() and (tmp_path / ".base.20K.fbin.partial").is_file()
    server.behaviour = Behaviour(short=0)
    (tmp_path / ".base.20K.fbin.parts.json").write_text(json.dumps(
        {"url": server.url, "size": len(data), "version": server.etag, "part_bytes": 1 << 18,
         "parts": {"0": _crc(data[: 1 << 18])}}))
    with open(tmp_path / ".base.20K.fbin.partial", "r+b") as fh:
        fh.write(data[: 1 << 18])  # a part a killed run finished, and one whose bytes were since damaged:
    record = json.loads((tmp_path / ".base.20K.fbin.parts.json").read_text())
    record["parts"][str(1 << 18)] = "00000000"
    (tmp_path / ".base.20K.fbin.parts.json").write_text(json.dumps(record))
    assert main([*argv, "-v"]) == 0
    assert "1 of 30 parts kept" in capsys.readouterr().err  # the first kept, the damaged one fetched again
    assert not any(r.startswith("bytes=0-") and r != "bytes=0-0" and r != "bytes=0-7" for r in
                   server.behaviour.requests)
    assert (tmp_path / "base.20K.fbin").read_bytes() == data


def test_a_resumed_fetch_starts_over_when_the_remote_file_changed(served, tmp_path, capsys):
    """Parts kept from one version of the remote file are never mixed with another's (ETag)."""
    server, data = served
    server.etag = '"v1"'
    argv = ["fetch", "deep1b", "--rows", "20K", "--url", server.url, "--out", str(tmp_path), "--connections", "1"]
    server.behaviour.cut_from = len(data) // 2  # the first half arrives whole, then the link fails
    fails(capsys, argv, "run the same command again to resume")
    assert len(json.loads((tmp_path / ".base.20K.fbin.parts.json").read_text())["parts"]) >= 10
    new = struct.pack("<II", 20_000, DIM) + bytes(len(data) - 8)  # the mirror now serves another file
    server.content, server.etag, server.behaviour = (lambda a, b: new[a:b]), '"v2"', Behaviour()
    assert main([*argv, "-v"]) == 0
    assert "parts kept" not in capsys.readouterr().err
    assert (tmp_path / "base.20K.fbin").read_bytes() == new


@pytest.mark.parametrize(("misbehave", "words"), [
    ("ignore ranges", ("ignores byte ranges",)),
    ("header lies", ("but its header says 30,000 rows", "truncated or foreign")),
    ("too many rows", ("--rows 30,000", "holds 20,000 rows")),
    ("missing", ("not found (HTTP 404)",)),
    ("refused", ("cannot connect",)),
    ("scheme", ("http:// or https://",)),
    ("port", ("127.0.0.1:99999", "not a URL that can be fetched", "out of range")),
])
def test_a_bad_source_is_one_line_and_leaves_nothing(misbehave, words, served, tmp_path, capsys):
    server, data = served
    url, rows = server.url, "10K"
    if misbehave == "ignore ranges":
        server.behaviour.ignore_ranges = True
    elif misbehave == "header lies":
        server.content = lambda a, b: (struct.pack("<II", 30_000, DIM) + data[8:])[a:b]
    elif misbehave == "too many rows":
        rows = "30K"
    elif misbehave == "missing":
        url = url.rsplit("/", 1)[0] + "/missing"
    elif misbehave == "refused":
        server.close()
    elif misbehave == "scheme":
        url = "ftp://127.0.0.1/base.1B.fbin"
    elif misbehave == "port":
        url = "http://127.0.0.1:99999/base.1B.fbin"
    fails(capsys, ["fetch", "deep1b", "--rows", rows, "--url", url, "--out", str(tmp_path / "o")], *words)
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_credentials_in_a_url_reach_no_output(served, tmp_path, capsys):
    server, _ = served
    secret = server.url.replace("http://", "http://user:hunter2@") + "?X-Amz-Signature=s3cr3t"
    assert main(["fetch", "deep1b", "--rows", "1K", "--url", secret, "--out", str(tmp_path), "-v",
                 "--summary", str(tmp_path / "s.json")]) == 0
    out = capsys.readouterr()
    for text in (out.out, out.err, *(p.read_text() for p in tmp_path.glob("*.json"))):
        assert "hunter2" not in text and "s3cr3t" not in text


def test_a_file_already_fetched_is_kept_unless_forced_and_then_kept_beside(served, tmp_path, capsys):
    server, _ = served
    argv = ["fetch", "deep1b", "--rows", "1K", "--url", server.url, "--out", str(tmp_path), "-q"]
    (tmp_path / "base.1K.fbin").write_bytes(b"mine")
    fails(capsys, argv, "already holds base.1K.fbin", "--force")
    assert (tmp_path / "base.1K.fbin").read_bytes() == b"mine"
    assert main([*argv, "--force"]) == 0
    assert (tmp_path / "base.1K.fbin.previous").read_bytes() == b"mine"
    assert open_deep1b(tmp_path / "base.1K.fbin").n_rows == 1_000


def test_fas100k_needs_its_link_and_is_checked_as_an_npz(served, tmp_path, capsys, monkeypatch):
    server, _ = served
    monkeypatch.delenv("VPRSCALE_FAS100K_URL", raising=False)
    fails(capsys, ["fetch", "fas100k", "--out", str(tmp_path)], "no default URL", "data.mendeley.com")
    fails(capsys, ["fetch", "fas100k", "--url", server.url, "--out", str(tmp_path)], "not an FAS100K .npz")
    assert not any(p.suffix == ".npz" for p in tmp_path.iterdir())


@pytest.mark.slow
def test_a_killed_fetch_resumes_to_the_same_bytes(tmp_path):
    """kill -9 in the middle of a 231 MB fetch (4 parts of 64 MiB): the rerun keeps the parts
    that had arrived whole and ends with every byte right."""
    rows = 600_000
    header = struct.pack("<II", rows, DIM)
    size = 8 + 4 * DIM * rows

    def content(a: int, b: int) -> bytes:
        head = header[a:b] if a < 8 else b""
        lo, hi = max(a, 8), b
        if hi <= lo:
            return head
        first, last = (lo - 8) // 4, (hi - 8 + 3) // 4
        values = (np.arange(first, last, dtype=np.float64) % 1009 / 7).astype("<f4").tobytes()
        return head + values[(lo - 8) - 4 * first : (hi - 8) - 4 * first]

    server = Server(content, size)
    try:
        server.behaviour.delay_s = 0.002
        argv = [sys.executable, "-m", "vprscale.cli", "fetch", "deep1b", "--url", server.url, "--out", str(tmp_path),
                "--connections", "2", "-q"]
        proc = subprocess.Popen(argv, start_new_session=True)
        record = tmp_path / ".base.600K.fbin.parts.json"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not (record.is_file() and json.loads(record.read_text())["parts"]):
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        kept = json.loads(record.read_text())["parts"]
        assert 1 <= len(kept) < 4 and not (tmp_path / "base.600K.fbin").exists()
        server.behaviour = Behaviour()
        assert subprocess.run(argv, timeout=300).returncode == 0
        fetched = {r for r in server.behaviour.requests if r not in ("bytes=0-0", "bytes=0-7")}
        assert len(fetched) == 4 - len(kept)  # only the parts that had not arrived
        with open(tmp_path / "base.600K.fbin", "rb") as fh:
            for a in range(0, size, 1 << 24):
                assert fh.read(1 << 24) == content(a, min(size, a + (1 << 24)))
        manifest = json.loads((tmp_path / "base.600K.fbin.manifest.json").read_text())
        assert manifest["bytes"] == size and manifest["rows"] == rows
    finally:
        server.close()


def test_a_build_reads_deep1b_where_it_lives_to_the_same_store(sources, tiny_store, tmp_path, capsys):
    """``build --deep1b https://…/base.fbin``: the rows the recipe reads come by byte ranges, no
    local copy made, and the store holds the same arrays as one built from the local file."""
    import zarr

    from .conftest import write_recipe

    data = sources["fbin"].read_bytes()
    server = Server(lambda a, b: data[a:b], len(data))
    try:
        server.behaviour.drops = 2
        assert main(["build", "--scale", str(write_recipe(tmp_path / "tiny.toml")), "--deep1b", server.url,
                     "--fas", str(sources["fas"]), "--out", str(tmp_path / "data"), "-q"]) == 0
        asked = [r for r in server.behaviour.requests if r.startswith("bytes=")]
        assert len(asked) == len(server.behaviour.requests) > 2
    finally:
        server.close()
    remote, local = (zarr.open_group(p, mode="r") for p in (tmp_path / "data" / "tiny.zarr", tiny_store))
    for name in ("ref", "query_qm1", "query_qm2", "gt", "ref_part", "query_part"):
        np.testing.assert_array_equal(remote[name][:], local[name][:])
    sources_seen = json.loads((tmp_path / "data" / "tiny.zarr" / "zarr.json").read_text())
    assert server.url in json.dumps(sources_seen)  # the URL is the source of record
    assert not list((tmp_path / "data").glob("*.fbin"))  # read where it lives: nothing copied


def test_a_urls_password_and_signature_reach_no_output_record_or_summary(sources, tmp_path, capsys):
    """``build --deep1b URL`` with a user, a password and a presigned query: the store's metadata,
    its build.json (the command in the provenance), the manifest, the ``--summary`` and what is
    printed hold neither secret, and the URL is still recorded as the source, without them."""
    from .conftest import write_recipe

    data = sources["fbin"].read_bytes()
    server = Server(lambda a, b: data[a:b], len(data))
    try:
        secret = server.url.replace("http://", "http://user:hunter2@") + "?X-Amz-Signature=s3cr3t"
        assert main(["build", "--scale", str(write_recipe(tmp_path / "tiny.toml")), f"--deep1b={secret}",
                     "--fas", str(sources["fas"]), "--out", str(tmp_path / "data"), "-v",
                     "--summary", str(tmp_path / "summary.json")]) == 0
    finally:
        server.close()
    printed = capsys.readouterr()
    written = [p.read_text() for p in (tmp_path / "data").rglob("*.json")] + [(tmp_path / "summary.json").read_text()]
    for text in (printed.out, printed.err, *written):
        assert "hunter2" not in text and "s3cr3t" not in text and "user:" not in text
    build = json.loads((tmp_path / "data" / "tiny.zarr" / "build.json").read_text())
    assert f"--deep1b={server.url}" in build["provenance"]["command"]


def test_credentials_never_follow_a_redirect_to_another_origin(served, tmp_path):
    """A mirror that redirects to another origin (a CDN, anyone): the fetch follows it, the
    user's Basic credentials go to the mirror only."""
    server, data = served
    mirror = Server(lambda a, b: b"", 0)
    try:
        mirror.behaviour.redirect = server.url
        secret = mirror.url.replace("http://", "http://user:hunter2@")
        assert main(["fetch", "deep1b", "--rows", "1K", "--url", secret, "--out", str(tmp_path), "-q"]) == 0
        assert mirror.behaviour.authorizations and all(a and a.startswith("Basic ")
                                                       for a in mirror.behaviour.authorizations)
        assert server.behaviour.authorizations and not any(server.behaviour.authorizations)
        assert (tmp_path / "base.1K.fbin").read_bytes()[8:] == data[8 : 8 + 1000 * DIM * 4]
    finally:
        mirror.close()


@pytest.mark.parametrize("command", ["fetch", "build"])
def test_a_file_that_changes_while_it_is_read_is_never_stitched(command, sources, tmp_path, capsys):
    """The remote file is replaced (another ETag) after a few requests: the fetch, and a build
    reading it by URL, stop in one line with nothing published; run again, they read the new
    file whole."""
    from .conftest import write_recipe

    data = sources["fbin"].read_bytes() if command == "build" else deep_rows(20_000)
    server = Server(lambda a, b: data[a:b], len(data))
    server.etag = '"v1"'
    server.behaviour.change_after = 4
    if command == "fetch":
        argv = ["fetch", "deep1b", "--rows", "20K", "--url", server.url, "--out", str(tmp_path / "o"),
                "--connections", "1"]
        made = tmp_path / "o" / "base.20K.fbin"
    else:
        argv = ["build", "--scale", str(write_recipe(tmp_path / "tiny.toml")), "--deep1b", server.url, "--fas",
                str(sources["fas"]), "--out", str(tmp_path / "o"), "--workers", "1"]
        made = tmp_path / "o" / "tiny.zarr"
    try:
        fails(capsys, argv, "changed while it was read", "run the command again")
        assert not made.exists()
        if command == "fetch":
            assert main([*argv, "-q"]) == 2  # header and rows of the new file: the header now says 0 rows
            assert not made.exists()
    finally:
        server.close()


def test_a_download_that_trickles_is_cut_off_and_resumable(served, tmp_path, capsys, monkeypatch):
    """A server that sends slower than the minimum rate holds no job forever: its answers are cut
    off and retried, and the run stops in one line, resumable."""
    server, _ = served
    monkeypatch.setattr("vprscale.core.ranged.MIN_RATE", 1 << 30)
    monkeypatch.setattr("vprscale.core.ranged.TIMEOUT_S", 1.0)
    monkeypatch.setattr("vprscale.core.ranged.PART_BYTES", 1 << 20)  # 16 blocks of 64 KiB, one each 0.2 s:
    monkeypatch.setattr("vprscale.core.ranged.RETRIES", 1)  # about 6 an answer, so 2 answers are not enough
    server.behaviour.delay_s = 0.2
    fails(capsys, ["fetch", "deep1b", "--rows", "20K", "--url", server.url, "--out", str(tmp_path),
                   "--connections", "1"],
          "slower than", "run the same command again to resume")
    assert not (tmp_path / "base.20K.fbin").exists()


def test_a_server_that_names_no_version_is_refused(sources, tmp_path, capsys):
    """A server that names no version (no ETag, no Last-Modified) could change its file between two
    range requests, same size, and nothing could tell: the fetch and a build by URL refuse it in
    one line, before any row is read."""
    from .conftest import write_recipe

    data = sources["fbin"].read_bytes()
    server = Server(lambda a, b: data[a:b], len(data))
    server.etag = None
    try:
        fails(capsys, ["fetch", "deep1b", "--rows", "1K", "--url", server.url, "--out", str(tmp_path / "f")],
              "names no version")
        fails(capsys, ["build", "--scale", str(write_recipe(tmp_path / "tiny.toml")), "--deep1b", server.url,
                       "--fas", str(sources["fas"]), "--out", str(tmp_path / "o")], "names no version")
        assert not (tmp_path / "f" / "base.1K.fbin").exists() and not (tmp_path / "o" / "tiny.zarr").exists()
    finally:
        server.close()


def test_a_planted_partial_link_is_refused_and_its_target_untouched(served, tmp_path, capsys):
    """Someone plants ``.base.1K.fbin.partial`` as a link to a file of theirs: the fetch refuses in one
    line, writes nothing through it and publishes nothing."""
    server, _ = served
    target = tmp_path / "precious"
    target.write_bytes(b"mine")
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / ".base.1K.fbin.partial").symlink_to(target)
    fails(capsys, ["fetch", "deep1b", "--rows", "1K", "--url", server.url, "--out", str(tmp_path / "o")],
          "symbolic link")
    assert target.read_bytes() == b"mine" and not (tmp_path / "o" / "base.1K.fbin").exists()


def test_a_fetch_that_filled_the_disk_resumes_with_what_it_holds(small_filesystem, capsys, monkeypatch):
    """The free-space check counts what the partial download already holds: a run stopped half
    way on a nearly full disk resumes, where asking for the whole file again would be refused."""
    data = deep_rows(500)  # 192 KB on a 300 KB filesystem, in parts of 32 KiB
    monkeypatch.setattr("vprscale.core.ranged.PART_BYTES", 1 << 15)
    server = Server(lambda a, b: data[a:b], len(data))
    out = small_filesystem / "o"
    argv = ["fetch", "deep1b", "--rows", "500", "--url", server.url, "--out", str(out), "--connections", "1"]
    try:
        # nothing past the middle arrives, however many times it is asked for (a retry of a part cut
        # in half asks for its rest, and would fill the file on a machine slow enough to retry often)
        server.behaviour.empty_from = len(data) // 2
        fails(capsys, argv, "run the same command again to resume")
        held = (out / ".base.500.fbin.partial").stat().st_blocks * 512
        assert 0 < held < len(data)
        free = os.statvfs(small_filesystem).f_bavail * os.statvfs(small_filesystem).f_frsize
        (small_filesystem / "filler").write_bytes(bytes(free - (len(data) - held) - 8192))
        server.behaviour.empty_from = None
        assert main([*argv, "-q"]) == 0
        assert (out / "base.500.fbin").read_bytes() == data
    finally:
        server.close()


@pytest.mark.parametrize("damage", ["truncated", "overwritten"])
def test_a_fetched_file_changed_since_is_refused_where_it_is_read(sources, tmp_path, capsys, damage):
    """A file ``fetch`` wrote is read against the manifest beside it: cut short or overwritten in
    place afterwards, a build refuses it in one line naming it, and writes nothing."""
    from .conftest import write_recipe

    data = sources["fbin"].read_bytes()
    server = Server(lambda a, b: data[a:b], len(data))
    try:
        assert main(["fetch", "deep1b", "--rows", "60K", "--url", server.url, "--out", str(tmp_path), "-q"]) == 0
    finally:
        server.close()
    (fetched,) = (p for p in tmp_path.glob("*.fbin"))
    build = ["build", "--scale", str(write_recipe(tmp_path / "tiny.toml")), "--deep1b", str(fetched),
             "--fas", str(sources["fas"]), "--out", str(tmp_path / "data"), "-q"]
    body = bytearray(fetched.read_bytes())
    if damage == "truncated":  # a whole row less, the header rewritten: a valid fbin, not the one fetched
        body[0:4] = np.array([59_999], "<u4").tobytes()
        body = body[: -4 * 96]
    else:  # the same size, one value changed
        body[-1] ^= 0x01
    fetched.write_bytes(bytes(body))
    capsys.readouterr()
    assert main(build) == 2
    err = capsys.readouterr().err.strip()
    assert str(fetched) in err and "fetch it again" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "data" / "tiny.zarr").exists()
