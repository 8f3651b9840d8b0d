"""Throughput in the field's units: rows per second per core and input gigabytes per second.

embedding-reader reports GB/s read, autofaiss vectors indexed per second per core; a stage's
seconds alone say neither. Per core is rows over wall time over the cores the job was given
(its ``--workers``), as the field divides: a machine busy elsewhere lowers it.
"""

from __future__ import annotations


def throughput(rows: int, nbytes: int, wall_s: float, cores: int, per: str = "core") -> str:
    """``1,047,781 rows (0.40 GB) in 12.3 s: 85,185 rows/s, 42,592 rows/s per core on 2 cores, 0.033 GB/s``
    (``per``: what the job's parallelism is counted in, cores or a fetch's connections)."""
    wall_s, cores = max(wall_s, 1e-9), max(1, cores)
    return (f"{rows:,} rows ({nbytes / 1e9:.2f} GB) in {wall_s:,.1f} s: {rows / wall_s:,.0f} rows/s, "
            f"{rows / wall_s / cores:,.0f} rows/s per {per} on {cores} {per}{'s' if cores > 1 else ''}, "
            f"{nbytes / 1e9 / wall_s:.3f} GB/s")
