"""Query engine, sequence matching and the baseline on hand-built cases with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from vprscale.compared.baseline import baseline_batch, nearest
from vprscale.evaluation.metrics import recall_curve
from vprscale.method.coarsehash import CoarseHasher
from vprscale.method.index import Index
from vprscale.method.kernels import match_batch
from vprscale.method.online import OnlineMatcher
from vprscale.protocol import MIN_FAS, NO_MASK, part_weights, query_centres

CENTRES = np.tile([[-1.0, 1.0]], (4, 1))  # d = 4, K = 2, equal gaps: δ = 2·Hamming in real units


def hand_index(ref_hash, centres: np.ndarray = CENTRES, errors=None) -> Index:
    """An index over given addresses with given centres (identity PCA); errors default to 0."""
    ref_hash = np.asarray(ref_hash, np.uint64)
    d = centres.shape[0]
    hasher = CoarseHasher.from_fitted(centres.shape[1], 1 << 14, len(ref_hash), np.zeros(d), np.eye(d), centres,
                                      np.ones(d))
    return Index.from_addresses(ref_hash, hasher, np.zeros(len(ref_hash)) if errors is None else errors)


def plain(idx: Index) -> dict[str, np.ndarray]:
    """The index's succinct parts decoded to plain arrays: what the tests' definitions read."""
    return {"addresses": idx.lists.occupied.decode().astype(np.uint64), "offsets": idx.lists.starts.decode(),
            "ids": idx.lists.ids_range(0, idx.n_ref), "ref_hash": idx.ref_addresses(),
            "best": idx.lists.best(np.arange(idx.occupied))}


# the window mask, n_best and threads as vprscale passes them (numba compiles the defaults left out as another
# signature)
ONE_BEST = (NO_MASK, 1, 2)  # every window exists (one traverse); the match alone; 2 threads


def run(idx: Index, q_hash, t, L, aligned=False):
    qf = idx.query_frames(np.asarray(q_hash, np.uint64))
    top, _, n_r = match_batch(np.asarray(t, np.int64), L, aligned, *qf.kernel_args(), *idx.kernel_args(), *ONE_BEST)
    return top[:, 0], n_r


def test_exact_and_fallback_addresses_with_ties_to_the_smaller():
    idx = hand_index([2, 6, 6, 10])
    got = plain(idx)["addresses"][idx.nearest_occupied(np.array([6, 7, 8, 9, 0, 15], np.uint64))]
    np.testing.assert_array_equal(got, [6, 6, 6, 10, 2, 10])  # 8 is 2 from 6 and 10: the smaller


def test_single_best_and_in_list_bound():
    idx = hand_index([3, 3, 3, 5], errors=np.array([0.3, 0.1, 0.1, 0.0]))
    a = idx.nearest_occupied(np.array([3], np.uint64))
    assert idx.lists.best(a)[0] == 1  # least error, ties to the smaller id
    np.testing.assert_array_equal(idx.lists.list_ids(a[0]), [1, 0, 2])  # the best first, then by id
    from vprscale.method.invlists import in_list_distance

    qf = idx.query_frames(np.array([3], np.uint64))
    np.testing.assert_array_equal(in_list_distance(qf.start, qf.stop, qf.ids, np.array([0]), np.array([3])), [1])


def test_sequence_match_picks_the_aligned_diagonal():
    ref = np.array([1, 2, 4, 8, 1, 2, 4, 8, 3, 5, 6, 9, 12, 10, 7, 11])
    idx = hand_index(ref)
    q = ref[8:13]  # query frames 0..4 repeat refs 8..12
    match, n_r = run(idx, q, [2], L=5)
    assert match[0] == 10 and n_r[0] == 5


def test_paper_mode_only_scores_listed_ids_but_aligned_proposes_diagonals():
    ref = np.array([0, 1, 2, 4, 8, 15, 3, 12])
    idx = hand_index(ref)
    # Query frames 0, 1, 2 are refs 3, 4, 5; the centre frame's own address is noisy (0b0110 is
    # unoccupied and falls back to address 4, whose list is {3}), so ref 4 is in no list.
    q = np.array([ref[3], 0b0110, ref[5]], np.uint64)
    paper, n_paper = run(idx, q, [1], L=3)
    aligned, n_aligned = run(idx, q, [1], L=3, aligned=True)
    assert aligned[0] == 4  # ref 3 at offset −1 and ref 5 at +1 both propose centre 4
    assert paper[0] != 4 and n_paper[0] >= 1


def test_out_of_range_reference_frames_cost_delta_max():
    ref = np.array([5, 9, 3, 12, 0, 7])
    idx = hand_index(ref)
    # Window of 3 centred at query frame 1; the query equals refs −1, 0, 1 shifted so centre 0 pays δ_max once.
    q = np.array([15, ref[0], ref[1]], np.uint64)
    match, _ = run(idx, q, [1], L=3)
    assert match[0] == 0
    *_, w, tables, d, k, dmax = idx.kernel_args()
    assert dmax == w[:, 0, 1].sum()


def test_ties_go_to_the_smallest_centre():
    idx = hand_index([7, 7, 7])
    match, n_r = run(idx, [7], [0], L=1)
    assert match[0] == 0 and n_r[0] == 3


def test_online_matches_batch_frame_by_frame():
    rng = np.random.default_rng(5)
    ref = rng.integers(0, 16, 400).astype(np.uint64)
    idx = hand_index(ref)
    truth = np.arange(100, 220)
    q = ref[truth] ^ (rng.random(len(truth)) < 0.2).astype(np.uint64) << rng.integers(0, 4, len(truth)).astype(
        np.uint64)
    for aligned in (False, True):
        for L in (1, 8, 9):
            online = OnlineMatcher(idx, L=L, mode="aligned" if aligned else "paper")
            got, n_rs = [], []
            for h in q:
                got.append(online.push_address(int(h)))
                n_rs.append(online.n_r)
            half = L // 2
            centres = np.arange(half, len(q) - (L - 1 - half))
            batch, batch_nr = run(idx, q, centres, L=L, aligned=aligned)
            if L == 1:  # a single frame's match is its address's single best
                a = idx.nearest_occupied(q)
                batch, batch_nr = plain(idx)["best"][a], np.diff(plain(idx)["offsets"])[a]
            assert got[: L - 1] == [None] * (L - 1)
            np.testing.assert_array_equal(np.array(got[L - 1 :]), batch)
            np.testing.assert_array_equal(np.array(n_rs[L - 1 :]), batch_nr)
            blocks = OnlineMatcher(idx, L=L, mode="aligned" if aligned else "paper")  # blocks of frames: the same
            parts = [blocks.push_addresses(q[a : a + 7]) for a in range(0, len(q), 7)]
            np.testing.assert_array_equal(np.concatenate([m for m, _ in parts]), np.r_[[-1] * (L - 1), batch])
            np.testing.assert_array_equal(np.concatenate([n for _, n in parts])[L - 1 :], batch_nr)


def test_online_matches_index_match_on_every_centre_with_bounded_state(tiny_store, tiny_index):
    """Every frame of a real traverse, both modes: the online matches are the batch matches,
    and the matcher holds the same bytes after 3,000 frames as after 100."""
    import zarr

    idx = Index.load(tiny_index)
    x = zarr.open_group(tiny_store, mode="r")["query_qm1"][47_000:50_000]
    for mode in ("paper", "aligned"):
        online = OnlineMatcher(idx, L=50, mode=mode)
        held = None
        got = []
        for i, row in enumerate(x):
            got.append(online.push(row))
            if i == 100:
                held = online.state_bytes
        match = idx.match(x, 50, mode=mode).match
        np.testing.assert_array_equal(np.array(got[49:]), match)
        assert online.state_bytes == held


def test_online_scores_are_the_batch_scores(tiny_store, tiny_index):
    """With ``return_score``, ``push`` and ``push_many`` give each match the batch's score (the same
    number, in δ_max units), and ``push`` leaves the batch's N_r and best-first list, at L = 1
    (quantisation error and the move to an occupied address) and for sequences in both modes;
    frames that complete no window have none."""
    import zarr

    idx = Index.load(tiny_index)
    x = zarr.open_group(tiny_store, mode="r")["query_qm2"][46_000:47_200]
    for L, mode in ((1, "paper"), (20, "paper"), (50, "aligned")):
        batch = idx.match(x, L, mode=mode)
        one = OnlineMatcher(idx, L=L, mode=mode, n_best=3)
        pushed, n_r, top = [], [], []
        for row in x:
            pushed.append(one.push(row, return_score=True))
            n_r.append(one.n_r)
            top.append(one.top)
        assert pushed[: L - 1] == [None] * (L - 1) and n_r[: L - 1] == [None] * (L - 1)
        np.testing.assert_array_equal([m for m, _ in pushed[L - 1 :]], batch.match)
        np.testing.assert_array_equal([s for _, s in pushed[L - 1 :]], batch.score)
        np.testing.assert_array_equal(n_r[L - 1 :], batch.n_r)
        np.testing.assert_array_equal(top[L - 1 :], idx.match(x, L, mode=mode, n_best=3).top)
        many = OnlineMatcher(idx, L=L, mode=mode)
        parts = [many.push_many(x[a : a + 333], return_score=True) for a in range(0, len(x), 333)]
        match, _, score = (np.concatenate(p) for p in zip(*parts, strict=True))
        np.testing.assert_array_equal(match[L - 1 :], batch.match)
        np.testing.assert_array_equal(score[L - 1 :], batch.score)
        assert np.isnan(score[: L - 1]).all()
        assert len(np.unique(score[L - 1 :])) > 10  # scores that tell matches apart, not a constant


def test_push_and_push_many_share_one_stream(tiny_store, tiny_index):
    """Frames pushed one at a time and in blocks, interleaved, are one traverse: the batch's
    matches; a frame of another width is refused and changes nothing."""
    import zarr

    idx = Index.load(tiny_index)
    x = zarr.open_group(tiny_store, mode="r")["query_qm1"][47_000:47_600]
    for L in (1, 30):
        online = OnlineMatcher(idx, L=L, mode="aligned")
        got = []
        for a in range(0, len(x), 50):
            if a % 100:
                got += list(online.push_many(x[a : a + 50])[0])
            else:
                got += [-1 if m is None else m for m in (online.push(row) for row in x[a : a + 50])]
            with pytest.raises(ValueError, match="a query frame of 95 features; this index hashes frames of 96"):
                online.push(x[a, :95])
        np.testing.assert_array_equal(got[L - 1 :], idx.match(x, L, mode="aligned").match)


def test_baseline_nearest_and_candidate_count():
    x = np.array([0.0, 5.0, 1.0, 1.0, 9.0, 2.0])
    np.testing.assert_array_equal(nearest(x, 1.2, 3, NO_MASK), [2, 3, 5])
    np.testing.assert_array_equal(nearest(x, 1.0, 1, NO_MASK), [2])  # ties: smaller id
    y = np.array([5.1, 0.9, 1.1])
    top, _, counts = baseline_batch(np.array([1]), 3, 2, x, y, float(np.ptp(x)), NO_MASK)
    match = top[:, 0]
    assert counts[0] == 2 and match[0] == 2  # candidates {2, 3}: centre 2 pairs (5,5.1),(1,0.9),(1,1.1)
    m1 = baseline_batch(np.array([0]), 1, 1, x, y, float(np.ptp(x)), NO_MASK)[0][:, 0]
    assert m1[0] == 1


def test_query_centres_keep_whole_windows_with_truth():
    gt = np.array([0, 1, -1, 3, 4, 5, 6, 7, 8, 9, 10])
    c = query_centres(gt.__getitem__, len(gt), len(gt), 2, 1)
    np.testing.assert_array_equal(c.t, [0, 4, 6, 8, 10])
    assert c.fas_stride is None
    np.testing.assert_array_equal(query_centres(gt.__getitem__, len(gt), len(gt), 2, 4).t, [4, 6, 8])  # t−2 … t+1


def test_query_centres_stratify_a_sparse_fas_part():
    """10M-like: the common stride leaves 3 FAS centres; the FAS part gets a stride of its own."""
    n_deep, n_fas, z = 100_000, 2_700, 1_000
    gt = np.r_[np.arange(n_deep), n_deep + np.arange(n_fas)]
    gt[n_deep + 5 :: 7] = -1  # some FAS frames have no truth
    c = query_centres(gt.__getitem__, len(gt), n_deep, z, 100)
    deep, fas = c.t[c.t < n_deep], c.t[c.t >= n_deep]
    np.testing.assert_array_equal(deep, np.arange(z, n_deep, z))  # t = 0 has no whole window
    assert len(fas) >= MIN_FAS and c.fas_stride is not None and c.fas_stride < z
    assert (gt[fas] >= 0).all() and (fas + 50 <= len(gt)).all()
    assert ((fas - n_deep) % c.fas_stride == 0).all()
    coarser = np.arange(n_deep, len(gt), c.fas_stride + 1)
    coarser = coarser[(gt[coarser] >= 0) & (coarser + 50 <= len(gt))]
    assert len(coarser) < MIN_FAS  # the largest stride that gives enough
    w = part_weights(len(gt), n_deep)
    assert w["deep1b"] + w["fas"] == pytest.approx(1) and w["fas"] == pytest.approx(n_fas / len(gt))


def test_recall_at_each_radius():
    curve = recall_curve(np.array([0, 3, 20, 21]))
    assert curve[0] == 0.25 and curve[2] == 0.25 and curve[3] == 0.5 and curve[20] == 0.75
    assert len(curve) == 21


@pytest.mark.parametrize("L", [1, 3])
def test_baseline_respects_n_r(L):
    x = np.linspace(0, 1, 50)
    y = np.linspace(0, 1, 50)
    _, _, counts = baseline_batch(np.array([10, 20]), L, 7, x, y, 1.0, NO_MASK)
    np.testing.assert_array_equal(counts, [7, 7])


def brute_force_match(idx: Index, q_hash, t, L, aligned):
    """The definition (SPEC §3.3), term by term in Python: candidates, scores, smallest best."""
    w = idx.weights()
    dmax = int(w[:, 0, -1].sum())
    digits = [idx.k ** (idx.d - 1 - j) for j in range(idx.d)]

    def delta(h1, h2):
        return sum(int(w[j, int(h1) // p % idx.k, int(h2) // p % idx.k]) for j, p in enumerate(digits))

    q_addr = idx.nearest_occupied(np.asarray(q_hash, np.uint64))
    arrays = plain(idx)
    half = L // 2
    cands = set()
    for i in range(L):
        a = q_addr[t + i - half]
        for r in arrays["ids"][arrays["offsets"][a]:arrays["offsets"][a + 1]]:
            c = int(r) - (i - half) if aligned else int(r)
            if 0 <= c < idx.n_ref:
                cands.add(c)
    scores = {c: sum(delta(arrays["ref_hash"][c + i - half], q_hash[t + i - half]) if 0 <= c + i - half < idx.n_ref
                     else dmax for i in range(L)) for c in cands}
    return min(scores, key=lambda c: (scores[c], c)), len(cands)


@pytest.mark.parametrize(("d", "k", "L"), [(6, 2, 5), (10, 2, 64), (10, 2, 100), (7, 2, 129), (4, 3, 9)])
@pytest.mark.parametrize("aligned", [False, True])
def test_batch_kernel_equals_the_definition(d, k, L, aligned):
    """Bit-plane scoring (K = 2, windows of any length, both ends of the map) and frame-by-frame
    scoring (K = 3) give the definition's match and candidate count for every centre."""
    rng = np.random.default_rng(d * 100 + L)
    n_ref, n_q = 300, 2 * L + 20
    ref = rng.integers(0, k**d, n_ref).astype(np.uint64)
    centres = np.tile(np.linspace(-1.0, 1.0, k), (d, 1)) * rng.uniform(0.5, 2.0, (d, 1))
    idx = hand_index(ref, centres)
    truth = rng.integers(0, n_ref - n_q)
    q = ref[truth:truth + n_q].copy()
    noisy = rng.random(n_q) < 0.3
    q[noisy] = rng.integers(0, k**d, noisy.sum()).astype(np.uint64)
    t = np.array([L // 2, n_q // 2, n_q - (L - L // 2)])
    match, n_r = run(idx, q, t, L, aligned)
    for i, ti in enumerate(t):
        assert (match[i], n_r[i]) == brute_force_match(idx, q, ti, L, aligned)
    # windows that reach past either end of the map: centres near 0 and near n_ref
    edge_q = np.concatenate([ref[:L], ref[-L:]])
    te = np.array([L // 2, 2 * L - (L - L // 2)])
    match, n_r = run(idx, edge_q, te, L, aligned)
    for i, ti in enumerate(te):
        assert (match[i], n_r[i]) == brute_force_match(idx, edge_q, ti, L, aligned)


def test_batches_do_not_depend_on_blocks_threads_or_batch_size():
    """More queries than one block of pairs, over a map of several sort buckets: the same
    matches in one call on every thread, on one thread, and query by query."""
    import numba

    from vprscale.method.kernels import QUERY_BLOCK

    rng = np.random.default_rng(11)
    d, L = 10, 9
    ref = rng.integers(0, 2**d, 20_000).astype(np.uint64)
    idx = hand_index(ref, np.tile([[-1.0, 1.0]], (d, 1)) * rng.uniform(0.5, 2.0, (d, 1)))
    start = rng.integers(0, len(ref) - 3_000, 8)
    q = np.concatenate([ref[s:s + 3_000] ^ (rng.random(3_000) < 0.2).astype(np.uint64) for s in start])
    centres = np.sort(rng.integers(L // 2, len(q) - L // 2, QUERY_BLOCK + 700))
    match, n_r = run(idx, q, centres, L)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        one_thread = run(idx, q, centres, L)
    finally:
        numba.set_num_threads(threads)
    np.testing.assert_array_equal(one_thread[0], match)
    np.testing.assert_array_equal(one_thread[1], n_r)
    for i in rng.choice(len(centres), 12, replace=False):
        alone = run(idx, q, centres[i:i + 1], L)
        assert (alone[0][0], alone[1][0]) == (match[i], n_r[i]) == brute_force_match(idx, q, centres[i], L, False)


def test_blocks_split_by_proposals_give_the_same_matches():
    """Long lists (d = 3 over 40,000 places): 127 queries propose more pairs than one block
    holds, so the batch is split by proposals; each query's match and N_r are those it gets alone."""
    from vprscale.method.kernels import PAIR_BUDGET

    rng = np.random.default_rng(3)
    ref = rng.integers(0, 8, 40_000).astype(np.uint64)
    idx = hand_index(ref, np.tile([[-1.0, 1.0]], (3, 1)) * np.array([[1.0], [0.7], [0.4]]))
    q = ref[5_000:5_400] ^ (rng.random(400) < 0.1).astype(np.uint64)
    centres = np.arange(10, 390, 3)
    sizes = idx.query_frames(q).stop - idx.query_frames(q).start
    assert sum(sizes[c - 4:c + 5].sum() for c in centres) > PAIR_BUDGET
    match, n_r = run(idx, q, centres, L=9)
    for i in (0, len(centres) // 2, len(centres) - 1):
        alone = run(idx, q, centres[i:i + 1], L=9)
        assert (alone[0][0], alone[1][0]) == (match[i], n_r[i])


def test_frames_sharing_long_lists_share_their_copies(monkeypatch):
    """A coarse index's frames mostly share a few long lists: beyond the limit each is decoded
    once and shared, and the matches are those of the lists copied frame by frame."""
    import vprscale.method.invlists as invlists

    rng = np.random.default_rng(8)
    ref = rng.integers(0, 64, 3_000).astype(np.uint64)
    idx = hand_index(ref, np.tile([[-1.0, 1.0]], (6, 1)))
    q = ref[1_000:1_300] ^ (rng.random(300) < 0.2).astype(np.uint64)
    centres = np.arange(10, 290, 7)
    copied = run(idx, q, centres, L=15, aligned=True)
    assert len(idx.query_frames(q).ids) == sum(len(idx.lists.list_ids(a)) for a in idx.query_frames(q).slot)
    monkeypatch.setattr(invlists, "SHARED_ABOVE", 0)
    qf = idx.query_frames(q)
    assert len(qf.ids) == sum(len(idx.lists.list_ids(a)) for a in np.unique(qf.slot))
    for i in range(0, 300, 37):
        np.testing.assert_array_equal(qf.ids[qf.start[i]:qf.stop[i]], idx.lists.list_ids(qf.slot[i]))
    shared = run(idx, q, centres, L=15, aligned=True)
    np.testing.assert_array_equal(shared[0], copied[0])
    np.testing.assert_array_equal(shared[1], copied[1])


def test_pairs_sorted_by_window_score_as_in_query_order():
    """The window-ordered pair sort (used for maps larger than the caches) is a stable
    bucket sort of the pairs, and scoring them in that order gives the query-order answer."""
    from vprscale.method.kernels import (
        _pairs_by_window,
        _query_words,
        _score_pairs,
        count_proposals,
        propose,
        score_window,
    )

    rng = np.random.default_rng(4)
    d, L = 10, 9
    ref = rng.integers(0, 2**d, 20_000).astype(np.uint64)
    idx = hand_index(ref, np.tile([[-1.0, 1.0]], (d, 1)) * rng.uniform(0.5, 2.0, (d, 1)))
    q = ref[7_000:9_000] ^ (rng.random(2_000) < 0.2).astype(np.uint64)
    qf = idx.query_frames(q)
    t = np.arange(L // 2, 2_000 - L // 2, 5)
    hashes, q_planes, start, stop, ids = qf.kernel_args()
    codes, code_bits, n_ref, planes, gaps, w, tables, d, k, dmax = idx.kernel_args()
    proposals = count_proposals(t, L, start, stop)
    in_order, by_window = (_pairs_by_window(*propose(t, L, False, start, stop, ids, len(ref), proposals, shift,
                                                     NO_MASK), shift)
                           for shift in (62, 12))
    cand, first, n_r, _ = propose(t, L, False, start, stop, ids, len(ref), proposals, 62, NO_MASK)
    expected = np.concatenate([(cand[first[i]:first[i] + n_r[i]] << 20) | i for i in range(len(t))])
    np.testing.assert_array_equal(in_order, expected)
    np.testing.assert_array_equal(by_window, expected[np.argsort(expected >> 32, kind="stable")])
    words = _query_words(t, L, q_planes, d)
    answers = [_score_pairs(p, t, L, hashes, words, codes, code_bits, n_ref, planes, gaps, w, tables, d, k, dmax, True,
                            5, runs)
               for p, runs in ((in_order, 16), (by_window, 3))]
    np.testing.assert_array_equal(answers[0][0], answers[1][0])
    np.testing.assert_array_equal(answers[0][1], answers[1][1])
    np.testing.assert_array_equal(answers[0][0][:, 0], run(idx, q, t, L)[0])
    # the five best are every candidate's full score, sorted (ties to the smaller centre)
    for i in range(0, len(t), 37):
        c = cand[first[i]:first[i] + n_r[i]]
        full = np.array([score_window(x, t[i], L, L // 2, codes, code_bits, n_ref, hashes, w, tables, d, k, dmax, 2**62)
                         for x in c])
        order = np.lexsort((c, full))[:5]
        np.testing.assert_array_equal(answers[0][0][i, : len(order)], c[order])
        np.testing.assert_array_equal(answers[0][1][i, : len(order)], full[order])


def test_query_frames_hold_only_the_frames_worked_on():
    ref = np.array([1, 2, 4, 8, 1, 2, 4, 8, 3, 5, 6, 9, 12, 10, 7, 11])
    idx = hand_index(ref)
    frames = np.r_[100:105, 200:210]
    q = idx.query_frames(ref[np.r_[8:13, 0:10]], frames)
    np.testing.assert_array_equal(q.positions(np.array([102, 205]), 5), [2, 10])
    match = match_batch(q.positions(np.array([102]), 5), 5, False, *q.kernel_args(), *idx.kernel_args(),
                        *ONE_BEST)[0][:, 0]
    assert match[0] == 10  # frames 100…104 repeat refs 8…12
    a = q.slot[0]
    np.testing.assert_array_equal(q.ids[q.start[0]:q.stop[0]], idx.lists.list_ids(a))
    with pytest.raises(ValueError, match="frame 103"):
        q.positions(np.array([103]), 5)  # its window reaches frame 105, which was not worked on


@pytest.mark.parametrize(("d", "k"), [(20, 2), (5, 3)])
def test_nearest_occupied_equals_a_full_scan(d, k):
    rng = np.random.default_rng(d)
    idx = hand_index(rng.integers(0, k**d, 500).astype(np.uint64), np.tile(np.linspace(-1, 1, k), (d, 1)))
    addresses = plain(idx)["addresses"]
    h = np.r_[rng.integers(0, k**d, 2000), addresses[:50], 0, k**d - 1].astype(np.uint64)
    a = addresses.astype(np.int64)
    gap = np.abs(a[None, :] - h.astype(np.int64)[:, None])
    np.testing.assert_array_equal(idx.nearest_occupied(h), gap.argmin(axis=1))  # argmin: first, i.e. smaller


def test_localise_command_streams_a_store_array_and_an_npy(tiny_store, tiny_index, tmp_path, capsys):
    import pyarrow.parquet as pq
    import zarr

    from vprscale.cli import main

    x = zarr.open_group(tiny_store, mode="r")["query_qm1"][48_000:49_000]
    np.save(tmp_path / "q.npy", x)
    assert main(["localise", str(tiny_index), str(tmp_path / "q.npy"), "--L", "50", "--mode", "aligned",
                 "--out", str(tmp_path / "m.parquet"), "--top", "4"]) == 0
    t = pq.read_table(tmp_path / "m.parquet").to_pandas()
    assert len(t) == 1000 and t["match"].isna().sum() == 49
    found = Index.load(tiny_index).match(x, 50, mode="aligned", n_best=4)
    match = found.match
    top = t[[f"top_{j}" for j in range(1, 5)]].dropna(how="all").fillna(-1).to_numpy(np.int64)
    np.testing.assert_array_equal(top, found.top)  # the batch's ranking, best first
    np.testing.assert_array_equal(found.centres, np.arange(25, 1000 - 24))
    np.testing.assert_array_equal(t["match"].dropna().to_numpy(np.int64), match)
    np.testing.assert_array_equal(t["centre"].dropna().to_numpy(np.int64), np.arange(25, 1000 - 24))
    assert main(["localise", str(tiny_index), str(tiny_store / "query_qm2"), "--L", "5", "--out",
                 str(tmp_path / "s.parquet")]) == 0
    assert pq.read_metadata(tmp_path / "s.parquet").num_rows == 52_000
    np.save(tmp_path / "bad.npy", x[:, :7])
    capsys.readouterr()
    assert main(["localise", str(tiny_index), str(tmp_path / "bad.npy")]) == 2
    assert "bad.npy: frames of 7 features; the index hashes frames of 96" in capsys.readouterr().err


@pytest.mark.parametrize(("d", "n"), [(26, 1000), (30, 200_000)])
def test_nearest_occupied_through_the_directory_equals_brute_force(d, n):
    rng = np.random.default_rng(d)
    occupied = np.unique(rng.integers(0, 2**d, n, dtype=np.uint64))
    idx = hand_index(occupied, np.tile([[-1.0, 1.0]], (d, 1)))
    h = np.r_[rng.integers(0, 2**d, 3000, dtype=np.uint64), occupied[:50], occupied[-5:] + np.uint64(1)]
    got = plain(idx)["addresses"][idx.nearest_occupied(h)]
    below = occupied[np.clip(np.searchsorted(occupied, h, "right") - 1, 0, None)]
    above = occupied[np.clip(np.searchsorted(occupied, h), None, len(occupied) - 1)]
    dist_below = np.where(below <= h, h - below, np.uint64(2**63))
    dist_above = np.where(above >= h, above - h, np.uint64(2**63))
    np.testing.assert_array_equal(got, np.where(dist_below <= dist_above, below, above))  # ties: the smaller


@pytest.mark.parametrize(("L", "mode"), [(1, "paper"), (30, "paper"), (30, "aligned")])
def test_online_best_candidates_are_the_batch_ranking(tiny_store, tiny_index, L, mode):
    """A matcher keeping its 6 best candidates a window gives the batch's ``top`` frame by frame and
    in blocks, pushes of both kinds interleaved; the first of them is the match."""
    import zarr

    idx = Index.load(tiny_index)
    x = zarr.open_group(tiny_store, mode="r")["query_qm1"][46_000:46_500]
    batch = idx.match(x, L, mode=mode, n_best=6)
    online = OnlineMatcher(idx, L=L, mode=mode, n_best=6)
    got = []
    for a in range(0, len(x), 40):
        if a % 80:
            match, _, top = online.push_many(x[a : a + 40], return_top=True)
            got += [t for m, t in zip(match, top, strict=True) if m >= 0]
            assert (top[match < 0] == -1).all()
        else:
            for row in x[a : a + 40]:
                if online.push(row) is not None:
                    got.append(online.top)
    np.testing.assert_array_equal(np.array(got), batch.top)
    np.testing.assert_array_equal(batch.top[:, 0], batch.match)
    assert (batch.top[:, 1] >= 0).any()  # lists with a second candidate: the ranking is exercised
    with pytest.raises(ValueError, match="n_best 0"):
        OnlineMatcher(idx, L=L, mode=mode, n_best=0)
