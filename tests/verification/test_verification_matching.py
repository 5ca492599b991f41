"""Correspondences: Hamming distances, ratio test, direct index, cross-check, empty inputs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import shared_path
from stablecues.errors import InputError
from stablecues.features import OrbExtractor
from stablecues.imageio import read_image
from stablecues.types import Features, FeatureVector
from stablecues.verification import Matches, hamming_matrix, hamming_pairs, match_features
from stablecues.vocabulary import default_vocabulary
from stablecues.vocabulary.engine import compiled_kernels


def _features(desc: np.ndarray) -> Features:
    n = desc.shape[0]
    rng = np.random.default_rng(n)
    return Features(
        keypoints=rng.uniform(0, 100, (n, 2)).astype(np.float32),
        descriptors=desc,
        octaves=np.zeros(n, np.int16),
        angles=np.zeros(n, np.float32),
        responses=np.ones(n, np.float32),
        sizes=np.full(n, 31.0, np.float32),
        image_size=(100, 100),
    )


def _flip(desc: np.ndarray, bits: int, rng: np.random.Generator) -> np.ndarray:
    out = desc.copy()
    for row in out:
        for b in rng.choice(256, bits, replace=False):
            row[b // 8] ^= np.uint8(1 << (b % 8))
    return out


def test_hamming_by_hand() -> None:
    a = np.zeros((2, 32), np.uint8)
    b = np.zeros((3, 32), np.uint8)
    a[1, :] = 255
    b[1, 0] = 0b1011
    b[2, 31] = 0xFF
    d = hamming_matrix(a, b)
    np.testing.assert_array_equal(d, [[0, 3, 8], [256, 253, 248]])
    np.testing.assert_array_equal(hamming_pairs(a, b, np.array([1, 0]), np.array([2, 1])), [248, 3])
    with pytest.raises(InputError):
        hamming_matrix(a[:, :16], b)


def test_brute_force_agrees_with_opencv() -> None:
    rng = np.random.default_rng(0)
    cand = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    query = _flip(cand[rng.permutation(300)[:200]], 20, rng)
    m = match_features(_features(query), _features(cand), ratio=1.0, max_distance=256)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING).match(query, cand)
    expected = {x.queryIdx: (x.trainIdx, int(x.distance)) for x in bf}
    for q, d in zip(m.query, m.distance, strict=True):  # ties may pick another candidate
        assert expected[int(q)][1] == d
    assert len(m) == 200
    assert (np.diff(m.distance) >= 0).all()  # ranked, best first


def test_ratio_test_and_ceiling() -> None:
    rng = np.random.default_rng(1)
    cand = rng.integers(0, 256, (2, 32), dtype=np.uint8)
    query = _flip(cand[:1], 10, rng)
    # an ambiguous candidate: the second candidate made almost equal to the first
    ambiguous = np.vstack([cand[0], _flip(cand[:1], 2, rng)[0]])
    assert len(match_features(_features(query), _features(ambiguous), ratio=0.8)) == 0
    m = match_features(_features(query), _features(cand), ratio=0.8)
    assert len(m) == 1 and m.distance[0] == 10 and m.ratio[0] < 0.2
    assert len(match_features(_features(query), _features(cand), max_distance=9)) == 0
    assert m.confidence[0] == pytest.approx(1 - 10 / 128)


def test_one_to_one() -> None:
    rng = np.random.default_rng(2)
    cand = rng.integers(0, 256, (1, 32), dtype=np.uint8)
    query = np.vstack([_flip(cand, 5, rng), _flip(cand, 12, rng)])
    m = match_features(_features(query), _features(cand), ratio=1.0)
    assert len(m) == 1 and m.query[0] == 0 and m.distance[0] == 5


def test_direct_index_restricts_comparisons() -> None:
    rng = np.random.default_rng(3)
    cand = rng.integers(0, 256, (6, 32), dtype=np.uint8)
    query = _flip(cand, 4, rng)
    qf = FeatureVector(np.array([0, 0, 1, 1, 2, -1], np.int32), 3)
    cf = FeatureVector(np.array([0, 0, 1, 5, 2, 2], np.int32), 3)
    m = match_features(_features(query), _features(cand), qf, cf)
    # feature 3 sits under another node, feature 5 under none: neither is compared
    assert sorted(zip(m.query.tolist(), m.candidate.tolist(), strict=True)) == [
        (0, 0),
        (1, 1),
        (2, 2),
        (4, 4),
    ]
    with pytest.raises(InputError):
        match_features(_features(query), _features(cand), qf, None)
    with pytest.raises(InputError):
        match_features(_features(query), _features(cand), FeatureVector(np.zeros(2, np.int32), 3), cf)


def test_direct_index_agrees_with_brute_force_in_one_node() -> None:
    rng = np.random.default_rng(4)
    cand = rng.integers(0, 256, (80, 32), dtype=np.uint8)
    query = _flip(cand[rng.permutation(80)], 30, rng)
    one = FeatureVector(np.zeros(80, np.int32), 0)
    a = match_features(_features(query), _features(cand), one, one)
    b = match_features(_features(query), _features(cand))
    np.testing.assert_array_equal(a.pairs(), b.pairs())
    np.testing.assert_array_equal(a.distance, b.distance)


def test_cross_check() -> None:
    rng = np.random.default_rng(5)
    cand = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    query = _flip(cand, 8, rng)
    for fv in (None, FeatureVector(np.zeros(40, np.int32), 0)):
        m = match_features(_features(query), _features(cand), fv, fv, cross_check=True)
        np.testing.assert_array_equal(np.sort(m.query), m.candidate[np.argsort(m.query)])


def test_empty_inputs() -> None:
    empty = Features.empty((100, 100))
    some = _features(np.zeros((3, 32), np.uint8))
    for a, b in ((empty, some), (some, empty), (empty, empty)):
        m = match_features(a, b)
        assert len(m) == 0
        assert m.pairs().shape == (0, 2) and m.distance.dtype == np.int32


def test_float_descriptors_match_on_the_binary_scale() -> None:
    """Float descriptors: unit-normalised L2 times 128, so 0 is identical and ~181 orthogonal;
    the matches are OpenCV's L2 matches of the normalised vectors."""
    from stablecues.verification.matching import scaled_distances

    rng = np.random.default_rng(3)
    cand = rng.normal(size=(200, 128)).astype(np.float32) * 50  # scale does not matter
    query = (cand[rng.permutation(200)[:120]] + rng.normal(scale=5.0, size=(120, 128))).astype(np.float32)
    d = scaled_distances(query, cand)
    unit = lambda x: x / np.linalg.norm(x, axis=1, keepdims=True)  # noqa: E731
    expected = np.linalg.norm(unit(query)[:, None] - unit(cand)[None], axis=2) * 128
    np.testing.assert_allclose(d, np.rint(expected), atol=1)
    e = np.eye(4, dtype=np.float32)
    assert scaled_distances(e, e)[0, 0] == 0 and scaled_distances(e, e)[0, 1] == round(np.sqrt(2) * 128)
    m = match_features(_features(query), _features(cand), ratio=0.8, max_distance=256)
    bf = cv2.BFMatcher(cv2.NORM_L2).match(unit(query).astype(np.float32), unit(cand).astype(np.float32))
    truth = {x.queryIdx: x.trainIdx for x in bf}
    assert len(m) >= 110 and all(truth[int(q)] == int(c) for q, c in zip(m.query, m.candidate, strict=True))
    pairs = scaled_distances(query, cand, np.array([0, 1]), np.array([5, 7]))
    np.testing.assert_array_equal(pairs, d[[0, 1], [5, 7]])
    with pytest.raises(InputError, match="candidate's are"):
        match_features(_features(query), _features(rng.integers(0, 256, (10, 32), dtype=np.uint8)))


