"""Deep1B's ``.fbin`` read where it lives: rows fetched by HTTP byte ranges as the build reads
them, with no local copy (:mod:`vprscale.core.ranged`: each read checked to be exactly the
range asked, a dropped answer retried from where it stopped)."""

from __future__ import annotations

import re
import struct
from typing import Any

import numpy as np

from vprscale.core.errors import InputError
from vprscale.core.objects import public
from vprscale.core.ranged import probe, read_range
from vprscale.dataset.sources.base import RowSource

URL = re.compile(r"^https?://", re.IGNORECASE)


def is_url(path: object) -> bool:
    return isinstance(path, str) and bool(URL.match(path))


class RemoteFbinSource(RowSource):
    """An ``.fbin`` at an http(s) URL: its header and size checked once, its rows read by range.

    The object holds the URL only (tasks on other processes or machines read for themselves);
    it is shown, and fingerprinted, without credentials or query string."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.name = public(url)
        n, d = struct.unpack("<II", read_range(url, 0, 8))
        size, self.version = probe(url)
        if d == 0 or size != 8 + 4 * n * d:
            raise InputError(f"{self.name}: header says n = {n}, d = {d} (a file of {8 + 4 * n * d:,} bytes) but the "
                             f"server has {size:,} bytes")
        self.n_rows, self.dim, self.bytes = n, d, size

    def _read(self, start: int, stop: int) -> np.ndarray:
        if stop == start:
            return np.empty((0, self.dim), np.float32)
        data = read_range(self.url, 8 + 4 * self.dim * start, 8 + 4 * self.dim * stop)
        return np.frombuffer(data, "<f4").reshape(stop - start, self.dim)

    def fingerprint(self) -> dict[str, Any]:
        return {"format": "fbin", "rows": self.n_rows, "dim": self.dim, "url": self.name, "bytes": self.bytes,
                "version": self.version}
