"""``vprscale synth --msls OUT``: a synthetic MSLS tree, in MSLS's own layout, of any size.

Real MSLS cannot be brought to every machine, and its 1.6M images are far from the sizes this
suite is for; this writes the same files (docs/bring-your-own.md, "MSLS") with descriptors that
behave like a place recognition network's: each city is a set of roads, each sequence a drive
of 20 to 200 frames along one, a few metres a frame, with the occasional dropped frame (a gap in
its frame numbers); an image's descriptor is a smooth function of where it was taken (random
Fourier features of its position, varying over about 15 m) seen through its drive's conditions
(a fixed distortion per drive, stronger at night and across seasons) and noise. Database drives
are taken in one season, query drives in others, so the subtasks mean what MSLS's do.

Everything is written in blocks of sequences (CSV rows appended, descriptors into an ``.npy``
written in place, keys one a line), so a tree of 10M database images needs memory for one
block only. The same seed writes the same bytes.
"""

from __future__ import annotations

import base64
import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.lib.format import open_memmap

from vprscale.core.errors import InputError
from vprscale.core.progress import ChunkProgress
from vprscale.dataset.msls import SUBTASKS

BLOCK_SEQUENCES = 2000  # sequences generated (and their rows written) at a time
SCALE_M = 15.0  # metres over which the appearance changes
STEP_M = (2.0, 8.0)  # metres between frames of a drive
LENGTHS = (20, 200)  # frames of a drive
GAP = 0.01  # chance that a frame of a drive is dropped (its frame number skipped)
PANO = 0.03  # share of panoramas
SIDE_M_PER_ROOT = 8.0  # a city's side in metres per square root of its database images (5M: 18 km)
ROADS_PER_ROOT = 0.4  # its roads per square root of its images (5M: 894 roads of about 9 km)


@dataclass
class MslsSynth:
    """What to write: ``frames`` database images over ``cities`` (and a query image for every
    ``query_ratio`` of them), ``dim``-d descriptors."""

    out: Path
    frames: int
    cities: list[str]
    dim: int = 64
    query_ratio: float = 0.2
    seed: int = 0


def image_key(city: int, side: int, i: int) -> str:
    """A 22-character key like MSLS's, unique to (city, side, row)."""
    digest = hashlib.blake2b(f"{city}/{side}/{i}".encode(), digest_size=16).digest()
    return base64.urlsafe_b64encode(digest).decode()[:22]


class Appearance:
    """A city's appearance: random Fourier features of position, and drive distortions."""

    def __init__(self, rng: np.random.Generator, dim: int) -> None:
        self.w = rng.normal(scale=1.0 / SCALE_M, size=(2, dim))
        self.b = rng.uniform(0, 2 * np.pi, size=dim)

    def __call__(self, pos: np.ndarray) -> np.ndarray:
        return np.cos(pos @ self.w + self.b)


def _drives(rng: np.random.Generator, n_frames: int, roads: np.ndarray) -> list[np.ndarray]:
    """Frame positions of drives summing to ``n_frames``, each along a road (a segment of the city)."""
    drives, total = [], 0
    while total < n_frames:
        length = min(int(rng.integers(LENGTHS[0], LENGTHS[1] + 1)), n_frames - total)
        a, b = roads[rng.integers(len(roads))]
        direction = (b - a) / max(np.linalg.norm(b - a), 1e-9)
        start = rng.uniform(0, 1) * (b - a) + a
        steps = np.cumsum(rng.uniform(*STEP_M, size=length))
        drives.append(start + steps[:, None] * direction + rng.normal(scale=1.0, size=(length, 2)))
        total += length
    return drives


