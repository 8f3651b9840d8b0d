"""vprscale: out-of-core dataset engineering and evaluation for coarse-hash place recognition.

The public Python API::

    from vprscale import CoarseHasher, ExactPCA, RandomizedPCA, Index, OnlineMatcher, load_results

(imported on first use, so that ``import vprscale`` and the command line start fast).
"""

__version__ = "0.10.0"

_PUBLIC = {"CoarseHasher": "vprscale.method.coarsehash", "ExactPCA": "vprscale.method.pca",
           "RandomizedPCA": "vprscale.method.pca", "Index": "vprscale.method.index",
           "OnlineMatcher": "vprscale.method.online", "load_results": "vprscale.evaluation.results"}
__all__ = [*_PUBLIC, "__version__"]


def __getattr__(name: str):
    if name in _PUBLIC:
        import importlib

        from vprscale.core.compiling import announce_compiling

        announce_compiling()  # the first use compiles numba kernels: logged (INFO) where logging is on
        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'vprscale' has no attribute {name!r}")


def _silent_library() -> None:
    """vprscale logs under the ``vprscale`` logger and prints nothing unless the application asks
    (``logging.basicConfig(level=logging.INFO)`` shows a job's progress); the command line does."""
    import logging

    logging.getLogger("vprscale").addHandler(logging.NullHandler())


_silent_library()
