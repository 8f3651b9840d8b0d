"""Progress bars and stage timings for long jobs."""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from contextlib import contextmanager
from typing import Any

import dask
from tqdm import tqdm
from tqdm.dask import TqdmCallback


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
        with TqdmCallback(desc=desc, unit="task", file=sys.stderr, leave=False, disable=None):
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


class ChunkProgress:
    """Progress of a long pass on stderr: tqdm's bar on a terminal, a line every ~5 % in a log.

    Scheduled runs write logs, where a bar's carriage returns are noise; a line with the
    chunks done and the time left tells the same.
    """

    def __init__(self, desc: str, total: int, done: int = 0) -> None:
        self.desc, self.total, self.done = desc, total, done
        self.t0, self.start = time.perf_counter(), done
        self.bar = (tqdm(total=total, initial=done, desc=desc, unit="chunk", file=sys.stderr, leave=False)
                    if sys.stderr.isatty() else None)
        self._next = done + max(1, total // 20)

    def update(self, n: int) -> None:
        self.done += n
        if self.bar is not None:
            self.bar.update(n)
            if self.done >= self.total:
                self.bar.close()
            return
        if self.done >= self._next or self.done == self.total:
            rate = (self.done - self.start) / max(1e-9, time.perf_counter() - self.t0)
            left = (self.total - self.done) / rate if rate > 0 else float("nan")
            print(f"  {self.desc}: {self.done:,}/{self.total:,} chunks, {left:,.0f} s left", file=sys.stderr,
                  flush=True)
            self._next = self.done + max(1, self.total // 20)
