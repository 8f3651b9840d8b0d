"""``vprscale occupancy``: how the references spread over the hash space (paper Fig. 4d data)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from vprscale.method.indexfile import read_lists

CHUNK = 1 << 24  # lists whose sizes are decoded together


def occupancy(index: str | Path, top: int = 10) -> dict[str, Any]:
    """Bucket-size histogram, occupied share of K^d, largest buckets, per-component balance.

    The list sizes come from the index's directory (no Parquet decode), a chunk at a time,
    so a billion places' half-billion lists take bounded memory.
    """
    _, lists, meta = read_lists(index)
    n, n_ref = lists.n_lists, int(meta["n_ref"])
    counts = np.zeros(lists.longest + 1, np.int64)
    best_slots, best_sizes = np.zeros(0, np.int64), np.zeros(0, np.int64)
    for a in range(0, n, CHUNK):
        sizes = lists.sizes(a, a + CHUNK)
        counts += np.bincount(sizes, minlength=len(counts))
        keep = min(top, len(sizes))
        cut = np.argpartition(-sizes, keep - 1)[:keep] if keep else np.empty(0, np.int64)
        best_slots, best_sizes = np.r_[best_slots, cut + a], np.r_[best_sizes, sizes[cut]]
        order = np.lexsort((best_slots, -best_sizes))[:top]  # largest first, ties by address order
        best_slots, best_sizes = best_slots[order], best_sizes[order]
    values = np.flatnonzero(counts)
    hashes = lists.addresses(best_slots)
    model = pq.read_table(Path(index) / "components.parquet").to_pylist()
    return {"d": meta["d"], "k": meta["k"], "n_ref": meta["n_ref"], "occupied": n,
            "address_space": meta["k"] ** meta["d"], "occupied_share": n / meta["k"] ** meta["d"],
            "mean_size": n_ref / max(1, n), "max_size": int(lists.longest),
            "size_histogram": [(int(v), int(counts[v])) for v in values],
            "largest": [(int(h), int(c)) for h, c in zip(hashes, best_sizes, strict=True)], "components": model}


def format_occupancy(o: dict[str, Any]) -> str:
    lines = [f"{o['n_ref']:,} refs in {o['occupied']:,} of {o['address_space']:,} addresses "
             f"({o['occupied_share']:.4%} occupied); mean bucket {o['mean_size']:.2f}, largest {o['max_size']}",
             "", "bucket size  buckets"]
    hist = o["size_histogram"]
    shown = hist if len(hist) <= 20 else hist[:15] + [(-1, -1)] + hist[-4:]
    lines += ["        …" if v < 0 else f"{v:>11}  {c:,}" for v, c in shown]
    lines += ["", "largest buckets (address: refs)"]
    lines += [f"  {h:>20}: {s}" for h, s in o["largest"]]
    lines += ["", "component  " + "  ".join(f"cluster {k} share" for k in range(o["k"]))]
    by_comp: dict[int, list[float]] = {}
    for row in o["components"]:
        by_comp.setdefault(row["component"], []).append(row["share"])
    lines += [f"{j:>9}  " + "  ".join(f"{s:>16.3f}" for s in shares) for j, shares in by_comp.items()]
    return "\n".join(lines)
