"""Shared fixtures: small sources written in the real layouts, and a small recipe."""

from __future__ import annotations

import json
import os

# The xdist workers share two cores, and each runs OpenMP regions (FAISS, its BLAS): an OpenMP
# thread left idle spins before it sleeps, on a core another worker needs. Set before FAISS loads
# OpenMP; the commands the tests start inherit it. (Scheduling only: no result depends on it.)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
import shutil
import subprocess
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import faiss
import numpy as np
import pytest
from filelock import FileLock
from hypothesis import settings
from threadpoolctl import threadpool_limits

from vprscale.compared.faisscodes import ENCODE_ROWS
from vprscale.dataset.sources.synthetic import FasParams, SyntheticDeep1B, SyntheticFAS
from vprscale.dataset.sources.writers import write_fas_npz, write_fbin, write_fvecs
from vprscale.method.hashkernels import hash_rows
from vprscale.method.kmeans1d import kmeans_1d

# Hypothesis's per-example deadline is a wall-clock assertion: the first example of a test
# compiles its numba kernels (0.5 s on a fresh checkout), and a loaded machine is slower.
settings.register_profile("vprscale", deadline=None)
settings.load_profile("vprscale")

# With -n, xdist hands out whole modules (--dist loadscope) in collection order
# (--no-loadscope-reorder, pyproject's addopts): the costliest first, so that a long module does not
# start when the other workers have nothing left to run (xdist's own order counts tests alone, and
# handed out a module of two two-minute fault-injection tests last). A module costs the seconds
# its tests took in the run that wrote DURATIONS (``--store-durations``); a test that run did not
# see counts as the median test of its kind (slow or not; without a file, a slow one as SLOW_WEIGHT).
DURATIONS = Path(__file__).with_name("durations.json")
SLOW_WEIGHT = 30


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--store-durations", action="store_true",
                     help=f"write each test's seconds (setup, call, teardown) to {DURATIONS.name}, for the order")


def _stored_durations() -> dict[str, float]:
    return json.loads(DURATIONS.read_text()) if DURATIONS.is_file() else {}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    took = _stored_durations()
    slow = {item.nodeid: item.get_closest_marker("slow") is not None for item in items}
    known = {kind: [took[k] for k, s in slow.items() if s == kind and k in took] for kind in (False, True)}
    typical = {False: float(np.median(known[False])) if known[False] else 1.0}
    typical[True] = float(np.median(known[True])) if known[True] else typical[False] * SLOW_WEIGHT
    cost: Counter[Path] = Counter()
    for item in items:
        cost[item.path] += took.get(item.nodeid, typical[slow[item.nodeid]])
    items.sort(key=lambda item: -cost[item.path])  # stable: a module's own order kept


_durations: Counter[str] = Counter()


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    _durations[report.nodeid] += report.duration  # with -n, the controller hears every worker's reports


def pytest_sessionfinish(session: pytest.Session) -> None:
    """With ``--store-durations``, this run's seconds over the stored ones (a quick run keeps the slow
    tests' seconds), without the tests of modules that are gone."""
    if not session.config.getoption("store_durations") or hasattr(session.config, "workerinput"):
        return
    took = {**_stored_durations(), **{k: round(v, 1) for k, v in _durations.items()}}
    root = DURATIONS.parent.parent
    DURATIONS.write_text(json.dumps({k: v for k, v in sorted(took.items()) if (root / k.split("::")[0]).is_file()},
                                    indent=0) + "\n")


EXACT_METHOD = (  # a method of the small contract: exact squared L2 by brute force (tests' own, small data)
    "import numpy as np\n"
    "class Exact:\n"
    "    def fit(self, ref):\n"
    "        self.ref = np.asarray(ref.compute(), np.float64)\n"
    "    def query(self, frames, k):\n"
    "        d = ((np.asarray(frames, np.float64)[:, None, :] - self.ref[None]) ** 2).sum(-1)\n"
    "        ids = np.argsort(d, axis=1, kind='stable')[:, :k]\n"
    "        return ids, np.take_along_axis(d, ids, 1)\n"
    "    def pair_distances(self, frames, ref_ids):\n"
    "        return ((np.asarray(frames, np.float64) - self.ref[ref_ids]) ** 2).sum(1)\n")


def exact_method_in(folder: Path, module: str, monkeypatch: pytest.MonkeyPatch) -> str:
    """:data:`EXACT_METHOD` written as ``folder/<module>.py`` and importable: its ``--method`` name."""
    (folder / f"{module}.py").write_text(EXACT_METHOD)
    monkeypatch.syspath_prepend(str(folder))
    return f"{module}:Exact"


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")  # report pages' tests need it


