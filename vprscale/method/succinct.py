"""Succinct arrays of the index (docs/method.md, "Storage"): integers bit-packed at their
width, and ascending sequences as Elias–Fano.

At a billion places every byte per place is a gigabyte, so the index stores what the query
engine reads at close to its information content: a place's id in ⌈log2 N⌉ bits, not 32,
and the directory of occupied addresses and list starts in about 2 + log2(u/n) bits per
entry, not 32 or 64.

*Packed*: value ``i`` of a ``bits``-wide array occupies bits ``[i·bits, (i + 1)·bits)`` of
little-endian uint64 words; a zero word pads the end, so that a read may always load two
words.

*Elias–Fano* (Elias 1974, Fano 1971; Vigna, "Quasi-succinct indices", 2013): ``n``
ascending values below ``u`` are split into their ``lb = ⌊log2(u/n)⌋`` low bits, stored
packed, and their high part, stored in unary in a bit vector: value ``i`` sets bit
``(v_i >> lb) + i``. Value ``i`` is then found from the position of the ``i``-th one
(select1); the values whose high part is ``h`` lie between the ``(h − 1)``-th and the
``h``-th zero (select0). Every ``SAMPLE``-th one and zero has its position kept, so a
select reads one sample and, on average, a couple of words. One uint64 array holds a
sequence whole (:meth:`EliasFano.words`), which is how the index files store it.

*Rank bitmap*: where the values are dense in their universe (the occupied addresses of an
index at its default width fill 37–55 % of K^d), one bit per possible value is smaller than
Elias–Fano's 2 + log2(u/n) bits per value, and faster: a value's rank is a sampled count
plus the popcounts of at most eight words, and its neighbours are usually in the same word.
:func:`occupancy_structure` builds whichever of the two is smaller.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from vprscale.core.kernelcache import share_kernels
from vprscale.method.intrinsics import leading_zeros, popcount, trailing_zeros

share_kernels()

SAMPLE_BITS = 8
SAMPLE = 1 << SAMPLE_BITS  # every 256th one (and zero) keeps its position: 0.25 bit per value
ALL = np.uint64(0xFFFFFFFFFFFFFFFF)


def packed_words(n: int, bits: int) -> int:
    """Words that hold ``n`` values of ``bits`` bits, with the padding word."""
    return (n * bits + 63) // 64 + 1


def width(top: int) -> int:
    """Bits that hold every value up to ``top`` (at least 1)."""
    return max(1, int(top).bit_length())


@numba.njit(cache=True, nogil=True, inline="always")
def get_packed(words: np.ndarray, bits: int, i: np.int64) -> np.uint64:
    """Value ``i`` of a packed array."""
    pos = np.uint64(i) * np.uint64(bits)
    w = np.int64(pos >> np.uint64(6))
    o = pos & np.uint64(63)
    v = words[w] >> o
    if o + np.uint64(bits) > np.uint64(64):
        v |= words[w + 1] << (np.uint64(64) - o)
    if bits < 64:
        v &= (np.uint64(1) << np.uint64(bits)) - np.uint64(1)
    return v


@numba.njit(cache=True, nogil=True, inline="always")
def _put(words: np.ndarray, bits: int, pos: np.uint64, v: np.uint64) -> None:
    """Or the ``bits``-bit value ``v`` into ``words`` at bit ``pos``."""
    w = np.int64(pos >> np.uint64(6))
    o = pos & np.uint64(63)
    words[w] |= v << o
    if o + np.uint64(bits) > np.uint64(64):
        words[w + 1] |= v >> (np.uint64(64) - o)


@numba.njit(cache=True, nogil=True)
def pack_bits_into(words: np.ndarray, bits: int, first_bit: np.int64, values: np.ndarray) -> None:
    """Write ``values`` of ``bits`` bits each from bit ``first_bit`` of ``words`` (still zero there)."""
    for j in range(values.shape[0]):
        _put(words, bits, np.uint64(first_bit) + np.uint64(j) * np.uint64(bits), np.uint64(values[j]))


@numba.njit(cache=True, nogil=True)
def unpack(words: np.ndarray, bits: int, a: np.int64, b: np.int64) -> np.ndarray:
    """Values ``a … b − 1`` of a packed array, as int64."""
    out = np.empty(max(0, b - a), np.int64)
    for j in range(out.shape[0]):
        out[j] = np.int64(get_packed(words, bits, a + j))
    return out


def pack(values: np.ndarray, bits: int) -> np.ndarray:
    """A packed array of ``values`` (non-negative, below ``2**bits``)."""
    words = np.zeros(packed_words(len(values), bits), np.uint64)
    pack_bits_into(words, bits, np.int64(0), np.asarray(values, np.uint64))
    return words


def _byte_select_table() -> np.ndarray:
    """``table[8·b + r]``: the position of the ``r``-th set bit of the byte ``b``."""
    table = np.zeros(256 * 8, np.uint8)
    for b in range(256):
        for r, p in enumerate(i for i in range(8) if b >> i & 1):
            table[8 * b + r] = p
    return table


BYTE_SELECT = _byte_select_table()
L8, H8 = np.uint64(0x0101010101010101), np.uint64(0x8080808080808080)
M1, M2, M4 = np.uint64(0x5555555555555555), np.uint64(0x3333333333333333), np.uint64(0x0F0F0F0F0F0F0F0F)


@numba.njit(cache=True, nogil=True, inline="always")
def _select_in_word(x: np.uint64, r: np.int64) -> np.int64:
    """Position of the ``r``-th (from 0) set bit of ``x``, which has more than ``r``.

    Broadword (Vigna, "Broadword implementation of rank/select queries", 2008): the bytes'
    cumulative popcounts in one multiply, the byte holding the bit by a bytewise compare,
    then a table of the 8 positions in each byte; no branch, about a nanosecond (a loop
    clearing bits took 14, its branches unpredictable).
    """
    s = x - ((x >> np.uint64(1)) & M1)
    s = (s & M2) + ((s >> np.uint64(2)) & M2)
    s = ((s + (s >> np.uint64(4))) & M4) * L8  # byte i: the set bits of bytes 0 … i
    below = ((((np.uint64(r) * L8) | H8) - s) & H8) >> np.uint64(7)  # 1 in each byte whose count is ≤ r
    shift = ((below * L8) >> np.uint64(56)) << np.uint64(3)  # 8 × the number of such bytes
    before = np.int64(((s << np.uint64(8)) >> shift) & np.uint64(255))
    byte = np.int64((x >> shift) & np.uint64(255))
    return np.int64(shift) + np.int64(BYTE_SELECT[8 * byte + r - before])


@numba.njit(cache=True, nogil=True, inline="always")
def select(high: np.ndarray, samples: np.ndarray, i: np.int64, ones: bool) -> np.int64:
    """Position of the ``i``-th one (``ones``) or zero of the bit vector ``high``."""
    s = i >> SAMPLE_BITS
    p = samples[s]
    r = i - (s << SAMPLE_BITS)
    w = p >> 6
    x = high[w] if ones else ~high[w]
    x &= ALL << np.uint64(p & 63)
    while True:
        c = popcount(x)
        if r < c:
            break
        r -= c
        w += 1
        x = high[w] if ones else ~high[w]
    return w * 64 + _select_in_word(x, r)


@numba.njit(cache=True, nogil=True, inline="always")
def _bit(high: np.ndarray, p: np.int64) -> bool:
    return (high[p >> 6] >> np.uint64(p & 63)) & np.uint64(1) != np.uint64(0)


@numba.njit(cache=True, nogil=True, inline="always")
def ef_get(high: np.ndarray, low: np.ndarray, lb: int, ones: np.ndarray, i: np.int64) -> np.int64:
    """Value ``i`` of an Elias–Fano sequence."""
    p = select(high, ones, i, True)
    v = np.uint64(p - i) << np.uint64(lb)
    if lb:
        v |= get_packed(low, lb, i)
    return np.int64(v)


@numba.njit(cache=True, nogil=True, inline="always")
def ef_pair(high: np.ndarray, low: np.ndarray, lb: int, ones: np.ndarray, i: np.int64) -> tuple[np.int64, np.int64]:
    """Values ``i`` and ``i + 1`` (a list's start and stop): one select, then the next one bit."""
    p = select(high, ones, i, True)
    w = p >> 6
    x = high[w] & (ALL << np.uint64(p & 63)) & ~(np.uint64(1) << np.uint64(p & 63))
    while x == np.uint64(0):
        w += 1
        x = high[w]
    q = w * 64 + trailing_zeros(x)
    a = np.uint64(p - i) << np.uint64(lb)
    b = np.uint64(q - i - 1) << np.uint64(lb)
    if lb:
        a |= get_packed(low, lb, i)
        b |= get_packed(low, lb, i + 1)
    return np.int64(a), np.int64(b)


@numba.njit(cache=True, nogil=True, inline="always")
def ef_lower_bound(high: np.ndarray, low: np.ndarray, lb: int, zeros: np.ndarray, n: np.int64,
                   buckets: np.int64, x: np.uint64) -> np.int64:
    """Index of the first value ≥ ``x`` (``n`` if none); ``buckets`` is the number of zeros."""
    hx = np.int64(x >> np.uint64(lb))
    if hx >= buckets:
        return n
    p = np.int64(0) if hx == 0 else select(high, zeros, hx - 1, False) + 1
    i = p - hx
    while _bit(high, p):  # the values whose high part is hx, ascending
        v = np.uint64(hx) << np.uint64(lb)
        if lb:
            v |= get_packed(low, lb, i)
        if v >= x:
            return i
        i += 1
        p += 1
    return i


@numba.njit(cache=True, nogil=True, inline="always")
def _value(low: np.ndarray, lb: int, i: np.int64, high_part: np.int64) -> np.uint64:
    v = np.uint64(high_part) << np.uint64(lb)
    if lb:
        v |= get_packed(low, lb, i)
    return v


@numba.njit(cache=True, nogil=True, inline="always")
def ef_nearest(high: np.ndarray, low: np.ndarray, lb: int, ones: np.ndarray, zeros: np.ndarray, n: np.int64,
               buckets: np.int64, x: np.uint64) -> tuple[np.int64, np.uint64]:
    """``(index, value)`` of the value equal to ``x``, else of the numerically nearest (ties: the smaller).

    One select0 finds the run of values sharing ``x``'s high part; the scan along it, on to
    the next one bit, and back to the one bit before the run, finds the neighbours without
    selecting them again.
    """
    hx = np.int64(x >> np.uint64(lb))
    if hx >= buckets:
        return n - 1, np.uint64(ef_get(high, low, lb, ones, n - 1))
    p = np.int64(0) if hx == 0 else select(high, zeros, hx - 1, False) + 1
    i = p - hx
    below, has_below = np.uint64(0), False
    while _bit(high, p):  # the run of values whose high part is hx
        v = _value(low, lb, i, hx)
        if v >= x:
            break
        below, has_below = v, True
        i += 1
        p += 1
    if i == n:  # every value is below x
        return n - 1, below if has_below else np.uint64(ef_get(high, low, lb, ones, n - 1))
    w = p >> 6  # the value at i: at or after p
    word = high[w] & (ALL << np.uint64(p & 63))
    while word == np.uint64(0):
        w += 1
        word = high[w]
    q = w * 64 + trailing_zeros(word)
    above = _value(low, lb, i, q - i)
    if above == x or i == 0:
        return i, above
    if not has_below:  # value i − 1 is the last one bit before the run's start p0 = p − (i − i0)
        r = p - 1
        w = r >> 6
        word = high[w] & (ALL >> np.uint64(63 - (r & 63)))
        while word == np.uint64(0):
            w -= 1
            word = high[w]
        below = _value(low, lb, i - 1, w * 64 + 63 - leading_zeros(word) - (i - 1))
    return (i - 1, below) if x - below <= above - x else (i, above)


@numba.njit(cache=True, nogil=True)
def _build_high(values: np.ndarray, lb: int, high: np.ndarray, low: np.ndarray) -> None:
    prev = np.uint64(0)
    for i in range(values.shape[0]):
        v = np.uint64(values[i])
        if v < prev:
            raise ValueError("Elias-Fano values must ascend")
        prev = v
        p = np.int64(v >> np.uint64(lb)) + i
        high[p >> 6] |= np.uint64(1) << np.uint64(p & 63)
    if lb:
        mask = (np.uint64(1) << np.uint64(lb)) - np.uint64(1)
        for i in range(values.shape[0]):
            _put(low, lb, np.uint64(i) * np.uint64(lb), np.uint64(values[i]) & mask)


@numba.njit(cache=True, nogil=True)
def _samples(high: np.ndarray, nbits: np.int64, ones: bool, count: np.int64) -> np.ndarray:
    """Positions of every ``SAMPLE``-th one (or zero) of the first ``nbits`` bits of ``high``."""
    out = np.zeros((count + SAMPLE - 1) // SAMPLE + 1, np.int64)
    k, seen = 0, np.int64(0)
    for w in range((nbits + 63) // 64):
        x = high[w] if ones else ~high[w]
        if (w + 1) * 64 > nbits:
            x &= (np.uint64(1) << np.uint64(nbits - w * 64)) - np.uint64(1)
        c = popcount(x)
        while k * SAMPLE < seen + c:
            out[k] = w * 64 + _select_in_word(x, k * SAMPLE - seen)
            k += 1
        seen += c
    return out


RANK_WORDS = 8  # words per rank sample of a bitmap: 512 bits, 12.5 % on top of the bitmap
LOCAL_WORDS = 2  # words a bitmap's neighbour search scans each way before it selects


@numba.njit(cache=True, nogil=True, inline="always")
def rb_rank(bits: np.ndarray, ranks: np.ndarray, x: np.int64) -> np.int64:
    """Set bits of ``bits`` before position ``x``."""
    w = x >> 6
    r = ranks[w >> 3]
    for j in range((w >> 3) << 3, w):
        r += popcount(bits[j])
    if x & 63:
        r += popcount(bits[w] & ((np.uint64(1) << np.uint64(x & 63)) - np.uint64(1)))
    return r


@numba.njit(cache=True, nogil=True, inline="always")
def rb_nearest(bits: np.ndarray, ranks: np.ndarray, ones: np.ndarray, n: np.int64, universe: np.int64,
               x: np.uint64) -> tuple[np.int64, np.uint64]:
    """``(rank, value)`` of the set bit at ``x``, else of the nearest one (ties: the smaller)."""
    if np.int64(x) >= universe:
        return n - 1, np.uint64(select(bits, ones, n - 1, True))
    xi = np.int64(x)
    r = rb_rank(bits, ranks, xi)
    w, o = xi >> 6, np.uint64(xi & 63)
    if (bits[w] >> o) & np.uint64(1):
        return r, x
    above = np.int64(-1)  # the next set bit: in this word or the next few, else by select
    word = bits[w] & (ALL << o)
    for j in range(w, min(w + LOCAL_WORDS + 1, bits.shape[0])):
        if j > w:
            word = bits[j]
        if word:
            above = j * 64 + trailing_zeros(word)
            break
    if above < 0 and r < n:
        above = select(bits, ones, r, True)
    below = np.int64(-1)  # the previous set bit, the same way down
    word = bits[w] & ((np.uint64(1) << o) - np.uint64(1))
    for j in range(w, max(w - LOCAL_WORDS - 1, -1), -1):
        if j < w:
            word = bits[j]
        if word:
            below = j * 64 + 63 - leading_zeros(word)
            break
    if below < 0 and r > 0:
        below = select(bits, ones, r - 1, True)
    if below < 0 or (above >= 0 and above - xi < xi - below):
        return r, np.uint64(above)
    return r - 1, np.uint64(below)


@numba.njit(cache=True, nogil=True)
def _set_bits(values: np.ndarray, bits: np.ndarray) -> None:
    prev = np.int64(-1)
    for i in range(values.shape[0]):
        v = np.int64(values[i])
        if v <= prev:
            raise ValueError("bitmap values must ascend strictly")
        prev = v
        bits[v >> 6] |= np.uint64(1) << np.uint64(v & 63)


@numba.njit(cache=True, nogil=True)
def _block_ranks(bits: np.ndarray) -> np.ndarray:
    out = np.zeros((bits.shape[0] + RANK_WORDS - 1) // RANK_WORDS + 1, np.int64)
    total = np.int64(0)
    for j in range(bits.shape[0]):
        if j % RANK_WORDS == 0:
            out[j // RANK_WORDS] = total
        total += popcount(bits[j])
    out[-1] = total
    return out


@numba.njit(cache=True, nogil=True)
def one_positions(bits: np.ndarray, ones: np.ndarray, a: np.int64, b: np.int64) -> np.ndarray:
    """Positions of the set bits ``a … b − 1`` of a bit vector: one select, then the following
    set bits in order (a bitmap's values; an Elias–Fano sequence's high parts plus index)."""
    out = np.empty(max(0, b - a), np.int64)
    if b <= a:
        return out
    p = select(bits, ones, a, True)
    w = p >> 6
    x = bits[w] & (ALL << np.uint64(p & 63))
    for i in range(b - a):
        while x == np.uint64(0):
            w += 1
            x = bits[w]
        out[i] = w * 64 + trailing_zeros(x)
        x &= x - np.uint64(1)
    return out


@numba.njit(cache=True, nogil=True)
def _bitmap_take(bits: np.ndarray, ones: np.ndarray, idx: np.ndarray) -> np.ndarray:
    out = np.empty(idx.shape[0], np.int64)
    for j in range(idx.shape[0]):
        out[j] = select(bits, ones, idx[j], True)
    return out


@dataclass
class RankBitmap:
    """A strictly ascending sequence of ``n`` integers below ``universe`` as a bitmap with rank
    and select samples (see the module)."""

    bits: np.ndarray
    ranks: np.ndarray  # set bits before each block of RANK_WORDS words (and the total last)
    ones: np.ndarray  # position of every SAMPLE-th set bit
    n: int
    universe: int

    @classmethod
    def build(cls, values: np.ndarray, universe: int) -> RankBitmap:
        bits = np.zeros((universe + 63) // 64 + 1, np.uint64)
        _set_bits(values, bits)
        return cls(bits, _block_ranks(bits), _samples(bits, np.int64(universe), True, len(values)), len(values),
                   universe)

    def words(self) -> np.ndarray:
        return np.concatenate([self.bits, self.ranks.view(np.uint64), self.ones.view(np.uint64)])

    def layout(self) -> dict[str, int | str]:
        return {"kind": "bitmap", "n": self.n, "universe": self.universe, "sample_bits": SAMPLE_BITS,
                "bits": len(self.bits), "ranks": len(self.ranks), "ones": len(self.ones)}

    @classmethod
    def from_words(cls, words: np.ndarray, layout: dict[str, Any]) -> RankBitmap:
        bits, ranks, ones = _split(words, layout, ("bits", "ranks", "ones"))
        return cls(bits, ranks.view(np.int64), ones.view(np.int64), int(layout["n"]), int(layout["universe"]))

    def in_memory(self) -> RankBitmap:
        return RankBitmap(np.array(self.bits), np.array(self.ranks), np.array(self.ones), self.n, self.universe)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.bits, self.ranks, self.ones))

    def __len__(self) -> int:
        return self.n

    def get(self, i: np.ndarray | int) -> np.ndarray:
        """Values at indexes ``i`` (int64)."""
        return _bitmap_take(self.bits, self.ones, np.atleast_1d(np.asarray(i, np.int64)))

    def decode(self, a: int = 0, b: int | None = None) -> np.ndarray:
        b = self.n if b is None else min(b, self.n)
        return one_positions(self.bits, self.ones, np.int64(a), np.int64(max(a, b)))

    def args(self) -> tuple:
        """The occupancy tuple the look-up kernels take (:func:`occupancy_structure`)."""
        return (np.int64(1), self.bits, np.zeros(1, np.uint64), np.int64(0), self.ones, self.ranks, np.int64(self.n),
                np.int64(self.universe))


def _split(words: np.ndarray, layout: dict[str, Any], parts: tuple[str, ...]) -> list[np.ndarray]:
    """Views of the consecutive ``parts`` of one array, by the lengths ``layout`` gives."""
    if layout.get("sample_bits") != SAMPLE_BITS:
        raise ValueError(f"select samples every 2^{layout.get('sample_bits')} bits, this vprscale reads "
                         f"2^{SAMPLE_BITS}")
    cuts = np.cumsum([0] + [int(layout[k]) for k in parts])
    if cuts[-1] != len(words):
        raise ValueError(f"{len(words)} words, the layout describes {cuts[-1]}")
    return [words[a:b] for a, b in zip(cuts[:-1], cuts[1:], strict=True)]


@dataclass
class EliasFano:
    """An ascending sequence of ``n`` integers below ``2**63``, in Elias–Fano form (see the module)."""

    high: np.ndarray  # the unary high parts, n + buckets bits
    low: np.ndarray  # the low lb bits, packed
    ones: np.ndarray  # position of every SAMPLE-th one
    zeros: np.ndarray  # position of every SAMPLE-th zero
    n: int
    lb: int
    buckets: int  # zeros of ``high``: the high parts 0 … buckets − 1

    @classmethod
    def build(cls, values: np.ndarray) -> EliasFano:
        """The sequence of ``values`` (ascending; a memory-mapped array is read once, in order)."""
        n = len(values)
        top = int(values[-1]) if n else 0
        lb = max(0, int(np.floor(np.log2((top + 1) / n)))) if n else 0
        buckets = (top >> lb) + 1
        nbits = n + buckets
        high = np.zeros((nbits + 63) // 64 + 1, np.uint64)
        low = np.zeros(packed_words(n, lb) if lb else 1, np.uint64)
        _build_high(values, lb, high, low)
        return cls(high, low, _samples(high, nbits, True, n), _samples(high, nbits, False, buckets), n, lb, buckets)

    def words(self) -> np.ndarray:
        """The sequence as one uint64 array (with :meth:`layout`, what :meth:`from_words` reads)."""
        return np.concatenate([self.high, self.low, self.ones.view(np.uint64), self.zeros.view(np.uint64)])

    def layout(self) -> dict[str, int | str]:
        return {"kind": "elias-fano", "n": self.n, "lb": self.lb, "buckets": self.buckets, "sample_bits": SAMPLE_BITS,
                "high": len(self.high), "low": len(self.low),
                "ones": len(self.ones), "zeros": len(self.zeros)}

    @classmethod
    def from_words(cls, words: np.ndarray, layout: dict[str, Any]) -> EliasFano:
        """The sequence over ``words`` (views: a memory-mapped file stays mapped)."""
        high, low, ones, zeros = _split(words, layout, ("high", "low", "ones", "zeros"))
        return cls(high, low, ones.view(np.int64), zeros.view(np.int64), int(layout["n"]), int(layout["lb"]),
                   int(layout["buckets"]))

    def in_memory(self) -> EliasFano:
        """A copy held in memory (a memory-mapped sequence read whole, in order)."""
        return EliasFano(*(np.array(a) for a in (self.high, self.low, self.ones, self.zeros)), self.n, self.lb,
                         self.buckets)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.high, self.low, self.ones, self.zeros))

    def __len__(self) -> int:
        return self.n

    def get(self, i: np.ndarray | int) -> np.ndarray:
        """Values at indexes ``i`` (int64)."""
        return ef_take(self.high, self.low, self.lb, self.ones, np.atleast_1d(np.asarray(i, np.int64)))

    def decode(self, a: int = 0, b: int | None = None) -> np.ndarray:
        """Values ``a … b − 1`` (default: all), decoded in one pass."""
        b = self.n if b is None else min(b, self.n)
        return ef_range(self.high, self.low, self.lb, self.ones, np.int64(a), np.int64(max(a, b)))

    def args(self) -> tuple:
        """The occupancy tuple the look-up kernels take (:func:`occupancy_structure`)."""
        return (np.int64(0), self.high, self.low, np.int64(self.lb), self.ones, self.zeros, np.int64(self.n),
                np.int64(self.buckets))

    def lower_bound(self, x: np.ndarray) -> np.ndarray:
        """Index of the first value ≥ each ``x`` (``n`` where none is)."""
        return ef_lower_bounds(self.high, self.low, self.lb, self.zeros, self.n, self.buckets,
                               np.asarray(x, np.uint64))


@numba.njit(cache=True, nogil=True)
def ef_take(high: np.ndarray, low: np.ndarray, lb: int, ones: np.ndarray, idx: np.ndarray) -> np.ndarray:
    out = np.empty(idx.shape[0], np.int64)
    for j in range(idx.shape[0]):
        out[j] = ef_get(high, low, lb, ones, idx[j])
    return out


@numba.njit(cache=True, nogil=True)
def ef_range(high: np.ndarray, low: np.ndarray, lb: int, ones: np.ndarray, a: np.int64, b: np.int64) -> np.ndarray:
    """Values ``a … b − 1``, decoded in one pass over their one bits."""
    out = one_positions(high, ones, a, b)
    for i in range(out.shape[0]):
        v = np.uint64(out[i] - (a + i)) << np.uint64(lb)
        if lb:
            v |= get_packed(low, lb, a + i)
        out[i] = np.int64(v)
    return out


@numba.njit(cache=True, nogil=True)
def ef_lower_bounds(high: np.ndarray, low: np.ndarray, lb: int, zeros: np.ndarray, n: np.int64, buckets: np.int64,
                    x: np.ndarray) -> np.ndarray:
    out = np.empty(x.shape[0], np.int64)
    for j in range(x.shape[0]):
        out[j] = ef_lower_bound(high, low, lb, zeros, n, buckets, x[j])
    return out


def occupancy_structure(values: np.ndarray, universe: int) -> EliasFano | RankBitmap:
    """The smaller of an Elias–Fano sequence and a rank bitmap over ``values`` (strictly
    ascending, below ``universe``): the bitmap where they are dense."""
    n = len(values)
    top = int(values[-1]) if n else 0
    lb = max(0, int(np.floor(np.log2((top + 1) / n)))) if n else 0
    buckets = (top >> lb) + 1
    samples = (n + SAMPLE - 1) // SAMPLE + 1
    ef_words = ((n + buckets + 63) // 64 + 1 + (packed_words(n, lb) if lb else 1) + samples
                + (buckets + SAMPLE - 1) // SAMPLE + 1)
    bits = (universe + 63) // 64 + 1
    bitmap_words = bits + (bits + RANK_WORDS - 1) // RANK_WORDS + 1 + samples
    return RankBitmap.build(values, universe) if bitmap_words < ef_words else EliasFano.build(values)


def structure_from_words(words: np.ndarray, layout: dict[str, Any]) -> EliasFano | RankBitmap:
    """The structure ``layout`` names, over ``words``."""
    if layout.get("kind") == "bitmap":
        return RankBitmap.from_words(words, layout)
    return EliasFano.from_words(words, layout)
