"""FAISS's codes scored by vprscale on small random data, form by form (docs/protocol.md): window
scores from each code's tables equal those of its decoded vectors, its table terms are FAISS's own
distances, residual IVF-PQ bounds keep the exact best, and the 2024-26 codes (RaBitQ, the additive
quantisers, HNSW) answer as FAISS itself whatever the chunks. test_compare holds the evaluations
of the tiny store; these need no store, so they run beside it.
"""

from __future__ import annotations

import faiss
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from threadpoolctl import threadpool_limits

from vprscale.compared import rabitq
from vprscale.compared.codescore import REF_LEVEL_BYTES, _smallest, score_windows
from vprscale.compared.faisscodes import ENCODE_ROWS, FaissCodes, FrameTerms, _plain_twin, _read_only, training_rows
from vprscale.core.errors import InputError

from .conftest import faiss_own


@pytest.mark.parametrize("factory, form", [("IVF16,PQ4", "residual"), ("IVF256,PQ4np", "residual"),
                                           ("IVF300,PQ4np", "residual"), ("OPQ3_30,IVF300,PQ3np", "residual"),
                                           ("OPQ4,IVF16,PQ4x6", "residual"),
                                           ("OPQ4,PQ4np", "tables"), ("PQ4x6", "tables"), ("PQ8x4fs", "tables"),
                                           ("OPQ8,PQ8x4fs", "tables"), ("PQ1x4", "tables")])
def test_table_scores_equal_decoded_vector_scores(factory, form):
    """Every candidate's window score from the tables (IVF-PQ: coarse distance + per-list term +
    frame table) equals, to float rounding, the sum of squared distances to the decoded codes."""
    rng = np.random.default_rng(3)
    ref = np.cumsum(rng.standard_normal((4000, 32)), axis=0).astype(np.float32) * 0.1
    query = ref[1000:1200] + rng.standard_normal((200, 32)).astype(np.float32) * 0.05
    codes = FaissCodes(factory, 32, k=8)
    for rotation in (t for t in codes.chain if isinstance(t, faiss.OPQMatrix)):
        rotation.niter = 4  # of FAISS's 50 (5 s a code here): the scores of any rotation are the subject
    codes.train(ref)
    codes.start(len(ref))
    for i in range(0, len(ref), 1500):
        codes.encode(ref[i : i + 1500])
    codes.finish()
    assert codes.form == form
    decoded = codes.inner.sa_decode(codes.inner.sa_encode(codes._transform(ref)))
    terms = codes.frame_terms(query)
    L, centres = 15, np.array([20, 90, 150])
    cand = np.concatenate([np.arange(900, 1300), np.arange(0, 40), np.arange(3980, 4000)]).astype(np.int64)
    first, n_r = np.arange(3) * len(cand), np.full(3, len(cand))
    both = []
    for t, vectors, codes_arg in ((terms, np.zeros((0, 0), np.float32), codes.codes),
                                  (FrameTerms(np.zeros((0, 1, 1), np.float32), codes._transform(query)), decoded,
                                   np.zeros((0, 1), np.uint8))):
        top, scores = _score(codes, t, centres, L, np.tile(cand, 3), first, n_r, len(cand), codes_arg, vectors)
        both.append({(q, int(c)): s for q in range(3) for c, s in zip(top[q], scores[q], strict=True)})
    assert both[0].keys() == both[1].keys() and len(both[0]) == 3 * len(cand)
    got, want = (np.array([b[key] for key in sorted(both[0])]) for b in both)
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=1e-6 * want.max())


def _fitted(factory: str, seed: int) -> tuple[FaissCodes, np.ndarray, np.ndarray]:
    """``factory`` trained on and holding 4,000 rows about their mean (as whitened descriptors lie),
    and 40 query rows near some of them; k = 8, nprobe = 16."""
    rng = np.random.default_rng(seed)
    ref = rng.standard_normal((4000, 32)).astype(np.float32)
    query = ref[1000:1040] + rng.standard_normal((40, 32)).astype(np.float32) * 0.3
    codes = FaissCodes(factory, 32, k=8, nprobe=16)
    codes.train(ref)
    codes.start(len(ref))
    codes.encode(ref)
    codes.finish()
    return codes, ref, query