def test_binary_descriptors_of_other_widths_are_scaled_to_256_bits() -> None:
    from stablecues.verification.matching import scaled_distances

    a = np.zeros((1, 61), np.uint8)  # AKAZE's 488 bits
    b = np.full((1, 61), 255, np.uint8)
    assert scaled_distances(a, b)[0, 0] == 256 and scaled_distances(a, a)[0, 0] == 0


needs_numba = pytest.mark.skipif(compiled_kernels() is None, reason="numba is not available")


def _assert_same_matches(a: Matches, b: Matches) -> None:
    for name in ("query", "candidate", "distance", "ratio"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


@needs_numba
@pytest.mark.parametrize("seed", range(6))
def test_compiled_matching_agrees_with_numpy_on_ties_and_lone_candidates(seed: int) -> None:
    """Descriptors drawn from a small pool (many equal distances), nodes with one candidate,
    none, or many, and features without a node (-1): both engines pick the same matches."""
    rng = np.random.default_rng(seed)
    pool = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    n, m = int(rng.integers(1, 400)), int(rng.integers(1, 400))
    qd = _flip(pool[rng.integers(0, 40, n)], 3, rng)
    cd = _flip(pool[rng.integers(0, 40, m)], 3, rng)
    qn = rng.integers(-1, 30, n).astype(np.int32)
    cn = rng.integers(-1, 45, m).astype(np.int32)
    q, c = _features(qd), _features(cd)
    qv, cv = FeatureVector(qn, 2), FeatureVector(cn, 2)
    for ratio, ceiling in ((0.8, 64), (1.0, 256), (0.6, 40)):
        for cross in (False, True):
            _assert_same_matches(
                match_features(q, c, qv, cv, ratio=ratio, max_distance=ceiling, cross_check=cross,
                               engine="numpy"),
                match_features(q, c, qv, cv, ratio=ratio, max_distance=ceiling, cross_check=cross,
                               engine="compiled"),
            )


@needs_numba
def test_compiled_matching_agrees_with_numpy_on_real_frames() -> None:
    files = sorted(shared_path("camvid", "test").glob("*.jpg"))[:60:6]
    if not files:
        pytest.skip("../shared/data/camvid/test is not here")
    voc = default_vocabulary()
    extractor = OrbExtractor()
    feats = [extractor.extract(read_image(f, "grey")) for f in files]
    fvecs = [voc.transform(f.descriptors)[1] for f in feats]
    total = 0
    for i in range(len(feats)):
        for j in (i + 1, i + 4):
            if j < len(feats):
                for cross in (False, True):
                    a = match_features(feats[i], feats[j], fvecs[i], fvecs[j], cross_check=cross,
                                       engine="numpy")
                    b = match_features(feats[i], feats[j], fvecs[i], fvecs[j], cross_check=cross,
                                       engine="compiled")
                    _assert_same_matches(a, b)
                    total += len(a)
    assert total > 200  # real matches were compared, not empty sets


def test_float_brute_force_is_the_full_distance_matrix_search() -> None:
    """Brute force over float descriptors (one float32 product, no distance matrix) finds what
    the full matrix of scaled distances finds: each query's nearest candidate, its best and
    second distances, and with cross-checking the mutual pairs only."""
    from stablecues.verification.matching import scaled_distances

    rng = np.random.default_rng(5)
    base = rng.normal(size=(300, 64)).astype(np.float32)
    q = base[:200] + 0.3 * rng.normal(size=(200, 64)).astype(np.float32)
    c = base[50:] + 0.3 * rng.normal(size=(250, 64)).astype(np.float32)
    fq = Features(np.zeros((200, 2), np.float32), q, np.zeros(200, np.int16), np.zeros(200, np.float32),
                  np.zeros(200, np.float32), np.zeros(200, np.float32), (640, 480))
    fc = Features(np.zeros((250, 2), np.float32), c, np.zeros(250, np.int16), np.zeros(250, np.float32),
                  np.zeros(250, np.float32), np.zeros(250, np.float32), (640, 480))
    d = scaled_distances(q, c)
    for cross in (False, True):
        m = match_features(fq, fc, ratio=0.9, max_distance=256, cross_check=cross)
        assert len(m) > 100
        assert (m.candidate == np.argmin(d[m.query], axis=1)).all()
        assert (m.distance == d[m.query, m.candidate]).all()
        if cross:
            assert (np.argmin(d[:, m.candidate], axis=0) == m.query).all()
