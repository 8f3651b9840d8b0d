"""Progress bars and stage timings for long jobs."""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from contextlib import contextmanager
from typing import Any

import dask
from distributed import as_completed, get_client
from distributed.diagnostics.progressbar import TextProgressBar
from tqdm import tqdm


def compute(*collections: Any) -> tuple[Any, ...]:
    """``dask.compute`` with a per-task progress bar when a distributed client is active.

    The bar is drawn only on an interactive terminal, so logs of scheduled runs stay clean.
    """
    try:
        client = get_client()
    except ValueError:
        return dask.compute(*collections)
    futures = client.compute(list(collections))
    if sys.stderr.isatty():
        TextProgressBar(futures, complete=True, start=False)
    return tuple(client.gather(futures))


def run_tasks(tasks: Sequence[Any], desc: str) -> list[Any]:
    """Compute Dask delayed objects on the current client with a progress bar; results in order."""
    if not tasks:
        return []
    client = get_client()
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
