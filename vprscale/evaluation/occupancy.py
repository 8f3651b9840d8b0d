"""``vprscale occupancy``: how the references spread over the hash space (paper Fig. 4d data)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from vprscale.method.indexfile import load_index_meta


def occupancy(index: str | Path, top: int = 10) -> dict[str, Any]:
    """Bucket-size histogram, occupied share of K^d, largest buckets, per-component balance."""
    index = Path(index)
    meta = load_index_meta(index)
    sizes = np.diff(np.load(index / "offsets.npy", mmap_mode="r"))  # the lists' lengths, no Parquet decode
    hashes = np.load(index / "addresses.npy", mmap_mode="r")
    counts = np.bincount(sizes)
    values = np.flatnonzero(counts)
    counts = counts[values]
    top = min(top, len(sizes))
    cut = np.argpartition(-sizes, top - 1)[:top] if top else np.empty(0, np.int64)
    largest = cut[np.lexsort((cut, -sizes[cut]))]  # largest first, ties by address order
    model = pq.read_table(index / "components.parquet").to_pylist()
    return {"d": meta["d"], "k": meta["k"], "n_ref": meta["n_ref"], "occupied": len(sizes),
            "address_space": meta["k"] ** meta["d"], "occupied_share": len(sizes) / meta["k"] ** meta["d"],
            "mean_size": float(sizes.mean()), "max_size": int(sizes.max()),
            "size_histogram": [(int(v), int(c)) for v, c in zip(values, counts, strict=True)],
            "largest": [(int(hashes[i]), int(sizes[i])) for i in largest], "components": model}


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
