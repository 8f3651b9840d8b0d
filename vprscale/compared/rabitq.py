"""RaBitQ codes (Gao and Long, 2024) as tables: the estimator of the distance, a sum of byte look-ups.

A 1-bit RaBitQ code of a row ``x`` near centre ``c`` (the data's mean for a flat index, the
list's centroid over an inverted file) holds the signs ``s`` of ``x − c``, ``A = ‖x − c‖²``
and a factor ``D``; FAISS estimates the distance from a query frame ``y`` as

    max(0, A + ‖y − c‖² − 2 D ⟨s, y − c⟩ / √d)

(its ``RaBitQDistanceComputerNotQ``; FAISS's search quantises the frame to ``qb`` bits first,
for speed). ``⟨s, y⟩ / √d`` is a sum over the code's bytes of one 256-entry table each, the
frame's (:func:`sign_tables`), and ``⟨s, c⟩`` does not depend on the frame, so a place's
record keeps ``F = A + 2 D ⟨s, c⟩ / √d`` beside ``D``: a term is ``F + ‖y − c‖² − 2 D Σ_b
T_b[byte_b]``, the frame's distance to the centre once per frame (flat) or to the place's
list's centroid (inverted file). Only 1-bit codes: the extended bits of ``RaBitQ4`` and its
kin enter the estimator through products of their own.
"""

from __future__ import annotations

import numba
import numpy as np

from vprscale.compared.codescore import list_numbers
from vprscale.core.kernelcache import share_kernels

share_kernels()

FACTOR_BYTES = 8  # F and D, float32
PAIRWISE_BLOCK = 128  # numpy sums a row of at most this many in one block (longer: halves, recursively)
_SIGNS = np.where(np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1, bitorder="little"), 1.0, -1.0)


def sign_bytes(dim: int) -> int:
    """Bytes of a code's signs."""
    return (dim + 7) // 8


def record_width(dim: int, list_bytes: int) -> int:
    """Bytes of a place's record: its signs, its list number (inverted file), zeros up to a
    multiple of 4, then ``F`` and ``D`` (float32, read through a float32 view of the records)."""
    head = sign_bytes(dim) + list_bytes
    return -(-head // 4) * 4 + FACTOR_BYTES


def sign_tables(y: np.ndarray, block: int = 2048) -> np.ndarray:
    """Each frame's byte tables ``T_b[v] = Σ_i s_i(v) y[8b + i] / √d`` with ``s_i(v) = ±1`` the
    ``i``-th bit of ``v`` (least significant first, as FAISS packs them): (frames, bytes, 256).

    Each frame's bytes times the 8 × 256 sign matrix, a block of frames at a time (one matrix
    product; 10× an ``einsum`` of the same sums, in 100 MB of working space at most): a sum of
    eight float32 values with signs is exact in float64 (for values within 2^26 of each other
    in scale), so any order of its terms gives the same table."""
    n, dim = y.shape
    nb = sign_bytes(dim)
    out = np.empty((n, nb, 256), np.float32)
    for a in range(0, n, block):
        part = np.zeros((min(block, n - a), nb * 8), np.float64)
        part[:, :dim] = y[a : a + block]
        out[a : a + block] = ((part.reshape(-1, 8) @ _SIGNS.T) / np.sqrt(dim)).reshape(-1, nb, 256)
    return out


def records(codes: np.ndarray, dim: int, list_bytes: int, centres: np.ndarray) -> np.ndarray:
    """Places' records from their standalone codes (an inverted file's: the list number's
    little-endian bytes first) and the centres their codes are relative to (``centres[l]``
    for list ``l``; one row for a flat index)."""
    nb = sign_bytes(dim)
    lists = list_numbers(codes, list_bytes)
    signs = np.ascontiguousarray(codes[:, list_bytes : list_bytes + nb])
    factors = codes[:, list_bytes + nb : list_bytes + nb + FACTOR_BYTES].copy().view(np.float32).astype(np.float64)
    if dim <= PAIRWISE_BLOCK:
        e = _signed_sums(signs, lists, np.ascontiguousarray(centres, np.float64), dim) / np.sqrt(dim)
    else:  # numpy splits longer rows in halves, recursively: its own sum
        s = np.where(np.unpackbits(signs, axis=1, bitorder="little")[:, :dim], 1.0, -1.0)
        e = (s * centres[lists]).sum(axis=1) / np.sqrt(dim)
    out = np.zeros((len(codes), record_width(dim, list_bytes)), np.uint8)
    out[:, :nb] = signs
    out[:, nb : nb + list_bytes] = codes[:, :list_bytes]
    fd = np.stack([factors[:, 0] + 2 * factors[:, 1] * e, factors[:, 1]], axis=1).astype(np.float32)
    out[:, -FACTOR_BYTES:] = fd.view(np.uint8)
    return out


@numba.njit(cache=True, nogil=True)
def _signed_sums(signs: np.ndarray, lists: np.ndarray, centres: np.ndarray, dim: int) -> np.ndarray:
    """``Σ_i s_i c_{l,i}`` of each place (its signs ``s = ±1`` and its list's centre ``c_l``),
    summed as numpy sums a row (:func:`_row_sum`): the bits ``(s * centres[lists]).sum(axis=1)``
    gives, without its two (places × dim) float64 arrays (a million 96-d places: 3.6 s → 0.13 s)."""
    out = np.empty(signs.shape[0])
    row = np.empty(dim)
    for n in range(signs.shape[0]):
        c = centres[lists[n]]
        for i in range(dim):
            row[i] = c[i] if signs[n, i >> 3] >> (i & 7) & 1 else -c[i]
        out[n] = 0.0 + _row_sum(row, dim)  # numpy adds the row's sum to its identity, +0.0
    return out


@numba.njit(cache=True, nogil=True)
def _row_sum(a: np.ndarray, n: int) -> float:
    """numpy's pairwise sum of ``a[:n]``, ``n`` ≤ ``PAIRWISE_BLOCK`` (``pairwise_sum`` in its loops):
    under 8 terms in order; else eight running sums combined as a tree, then the rest in order."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[i]
        return res
    r0, r1, r2, r3, r4, r5, r6, r7 = a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7]
    i = 8
    while i < n - n % 8:
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[i]
        i += 1
    return res
