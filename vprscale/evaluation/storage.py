"""Storage accounting of a CoarseHash index (docs/accounting.md): P1–P4 three ways.

P1 is the reference-id → address map, P2 the cluster centres, P3 the PCA matrix, P4 the
mean descriptor. "paper" counts as the paper did (8-byte numbers throughout), "packed"
stores each address in ⌈d·log2 K⌉ bits and the model in float32, "disk" is what the index
directory holds (its codes file for P1: the same bits, as bit planes for K = 2).
"""

from __future__ import annotations

import math
from pathlib import Path


def storage_table(n_ref: int, d: int, k: int, dim: int, disk: dict[str, int]) -> dict[str, dict[str, int]]:
    """``{part: {"paper": bytes, "packed": bytes, "disk": bytes}}`` for P1–P4 and the total."""
    bits = d if k == 2 else (k**d - 1).bit_length()
    table = {
        "P1": {"paper": 8 * n_ref, "packed": math.ceil(bits * n_ref / 8), "disk": disk["P1"]},
        "P2": {"paper": 8 * d * k, "packed": 4 * d * k, "disk": disk["P2"]},
        "P3": {"paper": 8 * d * dim, "packed": 4 * d * dim, "disk": disk["P3"]},
        "P4": {"paper": 8 * dim, "packed": 4 * dim, "disk": disk["P4"]},
    }
    table["total"] = {kind: sum(v[kind] for v in table.values()) for kind in ("paper", "packed", "disk")}
    return table


def file_bytes(*paths: Path) -> int:
    return sum(p.stat().st_size for p in paths if p.exists())


# The parts of an index directory, by the files that hold them (format 4, docs/accounting.md).
INDEX_PARTS = {
    "codes (P1)": ("codes.parquet",),
    "lists": ("lists.parquet",),
    "buckets": ("buckets.parquet",),
    "components": ("components.parquet",),
    "model (P2-P4)": tuple(f"model/{n}.npy" for n in ("mean", "components", "centres", "explained_variance")),
    "metadata": ("index.json", "manifest.json"),
}


def index_parts(path: Path) -> dict[str, int]:
    """Bytes of each part of an index directory, measured from its files (evaluations excluded)."""
    return {part: file_bytes(*(path / f for f in files)) for part, files in INDEX_PARTS.items()}


def floor_bits(n_ref: int, d: int, k: int) -> int:
    """The information floor per place: its code (⌈d·log2 K⌉ bits, what the window scores read)
    and its id in a list (⌈log2 N⌉ bits); the directory adds a few bits per occupied address."""
    n_ref, d, k = int(n_ref), int(d), int(k)  # numpy integers have no bit_length
    code = d if k == 2 else (k**d - 1).bit_length()
    return code + max(1, (n_ref - 1).bit_length())


def format_parts(parts: dict[str, int], n_ref: int, d: int, k: int) -> str:
    """Each part's bytes and bytes per place, the total, and the total against the floor."""
    total = sum(parts.values())
    floor = floor_bits(n_ref, d, k) / 8
    lines = [f"{'part':<16}{'bytes':>16}{'B/place':>10}"]
    lines += [f"{name:<16}{b:>16,}{b / max(1, n_ref):>10.3f}" for name, b in parts.items()]
    lines.append(f"{'whole index':<16}{total:>16,}{total / max(1, n_ref):>10.3f}")
    lines.append(f"floor d + ⌈log2 N⌉ = {floor_bits(n_ref, d, k)} bits = {floor:.3f} B/place; "
                 f"the index is {total / max(1, n_ref) / floor:.2f}× the floor")
    return "\n".join(lines)


def format_storage(table: dict[str, dict[str, int]]) -> str:
    names = {"P1": "ref-id → address map", "P2": "cluster centres", "P3": "PCA matrix",
             "P4": "mean descriptor", "total": "total"}
    lines = [f"{'part':<26}{'paper (8 B)':>14}{'packed':>14}{'on disk':>14}"]
    for part, row in table.items():
        label = f"{part} {names[part]}" if part != "total" else "total"
        lines.append(f"{label:<26}" + "".join(f"{row[k] / 1e6:>12.3f}MB" for k in ("paper", "packed", "disk")))
    return "\n".join(lines)
