"""The one exception type that means "the user gave us something wrong".

The CLI turns it into a one-line message and exit status 2; everything else is a bug and
keeps its traceback.
"""


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
