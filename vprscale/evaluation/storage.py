"""Storage accounting of a CoarseHash index (docs/accounting.md): P1–P4 three ways.

P1 is the reference-id → address map, P2 the cluster centres, P3 the PCA matrix, P4 the
mean descriptor. "paper" counts as the paper did (8-byte numbers throughout), "packed"
stores each address in ⌈d·log2 K / 8⌉ bytes and the model in float32, "disk" is what the
index directory holds.
"""

from __future__ import annotations

import math
from pathlib import Path


def storage_table(n_ref: int, d: int, k: int, dim: int, disk: dict[str, int]) -> dict[str, dict[str, int]]:
    """``{part: {"paper": bytes, "packed": bytes, "disk": bytes}}`` for P1–P4 and the total."""
    addr_bytes = math.ceil(d * math.log2(k) / 8)
    table = {
        "P1": {"paper": 8 * n_ref, "packed": addr_bytes * n_ref, "disk": disk["P1"]},
        "P2": {"paper": 8 * d * k, "packed": 4 * d * k, "disk": disk["P2"]},
        "P3": {"paper": 8 * d * dim, "packed": 4 * d * dim, "disk": disk["P3"]},
        "P4": {"paper": 8 * dim, "packed": 4 * dim, "disk": disk["P4"]},
    }
    table["total"] = {kind: sum(v[kind] for v in table.values()) for kind in ("paper", "packed", "disk")}
    return table


def file_bytes(*paths: Path) -> int:
    return sum(p.stat().st_size for p in paths if p.exists())


def format_storage(table: dict[str, dict[str, int]]) -> str:
    names = {"P1": "ref-id → address map", "P2": "cluster centres", "P3": "PCA matrix",
             "P4": "mean descriptor", "total": "total"}
    lines = [f"{'part':<26}{'paper (8 B)':>14}{'packed':>14}{'on disk':>14}"]
    for part, row in table.items():
        label = f"{part} {names[part]}" if part != "total" else "total"
        lines.append(f"{label:<26}" + "".join(f"{row[k] / 1e6:>12.3f}MB" for k in ("paper", "packed", "disk")))
    return "\n".join(lines)
