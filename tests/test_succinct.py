"""The succinct arrays under the index: bit-packed integers and Elias–Fano sequences, checked
against plain numpy on every shape hypothesis finds (duplicates, gaps, one value, wide values)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from vprscale.method.invlists import nearest_slots
from vprscale.method.succinct import EliasFano, RankBitmap, _select_in_word, occupancy_structure, pack, unpack

sorted_values = st.lists(st.integers(0, 2**40), min_size=1, max_size=3000).map(lambda v: np.sort(np.array(v, np.int64)))


@settings(max_examples=60, deadline=None)
@given(sorted_values, st.lists(st.integers(0, 2**40 + 10), max_size=200))
def test_elias_fano_equals_the_plain_sequence(values, probes):
    ef = EliasFano.build(values)
    np.testing.assert_array_equal(ef.decode(), values)
    np.testing.assert_array_equal(ef.get(np.arange(len(values))), values)
    x = np.array(probes + [0, int(values[0]), int(values[-1]), int(values[-1]) + 1], np.uint64)
    np.testing.assert_array_equal(ef.lower_bound(x), np.searchsorted(values, x.astype(np.int64)))
    again = EliasFano.from_words(ef.words(), ef.layout())  # the one-array form the index files hold
    np.testing.assert_array_equal(again.decode(3, 40), values[3:40])


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([2**12, 2**20]), st.data())
def test_nearest_occupied_slot_equals_a_full_scan(universe, data):
    """The directory's nearest occupied address, from Elias–Fano and from a rank bitmap (the
    smaller of the two stores it): equal, else the numerically nearest, ties to the smaller."""
    occupied = data.draw(st.lists(st.integers(0, universe - 1), min_size=1, max_size=2000, unique=True))
    probes = data.draw(st.lists(st.integers(0, universe - 1), max_size=300))
    occupied = np.sort(np.array(occupied, np.int64))
    for structure in (EliasFano.build(occupied), RankBitmap.build(occupied, universe)):
        np.testing.assert_array_equal(structure.decode(), occupied)
        np.testing.assert_array_equal(structure.get(np.arange(len(occupied))), occupied)
        _nearest_equals_a_scan(structure.args(), occupied, probes)
    chosen = occupancy_structure(occupied, universe)
    assert chosen.nbytes == min(EliasFano.build(occupied).nbytes, RankBitmap.build(occupied, universe).nbytes)


def _nearest_equals_a_scan(args, occupied, probes):
    h = np.array(probes + list(occupied[:5]), np.int64)
    gap = np.abs(occupied[None, :] - h[:, None])
    slots, taken = nearest_slots(args, h.astype(np.uint64))
    np.testing.assert_array_equal(slots, gap.argmin(axis=1))
    np.testing.assert_array_equal(taken, occupied[slots])


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 64), st.lists(st.integers(0, 2**64 - 1), max_size=500))
def test_packed_values_round_trip(bits, raw):
    values = np.array([v & ((1 << bits) - 1) for v in raw], np.uint64)
    words = pack(values, bits)
    assert len(words) == (len(values) * bits + 63) // 64 + 1
    np.testing.assert_array_equal(unpack(words, bits, 0, len(values)).astype(np.uint64), values)


@given(st.integers(1, 2**64 - 1), st.data())
def test_select_in_a_word_finds_the_rth_set_bit(x, data):
    ones = [i for i in range(64) if x >> i & 1]
    r = data.draw(st.integers(0, len(ones) - 1))
    assert _select_in_word(np.uint64(x), np.int64(r)) == ones[r]
