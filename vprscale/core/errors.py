"""The one exception type that means "the user gave us something wrong".

The CLI turns it into a one-line message and exit status 2; everything else is a bug and
keeps its traceback.
"""


class InputError(ValueError):
    """Bad input: the message names the file, row or parameter and what is wrong."""


class JobFailed(RuntimeError):
    """A job of vprscale's own failed (a pipeline stage crashed): exit status 1, not bad input."""
