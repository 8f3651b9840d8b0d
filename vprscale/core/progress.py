"""Progress bars and stage timings for long jobs, through the ``vprscale`` logger: silent in a
library unless the application enables INFO for it; the command line does (``--quiet`` turns it
off). A bar is drawn only on a terminal; a log gets lines."""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Sequence
from contextlib import contextmanager
from typing import Any

import dask
from dask.callbacks import Callback
from tqdm import tqdm
from tqdm.dask import TqdmCallback

log = logging.getLogger("vprscale")


def _bars() -> bool:
    """Whether progress is wanted and stderr is a terminal (a bar); else lines, if wanted."""
    return log.isEnabledFor(logging.INFO) and sys.stderr.isatty()


def _client() -> Any:
    """The active distributed client, if any (none can exist unless ``distributed`` was imported)."""
    if "distributed" not in sys.modules:
        return None
    from distributed import get_client

    try:
        return get_client()
    except ValueError:
        return None


class _LoggedTasks(Callback):
    """A Dask callback that reports finished tasks as :class:`ChunkProgress` lines (for logs)."""

    def __init__(self, desc: str) -> None:
        super().__init__()
        self.desc = desc
        self.progress: ChunkProgress | None = None

    def _start_state(self, dsk: Any, state: dict) -> None:
        total = sum(len(state[k]) for k in ("ready", "waiting", "running", "finished") if k in state)
        self.progress = ChunkProgress(self.desc, total, unit="tasks")

    def _posttask(self, key: Any, result: Any, dsk: Any, state: dict, worker_id: Any) -> None:
        if self.progress is not None:
            self.progress.update(1)


def compute(*collections: Any, desc: str = "compute") -> tuple[Any, ...]:
    """``dask.compute`` with per-task progress, on a distributed client if one is active.

    A bar on an interactive terminal; in a log (a scheduled run), a line every ~5 % of the
    tasks with the time left, so that no long pass is silent.
    """
    client = _client()
    if client is None:
        if _bars():
            with TqdmCallback(desc=desc, unit="task", file=sys.stderr, leave=False):
                return dask.compute(*collections)
        with _LoggedTasks(desc):
            return dask.compute(*collections)
    from distributed.diagnostics.progressbar import TextProgressBar

    futures = client.compute(list(collections))
    if _bars():
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
              disable=not _bars()) as bar:
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
            log.info("… %s", name)
        yield
        self.stages[name] = self.stages.get(name, 0.0) + time.perf_counter() - t0
        if not self.quiet:
            log.info("✓ %s (%.1f s)", name, self.stages[name])


LINE_SECONDS = 2.0  # in a log, a progress line at most this often (and the last one always)


class ChunkProgress:
    """Progress of a long pass on stderr: tqdm's bar on a terminal, in a log a line every ~5 %
    (at most one per ``LINE_SECONDS``, and the last).

    Scheduled runs write logs, where a bar's carriage returns are noise; a line with the
    chunks done and the time left tells the same.
    """

    def __init__(self, desc: str, total: int, done: int = 0, unit: str = "chunks") -> None:
        self.desc, self.total, self.done, self.unit = desc, total, done, unit
        self.t0, self.start = time.perf_counter(), done
        self.bar = (tqdm(total=total, initial=done, desc=desc, unit=unit, file=sys.stderr, leave=False)
                    if _bars() else None)
        self._next = done + max(1, total // 20)
        self._last = self.t0

    def update(self, n: int) -> None:
        self.done += n
        if self.bar is not None:
            self.bar.update(n)
            if self.done >= self.total:
                self.bar.close()
            return
        now = time.perf_counter()
        if (self.done >= self._next and now - self._last >= LINE_SECONDS) or self.done == self.total:
            self._last = now
            rate = (self.done - self.start) / max(1e-9, time.perf_counter() - self.t0)
            left = (self.total - self.done) / rate if rate > 0 else float("nan")
            log.info("  %s: %s/%s %s, %s s left", self.desc, f"{self.done:,}", f"{self.total:,}", self.unit,
                     f"{left:,.0f}")
            self._next = self.done + max(1, self.total // 20)


class StepProgress:
    """Named steps of a job: a bar showing the current step on a terminal, a line per step in a log."""

    def __init__(self, desc: str, total: int, quiet: bool = False) -> None:
        self.desc, self.total, self.quiet, self.done = desc, total, quiet, 0
        self.t0 = time.perf_counter()
        self.bar = (tqdm(total=total, desc=desc, unit="step", file=sys.stderr, leave=False)
                    if _bars() and not quiet else None)

    def step(self, name: str) -> None:
        """Step ``name`` starts (the previous one, if any, is done)."""
        if self.bar is not None:
            self.bar.update(1 if self.done else 0)
            self.bar.set_postfix_str(name)
        elif not self.quiet:
            log.info("  %s [%d/%d, %s s] %s", self.desc, self.done + 1, self.total,
                     f"{time.perf_counter() - self.t0:,.0f}", name)
        self.done += 1

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
