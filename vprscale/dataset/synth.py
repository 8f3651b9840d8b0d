"""``vprscale synth``: stage the synthetic sources on disk in the real layouts."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from vprscale.core.errors import InputError
from vprscale.core.publish import check_writable, keep_beside
from vprscale.dataset.sources.synthetic import FasParams, SyntheticDeep1B, SyntheticFAS
from vprscale.dataset.sources.writers import write_fas_npz, write_fbin, write_fvecs

LAYOUT = ("Deep1B/base", "Deep1B/base.fbin", "FAS/FAS_uniSam5_all.npz")  # the real sets' own names


RECORD = ".synth.json"  # in --out: what synth wrote there, so that --force tells its own files from others


def write_synthetic(out: Path, deep1b_rows: int, fas_dim: int, seed: int,
                    rows_per_file: int | None = None, force: bool = False) -> list[Path]:
    """Write ``Deep1B/base/base_NN`` (fvecs), ``Deep1B/base.fbin`` and ``FAS/FAS_uniSam5_all.npz``.

    These are the real datasets' own names, so a folder that already holds any of them (the real
    Deep1B, say) is refused unless ``force``: synthetic rows never silently replace real ones.
    With ``force``, files this command wrote before (recorded in ``.synth.json`` with their size
    and modification time) are replaced, and anything else there is kept beside, as
    ``<name>.previous`` (then ``.previous.1``, …), never deleted.
    """
    check_writable(out)
    held = [out / name for name in LAYOUT if (out / name).exists() and not _empty_dir(out / name)]
    if held and not force:
        raise InputError(f"--out {out}: already holds {held[0]}; --force replaces the synthetic files there "
                         "(or give another --out)")
    fas = FasParams(dim=fas_dim)
    need = 2 * deep1b_rows * 4 * (96 + 1) + 4 * fas_dim * (fas.n_ref + fas.n_query)  # fvecs and fbin; the npz
    free = shutil.disk_usage(out).free + sum(f.stat().st_size for p in held for f in _files(p))  # replaced ones
    if need > free:
        raise InputError(f"--out {out}: the files need {need / 2**30:,.1f} GiB and the disk there has "
                         f"{free / 2**30:,.1f} GiB free (--deep1b-rows {deep1b_rows:,}, --fas-dim {fas_dim})")
    ours = _written_before(out)
    for path in held:
        files = _files(path)
        if any(_identity(f) != ours.get(str(f.relative_to(out))) for f in files):
            keep_beside(path)  # not (all) synth's own: kept, not replaced
    deep = SyntheticDeep1B(deep1b_rows, seed)
    fvecs = write_fvecs(deep, out / "Deep1B" / "base", rows_per_file=rows_per_file or deep1b_rows)
    fbin = write_fbin(deep, out / "Deep1B" / "base.fbin")
    npz = write_fas_npz(SyntheticFAS(seed, fas).traverse(), out / "FAS" / "FAS_uniSam5_all.npz")
    written = [*fvecs, fbin, npz]
    tmp = out / f".{RECORD}.tmp"
    tmp.write_text(json.dumps({str(f.relative_to(out)): _identity(f) for f in written}, indent=0))
    tmp.replace(out / RECORD)
    return written


def _files(path: Path) -> list[Path]:
    """The files of ``path``: itself, or every file under it."""
    return sorted(f for f in path.rglob("*") if f.is_file()) if path.is_dir() else [path]


def _identity(path: Path) -> list[int]:
    st = path.stat()
    return [st.st_size, st.st_mtime_ns]


def _written_before(out: Path) -> dict[str, list[int]]:
    """The files synth wrote into ``out`` before, with their size and modification time then."""
    try:
        record = json.loads((out / RECORD).read_text())
    except (OSError, ValueError):
        return {}
    return record if isinstance(record, dict) else {}


def _empty_dir(path: Path) -> bool:
    return path.is_dir() and not any(path.iterdir())
