"""The one exception type that means "the user gave us something wrong", and how to tell the
failures of what a job runs on (a storage, a cluster) from vprscale's own.

The CLI turns an input error into a one-line message and exit status 2; so too a storage or a
cluster that failed under a job (its work is kept for the re-run); everything else is a bug.
"""

import threading

CLUSTER = ("distributed", "tornado")  # the Dask cluster's client and its networking
STOPPING = threading.Event()  # set once a signal asked the process to stop: waits in any thread end with it


class InputError(ValueError):
    """Bad input: the message names the file, row or parameter and what is wrong."""


class QueryError(InputError):
    """A statement that the SQL engine refused: one line for the message (what a one-shot command
    prints), and the engine's own context lines (the statement, a caret under the place) as
    ``detail``, which the interactive shell shows too."""

    def __init__(self, text: str) -> None:
        first, _, rest = text.partition("\n")
        super().__init__(first)
        self.detail = rest.rstrip("\n")


class JobFailed(RuntimeError):
    """A job of vprscale's own failed (a pipeline stage crashed): exit status 1, not bad input."""


class Interrupted(KeyboardInterrupt):
    """A signal asked the process to stop (SIGTERM: a batch scheduler's time limit, ``kill``): raised
    like Ctrl-C's KeyboardInterrupt, so every ``finally`` runs and a job's record is written."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum
        STOPPING.set()


def raised_by(exc: BaseException, packages: tuple[str, ...]) -> bool:
    """Whether ``exc``, or an error in its chain of causes, was raised by these packages' code."""
    seen: BaseException | None = exc
    for _ in range(8):  # the chain of causes is short; a cycle is not followed
        if seen is None:
            return False
        if type(seen).__module__.startswith(packages):
            return True
        seen = seen.__cause__ or seen.__context__
    return False
