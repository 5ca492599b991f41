"""Every scoring against hand-computed values (DBoW2's definitions)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stablecues.types import BowVector
from stablecues.vocabulary import Scoring, score
from stablecues.vocabulary.scoring import LOG_EPS, normalise


def bow(d: dict[int, float]) -> BowVector:
    words = np.array(sorted(d), np.int32)
    return BowVector(words, np.array([d[w] for w in sorted(d)], np.float64))


V = bow({1: 0.5, 2: 0.5})
W = bow({2: 0.25, 3: 0.75})


def test_l1_is_dbow2_formula() -> None:
    # DBoW2: -1/2 * sum over common (|v-w| - |v| - |w|) = 1 - ||v - w||_1 / 2
    assert score(V, W, Scoring.L1) == pytest.approx(0.25)
    l1_dist = 0.5 + 0.25 + 0.75
    assert score(V, W, Scoring.L1) == pytest.approx(1 - l1_dist / 2)
    assert score(V, V, Scoring.L1) == pytest.approx(1.0)
    assert score(V, bow({7: 1.0}), Scoring.L1) == 0.0


def test_chi_square_and_bhattacharyya() -> None:
    assert score(V, W, Scoring.CHI_SQUARE) == pytest.approx(2 * 0.5 * 0.25 / 0.75)
    assert score(V, V, Scoring.CHI_SQUARE) == pytest.approx(1.0)
    assert score(V, W, Scoring.BHATTACHARYYA) == pytest.approx(math.sqrt(0.125))
    assert score(V, V, Scoring.BHATTACHARYYA) == pytest.approx(1.0)


def test_kl_uses_epsilon_for_missing_words() -> None:
    expected = 0.5 * (math.log(0.5) - LOG_EPS) + 0.5 * math.log(0.5 / 0.25)
    assert score(V, W, Scoring.KL) == pytest.approx(expected)
    assert score(V, V, Scoring.KL) == pytest.approx(0.0)


def test_l2_and_dot_product() -> None:
    v2 = bow({1: 1 / math.sqrt(2), 2: 1 / math.sqrt(2)})
    w2 = bow({2: 0.6, 3: 0.8})
    assert score(v2, w2, Scoring.L2) == pytest.approx(1 - math.sqrt(1 - 0.6 / math.sqrt(2)))
    assert score(v2, v2, Scoring.L2) == pytest.approx(1.0)
    assert score(bow({1: 2.0, 2: 3.0}), bow({2: 4.0}), Scoring.DOT_PRODUCT) == pytest.approx(12.0)


def test_normalise() -> None:
    w = np.array([1.0, 3.0])
    np.testing.assert_allclose(normalise(w, Scoring.L1), [0.25, 0.75])
    np.testing.assert_allclose(normalise(w, Scoring.L2), w / math.sqrt(10))
    np.testing.assert_allclose(normalise(w, Scoring.DOT_PRODUCT), w)
    assert normalise(np.zeros(0), Scoring.L1).size == 0


@pytest.mark.parametrize("scoring", list(Scoring))
def test_empty_vectors_score_without_error(scoring: Scoring) -> None:
    empty = BowVector.empty()
    s = score(empty, V, scoring)
    assert math.isfinite(s)