def chromium(*args: str) -> subprocess.CompletedProcess:
    """Headless Chromium on a page, its console on stderr, every host unresolvable (no network)."""
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-logging=stderr", "--v=0",
             "--virtual-time-budget=10000", "--host-resolver-rules=MAP * ~NOTFOUND"]
    return subprocess.run([CHROMIUM, *flags, *args], capture_output=True, text=True, timeout=120, check=True)


def quantize(y: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Codes ``argmin_k |y_j − c_jk|`` (ties: the smaller k) and errors ``Σ_j min_k |y_j − c_jk|`` of
    already projected rows, through the method's own kernel with the identity projection."""
    d = y.shape[1]
    codes, _, err, _ = hash_rows(np.asarray(y, np.float64), np.zeros(d), np.eye(d), centres, centres.shape[1],
                                   np.empty(0, np.float32))
    return codes, err


def kmeans_1d_exact(column: np.ndarray, k: int) -> np.ndarray:
    """Exact 1-D k-means centres of an in-memory column (its distinct values weighted by count)."""
    values, counts = np.unique(np.asarray(column, np.float64), return_counts=True)
    return kmeans_1d(values, counts, k)


def faiss_own(factory: str, train: np.ndarray, ref: np.ndarray, anneal: int | None = None) -> faiss.Index:
    """``factory`` built with FAISS directly on one thread: trained on ``train`` (OPQ and ITQ
    training change with the BLAS thread count), then ``add`` of the references in blocks of
    ``ENCODE_ROWS`` (an HNSW graph's links and LSQ's codes depend on the rows added together).

    ``anneal``: the iterations of an 8-bit product quantiser's polysemous renumbering (FAISS's
    500,000 take 7 s whatever the sample; any number renumbers the codebook).
    """
    omp = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)
    try:
        index = faiss.index_factory(ref.shape[1], factory)
        if anneal is not None:
            schedule = faiss.PolysemousTraining()
            schedule.n_iter = anneal
            quantiser = faiss.downcast_index(faiss.extract_index_ivf(index) if "IVF" in factory else index)
            quantiser.polysemous_training = schedule  # an IVF-PQ holds a pointer: kept alive with the index
            index.referenced_objects = [schedule]
        with threadpool_limits(limits=1, user_api="blas"):
            index.train(train)
        for lo in range(0, len(ref), ENCODE_ROWS):
            index.add(ref[lo : lo + ENCODE_ROWS])
    finally:
        faiss.omp_set_num_threads(omp)
    if "IVF" in factory:
        faiss.extract_index_ivf(index).nprobe = 16
    if "HNSW" in factory:
        inner = faiss.downcast_index(index)
        faiss.downcast_index(getattr(inner, "index", inner)).hnsw.efSearch = 64  # past a transform, if any
    return index


@pytest.fixture(autouse=True)
def own_cache(tmp_path, monkeypatch):
    """Each test its own ``$VPRSCALE_CACHE``: a FAS fit (or a fetched copy) cached by one test must
    not stand in for the computation another test checks (same bytes for any workers, a bad file).
    Session fixtures, built before, use the default cache."""
    monkeypatch.setenv("VPRSCALE_CACHE", str(tmp_path / "vprscale-cache"))


SMALL_FAS = FasParams(dim=128, n_ref=3000, n_query=2000, segment_frames=(150, 500))
DEEP_ROWS = 70_000


# FAISS methods in tests that are about answers, not training, train on this many evenly spaced
# references of the tiny store's 52,500 (the sampling rule's path, as at scale; a 256-centroid
# product quantiser wants 9,984 rows): OPQ's training on all of them was most of those tests' time
SMALL_TRAINING = 12_288


@pytest.fixture
def small_training(monkeypatch):
    monkeypatch.setattr("vprscale.compared.faisscodes.TRAIN_ROWS", SMALL_TRAINING)


def made_once(tmp_path_factory: pytest.TempPathFactory, name: str, make: Callable[[Path], None]) -> Path:
    """The folder ``name`` of this run, filled by ``make`` once for every xdist worker: the first to
    ask makes it while the others wait. For session fixtures, whose contents are the same whoever
    makes them (same seeds, same code), and which no test changes."""
    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base  # the run's, not a worker's
    folder, made = root / name, root / f"{name}.made"
    with FileLock(root / f"{name}.lock"):
        if not made.exists():
            shutil.rmtree(folder, ignore_errors=True)  # what a worker that died making it left
            folder.mkdir()
            make(folder)
            made.touch()
    return folder


