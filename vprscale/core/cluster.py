"""Where Dask work runs: threads of this process, or an existing distributed scheduler."""

from __future__ import annotations

import ctypes
import logging
import resource
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

import dask
import dask.threaded
from threadpoolctl import threadpool_limits

if TYPE_CHECKING:
    from distributed import Client

from vprscale.core.errors import InputError

CONNECT_S = 20.0  # a scheduler that has not answered by then is none (a port of something else hangs a client)
WORKERS_S = 30.0  # a scheduler without a worker by then cannot run the job


def single_threaded_blas() -> None:
    """Pin BLAS to one thread in this process.

    Dask already runs one task per core; and a multi-threaded BLAS may split a product's
    sums differently with its thread count, which would make the bytes of a result depend
    on the machine's cores. One thread per product keeps "same seed, same bytes".
    """
    threadpool_limits(limits=1, user_api="blas")


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters
HEAP_BLOCK_BYTES = 32 << 20  # glibc's largest mmap threshold
HEAP_KEPT_BYTES = 1 << 30  # free heap memory kept for the next task rather than returned to the system


def reuse_task_memory() -> None:
    """Let glibc keep the memory a task frees for the next task (where glibc is the C library).

    A pass's tasks each make and free arrays of tens of MB; by default glibc maps each one
    afresh and unmaps it after, and with two threads working every unmap stops the other
    core to flush its address translations: at 1B the build spent a fifth of its CPU time in
    the kernel. Served from the heap and kept there (blocks up to 32 MB; up to 1 GB of free
    heap kept), the same pass takes 0.78 instead of 1.10 µs a row (moments pass, 2 threads).
    Peak memory is unchanged; memory freed at the end of a job may stay with the process.
    """
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc: its own allocator's defaults
        return
    mallopt(_M_MMAP_THRESHOLD, HEAP_BLOCK_BYTES)
    mallopt(_M_TRIM_THRESHOLD, HEAP_KEPT_BYTES)


def check_query_planning() -> None:
    """Refuse to run with Dask's array query planning on.

    Its expression graphs rewrite the streamed passes (and ``map_overlap``/``map_blocks``
    chunking) in ways they do not expect. Dask reads the setting once, when ``dask.array``
    is first imported, and leaves it off by default; vprscale does not change a program's
    environment to force it, it says so when a job starts.
    """
    import dask.array as da

    if getattr(da, "ARRAY_EXPR_ENABLED", None) or dask.config.get("array.query-planning", None):
        raise InputError("dask's array.query-planning is on (DASK_ARRAY__QUERY_PLANNING or dask config); "
                         "vprscale's streamed passes need it off")


@contextmanager
def dask_client(scheduler: str | None = None, workers: int = 2) -> Iterator[Client | None]:
    """The Dask scheduler of every Dask call inside the block; yields the client, if any.

    With ``scheduler`` the work runs on that distributed cluster. Without, it runs in this
    process on Dask's threaded scheduler with ``workers`` threads (numba, numpy and BLAS
    release the GIL in the hot loops), so peak memory is this process's peak. The threaded
    scheduler, not an in-process distributed cluster: the latter's bookkeeping cost about
    15 ms per task, which tripled the time of a pass over a 10M-row store read from the
    page cache.
    """
    check_query_planning()
    if scheduler:
        client = _connect(scheduler)
        with client, threadpool_limits(limits=1, user_api="blas"):
            try:
                client.wait_for_workers(1, timeout=WORKERS_S)
            except TimeoutError:
                raise InputError(f"--scheduler {scheduler}: the scheduler has no worker (waited {WORKERS_S:.0f} s); "
                                 "start workers, or leave --scheduler out to run here") from None
            client.run(single_threaded_blas)
            client.run(reuse_task_memory)
            yield client
        return
    if workers < 1:
        raise InputError(f"--workers {workers}: must be at least 1")
    reuse_task_memory()
    # The threaded scheduler's function, not its name: given a name, Dask imports
    # ``distributed`` to look for a client (0.5 s on every run).
    with (threadpool_limits(limits=1, user_api="blas"),
          dask.config.set(scheduler=dask.threaded.get, num_workers=workers)):
        yield None


def _connect(scheduler: str) -> Client:
    """A client of the scheduler at ``scheduler``, or one line within ``CONNECT_S``: the address is
    first asked who it is (distributed's client waits forever for an answer from a port where
    another server listens, and sets itself as Dask's scheduler before it does), then the client
    is made."""
    from distributed import Client  # imported only here: 0.3 s a local run need not pay

    if not logging.getLogger("vprscale").isEnabledFor(logging.DEBUG):
        # distributed sets up logging of its own when imported, and would print a lost scheduler's or
        # worker's tracebacks on stderr; the job says it in one line (they show with --verbose)
        for handler in logging.getLogger("distributed").handlers:  # its loggers' records all end there
            handler.setLevel(logging.CRITICAL)
    answer: dict[str, object] = {}

    def ask() -> None:  # in a thread of its own: its own event loop, whatever the caller runs
        import asyncio

        from distributed.comm import connect

        async def identity() -> object:
            comm = await connect(scheduler, timeout=CONNECT_S)
            try:
                await comm.write({"op": "identity", "reply": True})
                return await comm.read()
            finally:
                await comm.close()

        try:
            answer["reply"] = asyncio.run(asyncio.wait_for(identity(), CONNECT_S))
        except (OSError, TimeoutError) as exc:
            answer["error"] = exc
        except (ValueError, TypeError) as exc:  # an address distributed cannot parse
            answer["bad"] = exc

    asking = threading.Thread(target=ask, name="vprscale-scheduler-probe", daemon=True)
    asking.start()
    asking.join(CONNECT_S + 5)
    reply = answer.get("reply")
    if "bad" in answer:
        raise InputError(f"--scheduler {scheduler}: not a scheduler address ({answer['bad']}); "
                         "e.g. tcp://host:8786")
    if not isinstance(reply, dict) or reply.get("type") != "Scheduler":
        why = f" ({answer['error']})" if str(answer.get("error") or "") else ""
        raise InputError(f"--scheduler {scheduler}: no Dask scheduler answered within {CONNECT_S:.0f} s{why}")
    try:
        return Client(scheduler, timeout=f"{CONNECT_S:.0f}s", set_as_default=True)
    except (OSError, TimeoutError) as exc:
        raise InputError(f"--scheduler {scheduler}: cannot connect: {exc}") from None


def peak_rss_bytes() -> int:
    """Peak resident memory of this process (and its waited-for children)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return 1024 * max(own, kids)


def cluster_peak_rss(client: Client | None) -> int:
    """The largest peak RSS among this process and the client's worker processes."""
    peaks = [peak_rss_bytes()]
    if client is None:
        return peaks[0]
    try:
        peaks += list(client.run(peak_rss_bytes).values())
    except Exception:  # noqa: BLE001 - a worker that cannot answer does not fail the job
        pass
    return max(peaks)
