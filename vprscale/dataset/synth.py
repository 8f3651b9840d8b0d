"""``vprscale synth``: stage the synthetic sources on disk in the real layouts."""

from __future__ import annotations

from pathlib import Path

from vprscale.dataset.sources.synthetic import FasParams, SyntheticDeep1B, SyntheticFAS
from vprscale.dataset.sources.writers import write_fas_npz, write_fbin, write_fvecs


def write_synthetic(out: Path, deep1b_rows: int, fas_dim: int, seed: int,
                    rows_per_file: int | None = None) -> list[Path]:
    """Write ``Deep1B/base/base_NN`` (fvecs), ``Deep1B/base.fbin`` and ``FAS/FAS_uniSam5_all.npz``."""
    deep = SyntheticDeep1B(deep1b_rows, seed)
    fvecs = write_fvecs(deep, out / "Deep1B" / "base", rows_per_file=rows_per_file or deep1b_rows)
    fbin = write_fbin(deep, out / "Deep1B" / "base.fbin")
    fas = write_fas_npz(SyntheticFAS(seed, FasParams(dim=fas_dim)).traverse(),
                        out / "FAS" / "FAS_uniSam5_all.npz")
    return [*fvecs, fbin, fas]
