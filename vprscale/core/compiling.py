"""Saying so when numba compiles: a first run on a machine compiles vprscale's kernels (tens of
seconds to a few minutes, depending on the command) before any progress can be shown; numba
caches them (:mod:`vprscale.core.kernelcache`), so every later process loads them in
milliseconds. A listener on numba's compile event logs one line the first time a kernel of
vprscale's is compiled in a process, and nothing when they come from the cache; while compiling
goes on, a line every ``HEARTBEAT_S`` says so, so that a log is never silent for long.
"""

from __future__ import annotations

import logging
import threading
import time

from numba.core import event

log = logging.getLogger(__name__)
HEARTBEAT_S = 15.0


def _ours(ev: event.Event) -> bool:
    dispatcher = (ev.data or {}).get("dispatcher")
    module = getattr(getattr(dispatcher, "py_func", None), "__module__", "") or ""
    return module.startswith("vprscale.")


class _FirstCompile(event.Listener):
    def __init__(self) -> None:
        self.said = False
        self.active = 0  # compilations under way (they nest: a kernel compiles what it calls)
        self.done = 0
        self.t0 = 0.0
        self.lock = threading.Lock()

    def on_start(self, ev: event.Event) -> None:
        if not _ours(ev):
            return
        with self.lock:
            self.active += 1
            if self.said:
                return
            self.said, self.t0 = True, time.monotonic()
        log.info("compiling numba kernels (first run only: they are cached for every later run)")
        threading.Thread(target=self._heartbeat, name="vprscale-compiling", daemon=True).start()

    def on_end(self, ev: event.Event) -> None:
        if _ours(ev):
            with self.lock:
                self.active -= 1
                self.done += 1

    def _heartbeat(self) -> None:
        while True:
            time.sleep(HEARTBEAT_S)
            with self.lock:
                busy, done = self.active > 0, self.done
            if busy:
                log.info("  compiling numba kernels: %d compiled, %.0f s", done, time.monotonic() - self.t0)


_listener = _FirstCompile()
_registered: list[bool] = []


def announce_compiling() -> None:
    """Register the listener once per process (every module that defines kernels calls this)."""
    if not _registered:
        event.register("numba:compile", _listener)
        _registered.append(True)
