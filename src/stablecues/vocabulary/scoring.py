"""Weighting and scoring of bag-of-words vectors, as DBoW2 defines them.

All six scorings are computed by one loop over the words two vectors share (a sparse join),
parameterised by the scoring: a term per common word and a final transform. The database's
inverse-index query uses the very same terms (see :mod:`stablecues.database`).

=================  ==========  ============================================  ===========
scoring            norm        score                                         range
=================  ==========  ============================================  ===========
L1                 L1          -1/2 * sum(|v-w| - |v| - |w|) = sum(min(v,w))  [0, 1]
L2                 L2          1 - sqrt(1 - sum(v*w))                        [0, 1]
chi-square         L1          2 * sum(v*w / (v+w))                          [0, 1]
KL                 L1          sum_v v*log(v/w), eps where w missing         >= 0, lower
                                                                             is better
Bhattacharyya      L1          sum(sqrt(v*w))                                [0, 1]
dot product        none        sum(v*w)                                      >= 0
=================  ==========  ============================================  ===========

KL is a divergence, as in DBoW2 ("cannot be scaled"): lower means more similar; every other
scoring is a similarity. Use :func:`higher_is_better` when ranking.
"""

from __future__ import annotations

import enum
import math

import numpy as np

from ..types import BowVector

LOG_EPS = math.log(np.finfo(np.float64).eps)  # DBoW2: log(DBL_EPSILON)


class Weighting(enum.IntEnum):
    """Word weighting, numbered as DBoW2's ``WeightingType``."""

    TF_IDF = 0
    TF = 1
    IDF = 2
    BINARY = 3


class Scoring(enum.IntEnum):
    """Scoring, numbered as DBoW2's ``ScoringType``."""

    L1 = 0
    L2 = 1
    CHI_SQUARE = 2
    KL = 3
    BHATTACHARYYA = 4
    DOT_PRODUCT = 5


WEIGHTING_NAMES = {"tf-idf": Weighting.TF_IDF, "tf": Weighting.TF, "idf": Weighting.IDF,
                   "binary": Weighting.BINARY}
SCORING_NAMES = {"l1": Scoring.L1, "l2": Scoring.L2, "chi-square": Scoring.CHI_SQUARE,
                 "kl": Scoring.KL, "bhattacharyya": Scoring.BHATTACHARYYA,
                 "dot": Scoring.DOT_PRODUCT}


def parse_weighting(value: str | int | Weighting) -> Weighting:
    from ..errors import ConfigError

    if isinstance(value, str):
        if value.lower() not in WEIGHTING_NAMES:
            raise ConfigError(f"unknown weighting {value!r}; known: {', '.join(WEIGHTING_NAMES)}")
        return WEIGHTING_NAMES[value.lower()]
    return Weighting(int(value))


def parse_scoring(value: str | int | Scoring) -> Scoring:
    from ..errors import ConfigError

    if isinstance(value, str):
        if value.lower() not in SCORING_NAMES:
            raise ConfigError(f"unknown scoring {value!r}; known: {', '.join(SCORING_NAMES)}")
        return SCORING_NAMES[value.lower()]
    return Scoring(int(value))


def weighting_name(w: Weighting) -> str:
    return {v: k for k, v in WEIGHTING_NAMES.items()}[w]


def scoring_name(s: Scoring) -> str:
    return {v: k for k, v in SCORING_NAMES.items()}[s]


def norm_of(scoring: Scoring) -> str | None:
    """Which norm the scoring wants its vectors normalised with: "l1", "l2" or None."""
    if scoring == Scoring.L2:
        return "l2"
    if scoring == Scoring.DOT_PRODUCT:
        return None
    return "l1"


def higher_is_better(scoring: Scoring) -> bool:
    return scoring != Scoring.KL


def normalise(weights: np.ndarray, scoring: Scoring) -> np.ndarray:
    """Normalise a (M,) float64 weight vector as ``scoring`` needs (a new array)."""
    norm = norm_of(scoring)
    if norm is None or weights.size == 0:
        return weights.astype(np.float64, copy=True)
    total = np.abs(weights).sum() if norm == "l1" else math.sqrt(float(weights @ weights))
    return weights / total if total > 0 else weights.astype(np.float64, copy=True)


def common_terms(scoring: Scoring, v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Per-word contribution of words present in both vectors.

    Args:
        scoring: the scoring.
        v: (K,) query weights of the shared words.
        w: (K,) the other vector's weights of the same words.

    Returns:
        (K,) float64 terms; their sum per vector pair goes to :func:`finish`.
    """
    if scoring == Scoring.L1:
        # DBoW2 sums |v - w| - |v| - |w| and scales by -1/2; for the non-negative BoW weights
        # each term is then simply min(v, w)
        if (v.size and v.min() < 0) or (w.size and w.min() < 0):
            return -0.5 * (np.abs(v - w) - np.abs(v) - np.abs(w))
        return np.minimum(v, w)
    if scoring in (Scoring.L2, Scoring.DOT_PRODUCT):
        return v * w
    if scoring == Scoring.CHI_SQUARE:
        s = v + w
        return np.divide(v * w, s, out=np.zeros_like(s), where=s != 0)
    if scoring == Scoring.KL:
        # v*log(v/w) for shared words, minus what the "missing word" term of the same word
        # would have added, which :func:`finish` adds for every query word.
        ok = (v != 0) & (w != 0)
        logv = np.log(np.where(v > 0, v, 1.0))
        logw = np.log(np.where(w > 0, w, 1.0))
        return np.where(ok, v * (logv - logw), 0.0) - np.where(v != 0, v * (logv - LOG_EPS), 0.0)
    if scoring == Scoring.BHATTACHARYYA:
        return np.sqrt(v * w)
    raise ValueError(f"unknown scoring {scoring}")


def kl_missing_total(v: np.ndarray) -> float:
    """KL: the sum over all query words of the term DBoW2 adds when a word is missing."""
    nz = v[v != 0]
    return float(np.sum(nz * (np.log(nz) - LOG_EPS)))


def finish(scoring: Scoring, sums: np.ndarray, kl_missing: float = 0.0) -> np.ndarray:
    """Turn per-pair sums of :func:`common_terms` into DBoW2 scores (array in, array out)."""
    if scoring == Scoring.L2:
        return np.where(sums >= 1.0, 1.0, 1.0 - np.sqrt(np.clip(1.0 - sums, 0.0, None)))
    if scoring == Scoring.CHI_SQUARE:
        return 2.0 * sums
    if scoring == Scoring.KL:
        return sums + kl_missing
    return sums


def score(v: BowVector, w: BowVector, scoring: Scoring) -> float:
    """DBoW2 score between two BoW vectors (already normalised by the vocabulary)."""
    _, iv, iw = np.intersect1d(v.words, w.words, assume_unique=True, return_indices=True)
    terms = common_terms(scoring, v.weights[iv], w.weights[iw])
    kl = kl_missing_total(v.weights) if scoring == Scoring.KL else 0.0
    return float(finish(scoring, np.array([terms.sum()]), kl)[0])
