"""Fixed absolute row blocks that make every result independent of chunking.

All numerics that could depend on how rows are grouped (random draws, the running sums of
the homogenisation, the partial sums of covariance matrices) are defined on blocks of
``BLOCK`` rows at absolute positions. Dask chunks are whole numbers of blocks, so a
different chunk size or worker count regroups the same block computations and gives the
same bytes.
"""

from collections.abc import Iterator

import numpy as np

BLOCK = 16384


def block_spans(start: int, stop: int, block: int = BLOCK) -> Iterator[tuple[int, int, int]]:
    """Yield ``(block_index, lo, hi)`` for the absolute blocks intersecting ``[start, stop)``."""
    b = start // block
    while b * block < stop:
        yield b, max(start, b * block), min(stop, (b + 1) * block)
        b += 1


def chunk_bounds(n: int, chunk_rows: int) -> list[tuple[int, int]]:
    """Row ranges of consecutive chunks of ``chunk_rows`` (the last may be shorter)."""
    return [(a, min(n, a + chunk_rows)) for a in range(0, n, chunk_rows)]


def block_rng(seed: int, stream: int, block: int) -> np.random.Generator:
    """The generator for one block of one random stream: a pure function of its key.

    SFC64 seeded through a SeedSequence of ``(seed, stream, block)``: streams of different
    keys are independent, and it draws about twice as fast as a counter-based Philox.
    """
    return np.random.Generator(np.random.SFC64(np.random.SeedSequence([seed & (2**64 - 1), stream, block])))


def apply_by_block(func, x: np.ndarray, start: int, *args) -> np.ndarray:
    """``func`` on each absolute-block piece of rows ``x`` (first row at ``start``), concatenated.

    A BLAS product may round a row differently depending on how many rows share the call
    (edge tiles use other kernels); calling it on the same absolute blocks whatever the
    chunking keeps every row's bits independent of the chunk size.
    """
    spans = list(block_spans(start, start + len(x)))
    if len(spans) == 1:
        return func(x, *args)
    return np.concatenate([func(x[lo - start : hi - start], *args) for _, lo, hi in spans])
