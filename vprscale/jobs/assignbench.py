"""``vprscale bench assign``: an IVF code's coarse assignment, the part of encoding that grows with
the number of lists, for choosing the coarse quantiser at a billion.

Encoding a billion references costs one coarse assignment a row (a list among ``nlist``) and then
the row's code for that list. This prints, per IVF factory string, on the same reference rows of a
full store: CPU µs a row of the assignment as ``vprscale encode`` makes it (FaissCodes's
``assign_rows``: blocks of 4,096 rows on one FAISS thread), its median over ``repeats`` with the
range, the ratio to the first factory, the hours a billion rows would take on 2 cores at that
rate, and the share of rows that an approximate quantiser (``IVF…_HNSW32``) sends to the list an
exact search over the same centroids would. Times are the calling thread's CPU time, which load
on the machine does not change; nothing here is asserted in a test.
"""

from __future__ import annotations

import time
from pathlib import Path

import faiss
import numpy as np

from vprscale.compared.faisscodes import FaissCodes, training_rows
from vprscale.core.errors import InputError
from vprscale.dataset.store import open_complete_group, store_layout

DEFAULT_FACTORIES = ("IVF4096,PQ3", "IVF1024,PQ3", "IVF4096_HNSW32,PQ3")
ASSIGNED = 1 << 16  # rows assigned per repeat


def bench_assign(store: str, factories: list[str], places: int | None, repeats: int = 3) -> str:
    """The report's lines (see the module's docstring)."""
    group = open_complete_group(Path(store))
    if store_layout(group)["kind"] == "compact":
        raise InputError(f"bench assign: {store} is a compact store; give a full one (it reads its reference rows)")
    n = min(places or group["ref"].shape[0], group["ref"].shape[0])
    ref = np.asarray(group["ref"][:n], np.float32)
    rows = ref[np.linspace(0, n - 1, min(ASSIGNED, n)).astype(np.int64)]
    lines = [f"coarse assignment on {store}: trained on {len(training_rows(n)):,} of {n:,} references, "
             f"{len(rows):,} rows assigned in blocks of 4,096 on one thread; CPU µs a row, median of {repeats} "
             "(range)"]
    first = None
    for factory in factories:
        codes = FaissCodes(factory, ref.shape[1], k=1)
        if codes.ivf is None:
            raise InputError(f"bench assign: --compare {factory}: not an IVF code (no coarse assignment)")
        codes.train(ref[training_rows(n)])
        lists = codes.assign_rows(rows, 0)  # warm
        took = []
        for _ in range(repeats):
            t0 = time.thread_time()
            codes.assign_rows(rows, 0)
            took.append((time.thread_time() - t0) / len(rows) * 1e6)
        median = float(np.median(took))
        first = first or median
        exact = faiss.IndexFlatL2(codes.dim)
        exact.add(codes.ivf.quantizer.reconstruct_n(0, codes.ivf.nlist))
        same = float(np.mean(exact.search(rows, 1)[1].ravel() == lists))
        lines.append(f"  {factory:<24} {median:7.2f} µs ({min(took):.2f}–{max(took):.2f})  {median / first:5.2f}×  "
                     f"10^9 rows on 2 cores: {median * 1e9 / 2 / 3.6e9:5.2f} h  exact list for {same:6.1%} of rows")
    return "\n".join(lines)