@pytest.fixture(scope="session")
def sources(tmp_path_factory) -> dict[str, Path]:
    """Synthetic Deep1B as fvecs chunks and fbin, and a small FAS npz (seed 3)."""
    def make(root: Path) -> None:
        deep = SyntheticDeep1B(DEEP_ROWS, seed=3)
        write_fvecs(deep, root / "base", rows_per_file=30_000)
        write_fbin(deep, root / "base.fbin")
        write_fas_npz(SyntheticFAS(3, SMALL_FAS).traverse(), root / "fas.npz")

    root = made_once(tmp_path_factory, "sources", make)
    return {"fvecs": root / "base", "fbin": root / "base.fbin", "fas": root / "fas.npz", "root": root}


def write_recipe(path: Path, **overrides) -> Path:
    """A small recipe TOML (scale ``tiny``) with fields overridden as given."""
    fields = {"scale": "tiny", "deep1b_rows_read": 60_000, "deep1b_rows_kept": 50_000,
              "fas_ref_rows": 2500, "fas_query_rows": "all", "query_stride": 10, "window": 40,
              "dim": 96, "seed": 5, "chunk_rows": 16384}
    fields.update(overrides)
    lines = [f"{k} = {v!r}".replace("'", '"') for k, v in fields.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def recipe(tmp_path) -> Path:
    return write_recipe(tmp_path / "tiny.toml")


@pytest.fixture(scope="session")
def tiny_store(tmp_path_factory, sources) -> Path:
    """The tiny recipe built once from the fbin and npz sources."""
    from vprscale.dataset.build import BuildRequest, build

    def make(root: Path) -> None:
        recipe = write_recipe(root / "tiny.toml")
        build(BuildRequest(scale=str(recipe), out=root / "out", deep1b=str(sources["fbin"]), fas=str(sources["fas"]),
                           workers=2, quiet=True))

    return made_once(tmp_path_factory, "built", make) / "out" / "tiny.zarr"


@pytest.fixture(scope="session")
def fas_fit_20k(tmp_path_factory) -> Path:
    """The ``fas-fit`` folder of a cache that holds the FAS fit of the shipped 20K recipe on the
    synthetic traverse, made once by a real 20K build (a cold fit is most of a 20K build's time)."""
    from vprscale.dataset.build import BuildRequest, build

    def make(root: Path) -> None:
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv("VPRSCALE_CACHE", str(root / "cache"))
            build(BuildRequest(scale="20K", out=root / "build", workers=2, quiet=True))

    return made_once(tmp_path_factory, "fitted", make) / "cache" / "fas-fit"


def seed_fas_fit(cache: Path, fitted: Path) -> None:
    """``cache`` (a ``$VPRSCALE_CACHE``) given the fit in ``fitted``, linked: the cache replaces an
    entry whole (written beside, then renamed), never writes one in place."""
    shutil.copytree(fitted, cache / "fas-fit", copy_function=os.link)


@pytest.fixture
def fas_fitted(own_cache, fas_fit_20k) -> None:
    """This test's own cache seeded with that fit, for tests whose 20K builds (in this process or
    a child) are about something else: the same store bytes, without fitting FAS again. Tests of
    the fit itself keep an empty cache."""
    seed_fas_fit(Path(os.environ["VPRSCALE_CACHE"]), fas_fit_20k)


@pytest.fixture(scope="session")
def tiny_index(tiny_store, tmp_path_factory) -> Path:
    """A d = 12 CoarseHash index of the tiny store."""
    from vprscale.jobs.indexing import build_index

    def make(root: Path) -> None:
        build_index(tiny_store, d=12, out=root / "tiny.index", quiet=True)

    return made_once(tmp_path_factory, "index", make) / "tiny.index"


@pytest.fixture
def small_filesystem(tmp_path):
    """A 300 KB tmpfs (skipped where this test may not mount one)."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=300k", "tmpfs", str(mnt)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a small filesystem here ({done.stderr.decode().strip()[:80]})")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


@pytest.fixture
def read_only_folder(small_filesystem):
    """A folder on a filesystem remounted read-only (what root cannot write either)."""
    done = subprocess.run(["mount", "-o", "remount,ro", str(small_filesystem)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot remount read-only here ({done.stderr.decode().strip()[:80]})")
    return small_filesystem
