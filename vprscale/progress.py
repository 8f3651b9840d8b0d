"""Progress bars and stage timings for long jobs."""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from contextlib import contextmanager
from typing import Any

import dask
from dask.callbacks import Callback
from tqdm import tqdm


class _TaskBar(Callback):
    """A tqdm bar over the tasks of a computation on Dask's local (threaded) scheduler."""

    def __init__(self, desc: str) -> None:
        super().__init__()
        self.desc = desc

    def _start_state(self, dsk: Any, state: dict) -> None:
        total = sum(len(state[k]) for k in ("ready", "waiting", "running")) + len(state["finished"])
        self.bar = tqdm(total=total, desc=self.desc, unit="task", file=sys.stderr, leave=False, disable=None)

    def _posttask(self, key: Any, result: Any, dsk: Any, state: dict, worker_id: Any) -> None:
        self.bar.update()

    def _finish(self, dsk: Any, state: dict, errored: bool) -> None:
        self.bar.close()


def _client() -> Any:
    """The active distributed client, if any (none can exist unless ``distributed`` was imported)."""
    if "distributed" not in sys.modules:
        return None
    from distributed import get_client

    try:
        return get_client()
    except ValueError:
        return None


def compute(*collections: Any, desc: str = "compute") -> tuple[Any, ...]:
    """``dask.compute`` with a per-task progress bar, on a distributed client if one is active.

    Bars are drawn only on an interactive terminal, so logs of scheduled runs stay clean.
    """
    client = _client()
    if client is None:
        with _TaskBar(desc):
            return dask.compute(*collections)
    from distributed.diagnostics.progressbar import TextProgressBar

    futures = client.compute(list(collections))
    if sys.stderr.isatty():
        TextProgressBar(futures, complete=True, start=False)
    return tuple(client.gather(futures))


def run_tasks(tasks: Sequence[Any], desc: str) -> list[Any]:
    """Compute Dask delayed objects with a progress bar per task; results in order."""
    if not tasks:
        return []
    client = _client()
    if client is None:
        return list(compute(*tasks, desc=desc))
    from distributed import as_completed

    futures = client.compute(list(tasks))
    index = {f.key: i for i, f in enumerate(futures)}
    results: list[Any] = [None] * len(futures)
    with tqdm(total=len(futures), desc=desc, unit="task", file=sys.stderr, leave=False,
              disable=None) as bar:
        for fut in as_completed(futures):
            results[index[fut.key]] = fut.result()
            bar.update()
    return results


class Timings:
    """Wall time per named stage, printed as the stages end."""

    def __init__(self, quiet: bool = False) -> None:
        self.stages: dict[str, float] = {}
        self.quiet = quiet

    @contextmanager
    def stage(self, name: str):
        t0 = time.perf_counter()
        if not self.quiet:
            print(f"… {name}", file=sys.stderr, flush=True)
        yield
        self.stages[name] = self.stages.get(name, 0.0) + time.perf_counter() - t0
        if not self.quiet:
            print(f"✓ {name} ({self.stages[name]:.1f} s)", file=sys.stderr, flush=True)