def _one_frame_scores(codes: FaissCodes, query: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One-frame window scores of each query row's places ``ids``, flattened: ``(places, scores)``;
    each place is its own window's match."""
    cand = ids.reshape(-1)
    centres = np.repeat(np.arange(len(query)), ids.shape[1])
    top, scores = codes.score(centres, 1, cand, np.arange(len(cand)), np.ones(len(cand), np.int64),
                              codes.frame_terms(query))
    np.testing.assert_array_equal(top[:, 0], cand)
    return cand, scores[:, 0]


@pytest.mark.parametrize("factory, form", [("RQ3x8_Nqint8", "tables"), ("LSQ4x5_Nqint4", "tables"),
                                           ("PRQ2x2x4_Nqint8", "tables"), ("RQ2x8_Ncqint8", "tables"),
                                           ("IVF16,RQ3x8_Nqint8", "residual"),
                                           ("OPQ4,IVF16,PLSQ2x2x6_Nqint8", "residual"),
                                           ("RaBitQ", "factors"), ("IVF16,RaBitQ", "factors"),
                                           ("PCA16,IVF16,RaBitQ", "factors"), ("IVF1,RaBitQ", "factors")])
def test_table_terms_are_faiss_own_distances(factory, form):
    """An additive quantiser that keeps its norm in the code is scored from tables, one per
    codebook and one for the norm's levels (over an inverted file: the frame's coarse distance,
    the list's term and the frame's tables); RaBitQ from byte tables of its signs, its two
    factors and the frame's distance to the code's centre. Each term is the distance FAISS's
    own search ranks by (the quantised norm, not the decoded vector's; RaBitQ's estimator,
    with the frame unquantised: ``qb = 0``), for the places FAISS returns, and a window's
    score is the sum of its terms."""
    codes, ref, query = _fitted(factory, 4)
    assert codes.form == form
    if form == "factors":
        codes.inner.qb = 0
    distances, ids = codes.search(query)
    assert (distances > 0).mean() > 0.9  # distances, not RaBitQ's estimates clipped at 0
    terms = codes.frame_terms(query)
    cand = ids.reshape(-1)
    centres = np.repeat(np.arange(len(query)), ids.shape[1])
    first, n_r = np.arange(len(cand)), np.ones(len(cand), np.int64)
    top, scores = codes.score(centres, 1, cand, first, n_r, terms)
    np.testing.assert_array_equal(top[:, 0], cand)
    # both sum float32 terms of the size of ‖y‖² and ‖x‖² to a far smaller distance
    rounding = 1e-6 * ((query**2).sum(axis=1).max() + (ref**2).sum(axis=1).max())
    np.testing.assert_allclose(scores[:, 0], distances.reshape(-1), rtol=1e-5, atol=rounding)
    # a window of 5 frames: the sum of its terms, each a one-frame window's
    L, t, c = 5, np.array([20]), np.array([1020], np.int64)
    window = codes.score(t, L, c, np.zeros(1, np.int64), np.ones(1, np.int64), terms)[1][0, 0]
    singles = [codes.score(np.array([20 + i]), 1, np.array([1020 + i], np.int64), np.zeros(1, np.int64),
                           np.ones(1, np.int64), terms)[1][0, 0] for i in range(-2, 3)]
    np.testing.assert_allclose(window, sum(singles), rtol=1e-9)


@pytest.mark.parametrize("factory, form", [("IVF16,PQ8x4fsr", "residual"), ("IVF16,PQ8x4fs", "tables")])
def test_ivf_fast_scan_pq_is_scored_from_tables(factory, form):
    """FAISS's IVF fast-scan PQ searches 8-bit quantised tables, but its codes are an IVF-PQ's
    (of the residuals, ``…fsr``, or of the rows, ``…fs``): the windows read them from tables,
    as residual records or as product codes with the list number aside (FAISS cannot decode
    them: its ``sa_decode`` crashes), each term the exact ``‖y − x̂‖²`` of the place FAISS's
    search returned."""
    codes, ref, query = _fitted(factory, 5)
    assert codes.form == form and not codes.records_on_disk
    plain = faiss.IndexIVFPQ(codes.inner.quantizer, 32, 16, 8, 4)
    plain.pq, plain.by_residual, plain.is_trained = codes.inner.pq, codes.inner.by_residual, True
    decoded = plain.sa_decode(codes.inner.sa_encode(ref))
    _, ids = codes.search(query)
    assert (ids >= 0).all()
    cand, scores = _one_frame_scores(codes, query, ids)
    exact = ((np.repeat(query, ids.shape[1], axis=0).astype(np.float64) - decoded[cand]) ** 2).sum(axis=1)
    np.testing.assert_allclose(scores, exact, rtol=1e-5, atol=1e-4)

@pytest.mark.parametrize("factory", ["IVF16,RQ4x4fs_Nrq2x4", "RQ4x4fs_Nrq2x4", "IVF16,LSQ4x4fs_Nlsq2x4",
                                     "IVF16,PRQ2x2x4fs_Nrq2x4"])
def test_fast_scan_additive_codes_are_scored_from_tables(factory):
    """FAISS's fast-scan additive quantisers search 8-bit quantised tables and leave ``‖y‖²`` out
    of their distances; their codes are plain additive codes with a 2x4-bit norm. The windows
    read them from float tables (the list number aside), each term the distance the plain
    index over the same codes ranks by (float tables, the quantised norm), and the search's
    distances get ``‖y‖²`` back: FAISS's ranking, distances comparable across frames."""
    codes, ref, query = _fitted(factory, 6)
    assert codes.form == "tables" and codes.codes.shape == (len(ref), codes.subs.columns)
    plain = _plain_twin(codes.inner)  # the same codes, searched with float tables
    standalone = codes.inner.sa_encode(ref)
    if codes.ivf is not None:
        plain.add_sa_codes(standalone, np.arange(len(ref)))
        plain.nprobe = 16
    else:
        plain.add_sa_codes(standalone)
    plain_dist, plain_ids = plain.search(query, 8)
    dist, ids = codes.search(query)
    assert (np.isin(ids, plain_ids).mean()) > 0.8  # the 8-bit tables rank nearly as the float ones
    fs_dist = codes.searched.search(query, 8)[0]
    np.testing.assert_allclose(dist, fs_dist + (query.astype(np.float64) ** 2).sum(axis=1)[:, None], rtol=1e-6)
    _, scores = _one_frame_scores(codes, query, plain_ids)
    rounding = 1e-6 * ((query**2).sum(axis=1).max() + (ref**2).sum(axis=1).max())
    np.testing.assert_allclose(scores, plain_dist.reshape(-1), rtol=1e-5, atol=rounding)


@pytest.mark.parametrize("factory", ["IVF16,RQ4x4fsr_Nrq2x4", "IVF16,PRQ2x2x4fsr_Nrq2x4"])
def test_residual_fast_scan_additive_codes_are_scored_from_residual_tables(factory):
    """A residual fast-scan additive code keeps the residual's codebooks and the whole vector's
    norm: its windows read residual records whose list term is ``‖x̂‖² − ‖c_l‖²``, and a term is
    ``‖y‖² − 2⟨y, x̂⟩ + ‖x̂‖²`` with FAISS's own reconstruction ``x̂`` and the code's norm, for the
    places FAISS's search returns (whose 8-bit tables give nearly the same distances)."""
    codes, ref, query = _fitted(factory, 7)
    assert codes.form == "residual"
    dist, ids = codes.search(query)
    cand, scores = _one_frame_scores(codes, query, ids)
    standalone = codes.inner.sa_encode(ref[cand])
    decoded = codes.inner.sa_decode(standalone).astype(np.float64)
    norm = codes.subs.norms[codes.subs.indices(standalone[:, codes.ivf.coarse_code_size() :])[:, -1]]
    y = np.repeat(query, ids.shape[1], axis=0).astype(np.float64)
    exact = (y**2).sum(axis=1) - 2 * (y * decoded).sum(axis=1) + norm
    np.testing.assert_allclose(scores, exact, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(dist.reshape(-1), exact, rtol=0.05)  # FAISS's 8-bit tables


def test_coarse_levels_are_numpys_levels_row_by_row():
    """The compiled levels, lows and highs of ``g = coarse + ref_base`` are numpy's on the whole
    array, bit for bit, and a constant row (a step of 0) all level 0."""
    from vprscale.compared.codescore import _levels

    rng = np.random.default_rng(8)
    coarse = (rng.standard_normal((300, 500)) ** 2 * 50).astype(np.float32)
    ref_base = rng.standard_normal(500) * 3
    g = coarse.astype(np.float64) + ref_base[None, :]
    low, high = g.min(axis=1), g.max(axis=1)
    step = (high - low) / 256
    want = np.minimum(np.floor((g - low[:, None]) / np.where(step > 0, step, 1)[:, None]), 255).astype(np.uint8)
    for got, expected in zip(_levels(coarse, ref_base), (want, low, high), strict=True):
        np.testing.assert_array_equal(got, expected)
    assert len(np.unique(want)) == 256
    flat, low, high = _levels(np.full((2, 5), 3.0, np.float32), np.zeros(5))  # a step of 0: every level 0
    assert (flat == 0).all() and (low == 3.0).all() and (high == 3.0).all()


@pytest.mark.parametrize("dim", [5, 21, 96, 128, 200])
def test_rabitq_records_hold_the_factors_numpy_gives(dim):
    """A record's ``F = A + 2 D ⟨s, c⟩ / √d`` is the float32 of numpy's own sum of the signed
    centre (the bits of the definition, compiled or not), its ``D`` and signs as stored."""
    rng = np.random.default_rng(dim)
    n, nb, lists = 500, rabitq.sign_bytes(dim), rng.integers(0, 300, 500)
    codes = np.zeros((n, 2 + nb + rabitq.FACTOR_BYTES), np.uint8)
    codes[:, 0], codes[:, 1] = lists & 255, lists >> 8
    codes[:, 2 : 2 + nb] = rng.integers(0, 256, (n, nb))
    factors = rng.standard_normal((n, 2)).astype(np.float32)
    codes[:, 2 + nb :] = factors.view(np.uint8)
    centres = rng.standard_normal((300, dim)) * 10.0 ** rng.integers(-3, 3, (300, dim))
    signs = np.where(np.unpackbits(codes[:, 2 : 2 + nb], axis=1, bitorder="little")[:, :dim], 1.0, -1.0)
    e = (signs * centres[lists]).sum(axis=1) / np.sqrt(dim)
    want = np.stack([factors[:, 0] + 2 * factors[:, 1].astype(np.float64) * e, factors[:, 1]], axis=1)
    got = rabitq.records(codes, dim, 2, centres)
    np.testing.assert_array_equal(got[:, -rabitq.FACTOR_BYTES :].view(np.float32), want.astype(np.float32))
    np.testing.assert_array_equal(got[:, :nb], codes[:, 2 : 2 + nb])
    if dim <= rabitq.PAIRWISE_BLOCK:  # the compiled sums themselves, to the last bit of float64
        sums = rabitq._signed_sums(np.ascontiguousarray(codes[:, 2 : 2 + nb]), lists, centres, dim)
        np.testing.assert_array_equal(sums, (signs * centres[lists]).sum(axis=1))


def test_rabitq_sign_tables_are_the_signed_sums_block_by_block():
    """``T_b[v] = Σ_i s_i(v) y[8b + i] / √d``, term by term, for every frame, byte and value
    (a width that is not a whole number of bytes; frames across blocks; values 10^±6 apart)."""
    rng = np.random.default_rng(3)
    y = (rng.standard_normal((37, 21)) * 10.0 ** rng.integers(-6, 6, (37, 21))).astype(np.float32)
    tables = rabitq.sign_tables(y, block=8)
    assert tables.shape == (37, 3, 256) and tables.dtype == np.float32
    for n in (0, 9, 36):
        for b in range(3):
            for v in (0, 1, 128, 255, 77):
                want = sum((1.0 if v >> i & 1 else -1.0) * float(y[n, 8 * b + i]) for i in range(8) if 8 * b + i < 21)
                assert tables[n, b, v] == np.float32(want / np.sqrt(21)), (n, b, v)
    np.testing.assert_array_equal(tables, rabitq.sign_tables(y))  # the same bytes whatever the block


@pytest.mark.parametrize("factory", ["RQ3x8", "IVF16,RQ2x8_Nfloat", "LSQ2x8_Nfloat", "RaBitQ4"])
def test_codes_without_tables_are_decoded(factory):
    """An additive quantiser without its norm in the code (FAISS decodes it to search) or with
    a float32 norm has no per-index tables, nor has a RaBitQ code of extended bits: their windows
    read decoded vectors."""
    assert FaissCodes(factory, 32, k=8).form == "vectors"


def _score(codes: FaissCodes, t: FrameTerms, centres, L, cand, first, n_r, n_best, codes_arg=None, vectors=None):
    """:func:`score_windows` of ``codes`` with frame terms ``t`` (its own codes unless others are given)."""
    codes_arg = codes.codes if codes_arg is None else codes_arg
    vectors = np.zeros((0, 0), np.float32) if vectors is None else vectors
    return score_windows(centres, L, cand, first, n_r, codes.n_ref, t.tables, t.levels, t.scale, codes.per_list,
                         _read_only(codes_arg), t.vectors, _read_only(vectors), codes.centroids, n_best)



@settings(max_examples=200, deadline=None)
@given(st.lists(st.sampled_from([0.0, 1.0, 1.5, 2.0, -3.0, np.inf]), min_size=1, max_size=30), st.data())
def test_smallest_is_a_stable_sort_prefix(values, data):
    """A window's bar and best lower bounds: the n smallest values, ties (and infinities) to
    the smaller index, as a stable sort's first n."""
    values = np.array(values)
    n = data.draw(st.integers(1, len(values)))
    np.testing.assert_array_equal(_smallest(values, n), np.argsort(values, kind="stable")[:n])


@pytest.mark.parametrize("spread", ["data", "one far list", "flat rows"])
@pytest.mark.parametrize("factory, dim", [("IVF256,PQ2np", 16), ("IVF300,PQ3np", 18)])
def test_residual_best_from_coarse_levels_are_the_exact_best(spread, factory, dim):
    """IVF-PQ windows bound their candidates from 8-bit levels of each frame's distances to
    the lists and of each place's term, and score exactly only those that could be among the
    best: the best few are the exact scoring's, score for score (its scores of every
    candidate, asked for all of them), however coarse the levels are (a list centroid far
    from the rest makes every step wide; equal ones make them zero); for records of one
    list byte and of two with three code bytes (the bounds' loop specialised to them), in
    windows that reach outside the map and windows that do not (a loop of their own)."""
    rng = np.random.default_rng(5)
    ref = np.cumsum(rng.standard_normal((3000, dim)), axis=0).astype(np.float32) * 0.1
    query = ref[500:800] + rng.standard_normal((300, dim)).astype(np.float32) * 0.05
    codes = FaissCodes(factory, dim, k=4)
    codes.train(ref)
    codes.start(len(ref))
    codes.encode(ref)
    codes.finish()
    if spread == "one far list":
        codes.centroids[7] += 100
    elif spread == "flat rows":
        codes.centroids[:] = codes.centroids[0]
    terms = codes.frame_terms(query)
    L, centres = 21, np.array([15, 100, 200, 284])  # the first and last windows reach outside the map
    cand = np.unique(np.concatenate([np.arange(480, 540), np.arange(0, 12), np.arange(2990, 3000),
                                     rng.integers(0, 3000, 60)]))
    inside = cand[(cand >= L) & (cand < len(ref) - L)]  # windows of no reference outside the map
    for some in (cand, cand[::40], inside):  # many candidates, few, and none at the map's ends
        first, n_r = np.arange(4) * len(some), np.full(4, len(some))
        every = _score(codes, terms, centres, L, np.tile(some, 4), first, n_r, len(some) + 20)
        assert np.isfinite(every[1][:, : len(some)]).all()
        for n_best in (1, 3, 20):
            top, scores = _score(codes, terms, centres, L, np.tile(some, 4), first, n_r, n_best)
            np.testing.assert_array_equal(top, every[0][:, :n_best])
            np.testing.assert_array_equal(scores, every[1][:, :n_best])


def _trained_and_encoded(codes: FaissCodes, train: np.ndarray, ref: np.ndarray, block: int) -> FaissCodes:
    """``codes`` trained on ``train`` as a job trains them (BLAS on one thread) and holding ``ref``,
    given in chunks of ``block`` rows."""
    with threadpool_limits(limits=1, user_api="blas"):
        codes.train(train)
    codes.start(len(ref))
    for lo in range(0, len(ref), block):
        codes.encode(ref[lo : lo + block])
    codes.finish()
    return codes


@pytest.mark.parametrize("factory", ["RaBitQfs", "IVF16,RaBitQfs", "IVF16,PQ4x4fs", "IVF16,RaBitQ", "LSQ2x8",
                                     "PRQ2x2x6", "IVF16,RQ4x4fs_Nrq2x4", "IVF16,LSQ2x4fsr_Nlsq2x4", "HNSW16",
                                     "PCA8,HNSW16"])
def test_new_codes_answer_as_faiss_itself_whatever_the_chunks(factory):
    """RaBitQ (flat, IVF, fast-scan: built from a plain twin holding the standalone codes),
    additive quantisers (LSQ's codes depend on the rows encoded together: encoded in blocks
    at fixed offsets) and HNSW graphs (linked in such blocks on one thread), given their
    references in uneven chunks, answer as FAISS's own index built by ``add``, and their
    decoded vectors (a graph's: its rows; RaBitQ's: its records; an IVF fast-scan PQ's: its
    indices) are what the window scores read."""
    rng = np.random.default_rng(3)
    ref = rng.standard_normal((9000, 16)).astype(np.float32)
    query = ref[::50] + 0.2 * rng.standard_normal((180, 16)).astype(np.float32)
    train = ref[::3]  # 3,000 rows: LSQ's training (both sides) costs 1 s a 1,000 rows here
    codes = _trained_and_encoded(FaissCodes(factory, 16, k=7), train, ref, block=2500)
    own = faiss_own(factory, train, ref)
    dist, ids = codes.search(query)
    own_dist, own_ids = own.search(query, 7)
    if isinstance(codes.inner, (faiss.IndexIVFAdditiveQuantizerFastScan, faiss.IndexAdditiveQuantizerFastScan)):
        own_dist = own_dist + (query.astype(np.float64) ** 2).sum(axis=1)[:, None]  # FAISS leaves ‖y‖² out
    np.testing.assert_array_equal(ids, own_ids)
    np.testing.assert_allclose(dist, own_dist, rtol=1e-5, atol=1e-5)
    if "HNSW" in factory:
        # the rows transformed in blocks at fixed offsets, whatever chunks they came in (BLAS may round a
        # row otherwise in a product of another height: the blocks are what makes the bytes reproducible)
        blocks = [codes._transform(ref[lo : lo + ENCODE_ROWS]) for lo in range(0, len(ref), ENCODE_ROWS)]
        np.testing.assert_array_equal(codes.vectors, np.concatenate(blocks))
        assert codes.scan_per_frame() > 0 and codes.params == "k=7 efSearch=64"
    elif codes.form == "factors":  # RaBitQ's records: signs, list number, two float32 factors
        assert codes.codes.shape == (len(ref), rabitq.record_width(16, codes.inner.sa_code_size() - 10))
        assert codes.vectors.shape == (0, 0)
    elif codes.form == "tables":  # an IVF fast-scan code of the rows: its indices, the list number aside
        assert codes.codes.shape == (len(ref), codes.subs.columns) and codes.vectors.shape == (0, 0)
    elif codes.form == "residual":  # a residual fast-scan code's records: indices, list number, term's level
        width = codes.subs.columns + codes.ivf.coarse_code_size() + REF_LEVEL_BYTES
        assert codes.codes.shape == (len(ref), width) and codes.vectors.shape == (0, 0)
    else:
        assert codes.vectors.shape == (len(ref), codes.inner.d)


@pytest.mark.parametrize("factory", ["PQ4", "IVF16,PQ4"])
def test_product_codes_answer_as_faiss_polysemous_trained_ones(factory):
    """A product quantiser trained without FAISS's polysemous renumbering (it only numbers the
    centroids otherwise) finds what the factory's own polysemous-trained index finds: the same
    neighbours at the same distances, bit for bit."""
    rng = np.random.default_rng(5)
    ref = np.cumsum(rng.standard_normal((6000, 16)), axis=0).astype(np.float32) * 0.1
    query = ref[::40] + 0.05 * rng.standard_normal((150, 16)).astype(np.float32)
    train = ref[training_rows(len(ref))]
    codes = _trained_and_encoded(FaissCodes(factory, 16, k=9), train, ref, block=len(ref))
    own = faiss_own(factory, train, ref, anneal=20_000)
    own_pq = faiss.downcast_index(faiss.extract_index_ivf(own) if "IVF" in factory else own).pq
    assert not codes.inner.do_polysemous_training and faiss.downcast_index(own).do_polysemous_training
    centroids = (faiss.vector_to_array(q.centroids).reshape(q.M, q.ksub, q.dsub) for q in (codes.inner.pq, own_pq))
    assert any((ours != theirs).any() for ours, theirs in zip(*centroids, strict=True))  # renumbered
    dist, ids = codes.search(query)
    own_dist, own_ids = own.search(query, 9)
    np.testing.assert_array_equal(ids, own_ids)
    np.testing.assert_array_equal(dist, own_dist)


@pytest.mark.parametrize("factory, message", [
    ("HNSW32,PQ4", "not a FAISS index_factory string with standalone codes"),
    ("NSG32", "not a FAISS index_factory string with standalone codes"),
])
def test_codes_without_a_comparable_form_are_refused(factory, message):
    with pytest.raises(InputError, match=message):
        FaissCodes(factory, 16, k=4)