def write_msls(req: MslsSynth) -> list[Path]:
    """Write ``OUT/train_val/<city>/{database,query}/*.csv``, ``OUT/descriptors.npy`` and
    ``OUT/keys.txt`` (every image's descriptor row and key); returns the files written."""
    out = Path(req.out)
    if out.exists() and any(out.iterdir()):
        raise InputError(f"--out {out}: not empty; synth --msls writes a new tree")
    if req.frames < len(req.cities) * LENGTHS[1]:
        raise InputError(f"--frames {req.frames}: at least {LENGTHS[1]:,} a city")
    rng = np.random.default_rng(req.seed)
    per_city = [req.frames // len(req.cities) + (i < req.frames % len(req.cities)) for i in range(len(req.cities))]
    plan = []  # (city, side, frames)
    for c, n in enumerate(per_city):
        plan += [(c, 0, n), (c, 1, max(LENGTHS[1], int(n * req.query_ratio)))]
    total = sum(n for *_, n in plan)
    out.mkdir(parents=True, exist_ok=True)
    desc = open_memmap(out / "descriptors.npy", mode="w+", dtype=np.float32, shape=(total, req.dim))
    written, row = [out / "descriptors.npy", out / "keys.txt"], 0
    bar = ChunkProgress("write the synthetic MSLS tree", total, unit="images")
    with open(out / "keys.txt", "w") as keys:
        for c, city in enumerate(req.cities):
            city_rng = np.random.default_rng([req.seed, c])
            look = Appearance(city_rng, req.dim)
            # a city whose side and number of roads grow as the square root of its images: each street
            # driven by about three database drives, as MSLS's are (a query frame then has some tens of
            # database frames within 25 m, whatever the size)
            side_m = SIDE_M_PER_ROOT * np.sqrt(per_city[c])
            roads = city_rng.uniform(0, side_m, size=(max(8, int(ROADS_PER_ROOT * np.sqrt(per_city[c]))), 2, 2))
            for side, n in ((s, n) for cc, s, n in plan if cc == c):
                folder = out / "train_val" / city / ("database", "query")[side]
                folder.mkdir(parents=True)
                files = _open_csvs(folder)
                written += [folder / name for name in files]
                i = 0
                drives = _drives(np.random.default_rng([req.seed, c, side]), n, roads)
                for d0 in range(0, len(drives), BLOCK_SEQUENCES):
                    block = drives[d0 : d0 + BLOCK_SEQUENCES]
                    i = _write_block(block, d0, c, side, i, look, rng, files, desc, row, keys, req.dim)
                    row += sum(len(d) for d in block)
                    bar.update(sum(len(d) for d in block))
                for f in files.values():
                    f.close()
    desc.flush()
    del desc
    return written


HEADERS = {"seq_info.csv": ",key,frame_number,sequence_key\n",
           "postprocessed.csv": ",key,easting,northing,night,view_direction\n",
           "raw.csv": ",key,pano\n",
           "subtask_index.csv": "," + ",".join(SUBTASKS) + "\n"}


def _open_csvs(folder: Path) -> dict:
    files = {name: open(folder / name, "w") for name in HEADERS}
    for name, f in files.items():
        f.write(HEADERS[name])
    return files


def _write_block(drives: list[np.ndarray], d0: int, c: int, side: int, i: int, look: Appearance,
                 rng: np.random.Generator, files: dict, desc: np.ndarray, row: int, keys, dim: int) -> int:
    """One block of drives: their CSV rows, descriptors and keys; returns the next image index."""
    seq_lines, post_lines, raw_lines, sub_lines, key_lines = [], [], [], [], []
    out_rows = []
    for s, pos in enumerate(drives):
        n = len(pos)
        seq_key = image_key(c, 2 + side, d0 + s)
        frames = np.cumsum(1 + (rng.uniform(size=n) < GAP)) - 1  # a dropped frame skips a number
        night = bool(side and rng.uniform() < 0.25)
        season = 0 if side == 0 else int(rng.integers(1, 3))  # the database's summer; queries' winter or later
        old = bool(rng.uniform() < 0.5)
        sideways = rng.uniform() < 0.2
        strength = 0.15 + 0.25 * night + 0.1 * (season > 0)
        twist = np.eye(dim) + rng.normal(scale=strength / np.sqrt(dim), size=(dim, dim))
        x = look(pos) @ twist + rng.normal(scale=0.3, size=(n, dim))
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        out_rows.append(x.astype(np.float32))
        pano = rng.uniform(size=n) < PANO
        # MSLS's subtasks name the database's condition, then the query's: the database (summer, day,
        # old and new drives) is in s2w and d2n, its old drives in o2n and its new ones in n2o
        if side == 0:
            sub = {"all": True, "s2w": True, "w2s": False, "o2n": old, "n2o": not old, "d2n": True, "n2d": False}
        else:
            sub = {"all": True, "s2w": season == 1, "w2s": False, "o2n": not old, "n2o": old, "d2n": night,
                   "n2d": False}
        for j in range(n):
            key = image_key(c, side, i + j)
            key_lines.append(key)
            seq_lines.append(f"{i + j},{key},{frames[j]},{seq_key}")
            post_lines.append(f"{i + j},{key},{pos[j, 0]:.3f},{pos[j, 1]:.3f},{night},"
                              f"{'Sideways' if sideways else 'Forward'}")
            raw_lines.append(f"{i + j},{key},{bool(pano[j])}")
            sub_lines.append(f"{i + j}," + ",".join(str(bool(sub[t])) for t in SUBTASKS))
        i += n
    for name, lines in (("seq_info.csv", seq_lines), ("postprocessed.csv", post_lines), ("raw.csv", raw_lines),
                        ("subtask_index.csv", sub_lines)):
        files[name].write("\n".join(lines) + "\n")
    keys.write("\n".join(key_lines) + "\n")
    block = np.concatenate(out_rows)
    desc[row : row + len(block)] = block
    return i
