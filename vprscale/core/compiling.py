"""Saying so when numba compiles: a first run on a machine compiles vprscale's kernels (tens of
seconds to a few minutes, depending on the command) before any progress can be shown; numba
caches them (``cache=True``, beside the modules or under ``$NUMBA_CACHE_DIR``), so every later
process loads them in milliseconds. A listener on numba's compile event logs one line the first
time a kernel of vprscale's is compiled in a process, and nothing when they come from the cache.
"""

from __future__ import annotations

import logging

from numba.core import event

log = logging.getLogger(__name__)


class _FirstCompile(event.Listener):
    def __init__(self) -> None:
        self.said = False

    def on_start(self, ev: event.Event) -> None:
        if self.said:
            return
        dispatcher = (ev.data or {}).get("dispatcher")
        module = getattr(getattr(dispatcher, "py_func", None), "__module__", "") or ""
        if module.startswith("vprscale."):
            self.said = True
            log.info("compiling numba kernels (first run only: they are cached for every later run)")

    def on_end(self, ev: event.Event) -> None:
        pass


_listener = _FirstCompile()
_registered: list[bool] = []


def announce_compiling() -> None:
    """Register the listener once per process (every module that defines kernels calls this)."""
    if not _registered:
        event.register("numba:compile", _listener)
        _registered.append(True)
