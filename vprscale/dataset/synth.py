"""``vprscale synth``: stage the synthetic sources on disk in the real layouts."""

from __future__ import annotations

from pathlib import Path

from vprscale.core.errors import InputError
from vprscale.core.publish import check_writable
from vprscale.dataset.sources.synthetic import FasParams, SyntheticDeep1B, SyntheticFAS
from vprscale.dataset.sources.writers import write_fas_npz, write_fbin, write_fvecs

LAYOUT = ("Deep1B/base", "Deep1B/base.fbin", "FAS/FAS_uniSam5_all.npz")  # the real sets' own names


def write_synthetic(out: Path, deep1b_rows: int, fas_dim: int, seed: int,
                    rows_per_file: int | None = None, force: bool = False) -> list[Path]:
    """Write ``Deep1B/base/base_NN`` (fvecs), ``Deep1B/base.fbin`` and ``FAS/FAS_uniSam5_all.npz``.

    These are the real datasets' own names, so a folder that already holds any of them (the real
    Deep1B, say) is refused unless ``force``: synthetic rows never silently replace real ones.
    """
    check_writable(out)
    held = [out / name for name in LAYOUT if (out / name).exists() and not _empty_dir(out / name)]
    if held and not force:
        raise InputError(f"--out {out}: already holds {held[0]}; --force replaces the synthetic files there "
                         "(or give another --out)")
    deep = SyntheticDeep1B(deep1b_rows, seed)
    fvecs = write_fvecs(deep, out / "Deep1B" / "base", rows_per_file=rows_per_file or deep1b_rows)
    fbin = write_fbin(deep, out / "Deep1B" / "base.fbin")
    fas = write_fas_npz(SyntheticFAS(seed, FasParams(dim=fas_dim)).traverse(),
                        out / "FAS" / "FAS_uniSam5_all.npz")
    return [*fvecs, fbin, fas]


def _empty_dir(path: Path) -> bool:
    return path.is_dir() and not any(path.iterdir())
