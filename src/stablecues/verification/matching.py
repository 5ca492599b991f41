"""Correspondences between a query frame's features and a candidate's, as DBoW2/ORB-SLAM find them.

With feature vectors (the direct index), only features under the same vocabulary node are
compared, which is both faster and a prior that the two descriptors look alike at a coarse
level. Without them, every pair is compared (brute force). Then:

* Lowe's ratio test, ``best < ratio * second_best`` as ORB-SLAM writes it; a feature with a
  single candidate in its node compares against 256 (the largest Hamming distance), so it
  passes when ``best < ratio * 256`` and under ``max_distance``;
* an absolute ceiling ``max_distance`` on the best distance;
* one-to-one: when several query features pick the same candidate feature, the closest keeps
  it (optionally a full mutual cross-check);
* ranking by distance, then by ratio (best first).

Hamming distances use ``np.bitwise_count`` on the descriptors viewed as 4 uint64 words, summed
word by word (4x faster than ``.sum(-1)`` on the 3-D popcount array).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InputError, check_array
from ..types import DescriptorKind, Features, FeatureVector
from ..vocabulary.descriptors import as_words, check_descriptors, hamming_cross, hamming_rows
from ..vocabulary.engine import compiled_kernels, resolve

__all__ = ["Matches", "hamming_matrix", "hamming_pairs", "match_features", "scaled_distances"]

_NONE = 256  # "second best" when a feature has a single candidate


@dataclass(frozen=True, eq=False)
class Matches:
    """Ranked correspondences (best first).

    Attributes:
        query: (M,) int32 index of each match's query feature.
        candidate: (M,) int32 index of its candidate feature.
        distance: (M,) int32 distance of the two descriptors on the scale of
            :func:`scaled_distances` (0..256; the Hamming distance for 256-bit descriptors).
        ratio: (M,) float32 best / second-best distance (second best 256 when alone).
    """

    query: np.ndarray
    candidate: np.ndarray
    distance: np.ndarray
    ratio: np.ndarray

    def __post_init__(self) -> None:
        check_array("match query indices", self.query, dtype=np.int32, ndim=1)
        m = self.query.shape[0]
        check_array("match candidate indices", self.candidate, dtype=np.int32, shape=(m,))
        check_array("match distances", self.distance, dtype=np.int32, shape=(m,))
        check_array("match ratios", self.ratio, dtype=np.float32, shape=(m,))

    def __len__(self) -> int:
        return int(self.query.shape[0])

    @staticmethod
    def empty() -> Matches:
        return Matches(
            np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, np.float32)
        )

    def subset(self, index: np.ndarray) -> Matches:
        """Matches selected by a boolean mask or an index array (order kept)."""
        index = np.asarray(index)
        return Matches(self.query[index], self.candidate[index], self.distance[index], self.ratio[index])

    def pairs(self) -> np.ndarray:
        """(M, 2) int32 ``[query index, candidate index]`` rows."""
        return np.stack((self.query, self.candidate), axis=1)

    @property
    def confidence(self) -> np.ndarray:
        """(M,) float32 in [0, 1]: ``1 - distance / 128``. Unrelated 256-bit descriptors differ
        in 128 bits on average, so 0 is "no better than chance" and 1 "identical"."""
        return np.clip(1.0 - self.distance.astype(np.float32) / 128.0, 0.0, 1.0)


def hamming_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """All Hamming distances between two sets of 256-bit descriptors.

    Args:
        a: (N, 32) uint8 descriptors.
        b: (M, 32) uint8 descriptors.

    Returns:
        (N, M) uint16 distances.
    """
    check_descriptors(a, "descriptors a")
    check_descriptors(b, "descriptors b")
    return hamming_cross(as_words(a), as_words(b)).astype(np.uint16)


def hamming_pairs(a: np.ndarray, b: np.ndarray, ia: np.ndarray, ib: np.ndarray) -> np.ndarray:
    """Hamming distances of the pairs ``(a[ia[k]], b[ib[k]])``.

    Args:
        a: (N, 32) uint8 descriptors; b: (M, 32) uint8 descriptors.
        ia, ib: (P,) index arrays.

    Returns:
        (P,) int32 distances.
    """
    check_descriptors(a, "descriptors a")
    check_descriptors(b, "descriptors b")
    return hamming_rows(as_words(a)[ia], as_words(b)[ib])


def _unit(d: np.ndarray) -> np.ndarray:
    x = np.asarray(d, np.float64)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


def _checked_kind(a: np.ndarray, b: np.ndarray) -> DescriptorKind:
    """The descriptors' common kind, both arrays checked against it (one-line InputError)."""
    kind = DescriptorKind.of(a, "query descriptors")
    if DescriptorKind.of(b, "candidate descriptors") != kind:
        raise InputError(f"matching: query descriptors are {kind} but the candidate's are "
                         f"{DescriptorKind.of(b, 'candidate descriptors')}")
    check_descriptors(a, "query descriptors", kind)
    check_descriptors(b, "candidate descriptors", kind)
    return kind


def scaled_distances(
    a: np.ndarray, b: np.ndarray, ia: np.ndarray | None = None, ib: np.ndarray | None = None
) -> np.ndarray:
    """Descriptor distances of any kind on one integer scale of 0..256, 128 meaning "chance".

    Binary descriptors of 256 bits: the Hamming distance itself; of other widths, scaled to 256
    bits. Float descriptors (SIFT, learned ones): the Euclidean distance of the unit-normalised
    vectors (0..2) times 128, rounded, so unrelated descriptors (about orthogonal, distance
    ~1.4) land near the binary "chance" of 128 and ``max_distance``, ``Matches.confidence`` and the
    ratio test keep their meaning.

    Args:
        a, b: (N, D) and (M, D) descriptors of one kind.
        ia, ib: index arrays of the pairs to measure; None for the full (N, M) matrix.

    Returns:
        int64 distances, (P,) for pairs or (N, M).
    """
    kind = _checked_kind(a, b)
    if kind.kind == "float":
        if ia is not None and ib is not None:
            return _pair_distances(a, b, ia, ib)
        ua, ub = _unit(a), _unit(b)
        sq = 2.0 - 2.0 * (ua @ ub.T)
        return np.clip(np.rint(np.sqrt(np.maximum(sq, 0.0)) * 128.0), 0, 256).astype(np.int64)
    wa, wb = as_words(a), as_words(b)
    h = hamming_cross(wa, wb) if ia is None or ib is None else hamming_rows(wa[ia], wb[ib])
    bits = 8 * a.shape[1]
    h = np.asarray(h, np.int64)
    return h if bits == 256 else np.rint(h * (256.0 / bits)).astype(np.int64)


def _ragged_pairs(query_nodes: np.ndarray, cand_nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All (query, candidate) index pairs whose nodes are equal (and >= 0), grouped by query."""
    corder = np.argsort(cand_nodes, kind="stable")
    csorted = cand_nodes[corder]
    lo = np.searchsorted(csorted, query_nodes, side="left")
    hi = np.searchsorted(csorted, query_nodes, side="right")
    counts = np.where(query_nodes >= 0, hi - lo, 0)
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    qi = np.repeat(np.arange(query_nodes.size), counts)
    group_start = np.repeat(np.cumsum(counts) - counts, counts)
    ci = corder[np.repeat(lo, counts) + (np.arange(total) - group_start)]
    return qi, ci


def _binary_kernels(a: np.ndarray, b: np.ndarray, engine: str) -> Any:
    """The compiled kernels when they can match these descriptors (256-bit binary, the engine
    allowing it), else None."""
    if engine == "numpy":
        return None
    kind = DescriptorKind.of(a, "query descriptors")
    if kind.kind == "float" or kind.size != 32 or resolve(engine) != "compiled":
        return None  # scaled_distances checks the descriptors on the NumPy path
    _checked_kind(a, b)
    return compiled_kernels()


def _best_two_compiled(
    kernels: Any, a: np.ndarray, b: np.ndarray, query_fvec: FeatureVector, cand_fvec: FeatureVector
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per query feature: its nearest candidate (-1: none), best and second-best distance,
    among the candidates under its node; what :func:`_ragged_pairs` and
    :func:`_best_two_grouped` give, in one compiled loop."""
    corder = cand_fvec.order
    n = len(query_fvec)
    best_j, best, second = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64)
    kernels.best_two_binary(as_words(a), as_words(b), query_fvec.nodes, query_fvec.order,
                            cand_fvec.nodes[corder], corder, _NONE, best_j, best, second)
    return best_j, best, second


def _best_two_grouped(
    qi: np.ndarray, dist: np.ndarray, n_query: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per query feature: position of its best pair, best and second-best distance.

    ``qi`` must be non-decreasing (pairs grouped by query).
    """
    best_pos = np.full(n_query, -1, np.int64)
    best = np.full(n_query, _NONE + 1, np.int64)
    second = np.full(n_query, _NONE, np.int64)
    if qi.size == 0:
        return best_pos, best, second
    starts = np.flatnonzero(np.r_[True, qi[1:] != qi[:-1]])
    owners = qi[starts]
    key = (dist.astype(np.int64) << 32) | np.arange(qi.size, dtype=np.int64)
    mins = np.minimum.reduceat(key, starts)
    pos = mins & 0xFFFFFFFF
    best_pos[owners] = pos
    best[owners] = mins >> 32
    masked = dist.astype(np.int64).copy()
    masked[pos] = _NONE
    second[owners] = np.minimum.reduceat(masked, starts)
    return best_pos, best, second


def _best_two_float(
    a: np.ndarray, b: np.ndarray, cross_check: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Brute force over float descriptors: per query feature its nearest candidate, the best and
    second-best distances (on :func:`scaled_distances`' scale) and, with ``cross_check``, whether
    the query feature is also its nearest candidate's nearest query feature (else an empty array).

    The nearest neighbours come from one float32 product of the unit vectors (BLAS; the full
    (N, M) distance matrix of :func:`scaled_distances` is never made); the mutual check compares
    each chosen pair with its column's maximum (a row-wise reduction, not a strided argmax); the
    distances of the pairs chosen are then computed as :func:`scaled_distances` computes them.
    """
    _checked_kind(a, b)
    n, m = a.shape[0], b.shape[0]
    sim = _unit32(a) @ _unit32(b).T
    rows = np.arange(n)
    best_j = np.argmax(sim, axis=1).astype(np.int64)
    top = sim[rows, best_j]
    mutual = top >= sim.max(axis=0)[best_j] if cross_check else np.zeros(0, bool)
    best = _pair_distances(a, b, rows, best_j)
    if m < 2:
        return best_j, best, np.full(n, _NONE, np.int64), mutual
    sim[rows, best_j] = -np.inf
    second = _pair_distances(a, b, rows, np.argmax(sim, axis=1))
    return best_j, best, np.maximum(second, best), mutual


def _unit32(d: np.ndarray) -> np.ndarray:
    """Unit rows in float32 (for the similarity product only)."""
    x = np.asarray(d, np.float32)
    return x / np.maximum(np.sqrt(np.einsum("ij,ij->i", x, x)), 1e-12)[:, None]


def _pair_distances(a: np.ndarray, b: np.ndarray, ia: np.ndarray, ib: np.ndarray) -> np.ndarray:
    """:func:`scaled_distances` of the pairs ``(a[ia], b[ib])``, each row made a unit vector in
    float64 first (only the rows of the pairs are normalised)."""
    diff = _unit(a[ia]) - _unit(b[ib])
    sq = np.einsum("ij,ij->i", diff, diff)
    return np.clip(np.rint(np.sqrt(np.maximum(sq, 0.0)) * 128.0), 0, 256).astype(np.int64)


def _one_node(fvec: FeatureVector) -> bool:
    """Whether every feature sits under one and the same node (an incremental vocabulary's)."""
    nodes = fvec.nodes
    return bool(nodes.size) and int(nodes.min()) >= 0 and int(nodes.min()) == int(nodes.max())


def _best_two_indexed(
    query: Features, candidate: Features, query_fvec: FeatureVector, candidate_fvec: FeatureVector,
    cross_check: bool, engine: str,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Per query feature, among the candidates under its vocabulary node: its nearest candidate,
    best and second-best distance, whether it has any; with ``cross_check`` each candidate
    feature's nearest query feature among the pairs it takes part in (-1: none)."""
    n, m = len(query), len(candidate)
    if len(query_fvec) != n or len(candidate_fvec) != m:
        raise InputError(
            f"feature vectors: expected {n} and {m} nodes like the features, "
            f"got {len(query_fvec)} and {len(candidate_fvec)}"
        )
    kernels = _binary_kernels(query.descriptors, candidate.descriptors, engine)
    if kernels is not None:
        best_j, best, second = _best_two_compiled(
            kernels, query.descriptors, candidate.descriptors, query_fvec, candidate_fvec)
        back = None
        if cross_check:  # each candidate feature's nearest query feature under its node: the same
            # kernel the other way round (ties to the lower query index, as the NumPy path's key)
            back = _best_two_compiled(kernels, candidate.descriptors, query.descriptors, candidate_fvec,
                                      query_fvec)[0]
        return best_j, best, second, best_j >= 0, back
    qi, ci = _ragged_pairs(query_fvec.nodes, candidate_fvec.nodes)
    dist = scaled_distances(query.descriptors, candidate.descriptors, qi, ci)
    best_pos, best, second = _best_two_grouped(qi, dist, n)
    has = best_pos >= 0
    best_j = np.full(n, -1, np.int64)
    best_j[has] = ci[best_pos[has]]
    if not cross_check:
        return best_j, best, second, has, None
    ckey = np.full(m, np.iinfo(np.int64).max, np.int64)
    np.minimum.at(ckey, ci, (dist.astype(np.int64) << 32) | qi)
    return best_j, best, second, has, np.where(ckey == np.iinfo(np.int64).max, -1, ckey & 0xFFFFFFFF)


def match_features(
    query: Features,
    candidate: Features,
    query_fvec: FeatureVector | None = None,
    candidate_fvec: FeatureVector | None = None,
    ratio: float = 0.8,
    cross_check: bool = False,
    *,
    max_distance: int = 64,
    engine: str = "auto",
) -> Matches:
    """Match query features to candidate features.

    Args:
        query: the query frame's features (N).
        candidate: the candidate frame's features (M).
        query_fvec: the query's direct index; with ``candidate_fvec`` restricts comparisons to
            features under the same vocabulary node. Both or neither.
        candidate_fvec: the candidate's direct index.
        ratio: Lowe's ratio; a match needs ``best < ratio * second_best``.
        cross_check: also require the query feature to be the candidate feature's best match
            (among the features it is compared with).
        max_distance: largest accepted distance of the best candidate, on the scale of
            :func:`scaled_distances` (the Hamming distance for 256-bit descriptors).
        engine: ``"auto"``, ``"compiled"`` or ``"numpy"`` (see
            :mod:`stablecues.vocabulary.engine`): the nearest two of 256-bit descriptors under
            their nodes (no cross-check) in one compiled loop, or vectorised over all pairs;
            the two give identical matches.

    Returns:
        One-to-one matches ranked by distance then ratio; empty (correctly shaped) when either
        side has no features.
    """
    if not isinstance(query, Features) or not isinstance(candidate, Features):
        raise InputError("match_features: expected two Features objects")
    if (query_fvec is None) != (candidate_fvec is None):
        raise InputError("match_features: give both feature vectors or neither")
    if not 0 < ratio <= 1:
        raise InputError(f"match ratio: expected a number in (0, 1], got {ratio}")
    n, m = len(query), len(candidate)
    if n == 0 or m == 0:
        return Matches.empty()

    back: np.ndarray | None = None  # with cross_check: each candidate feature's nearest query feature
    mutual = np.ones(n, bool)
    if (query_fvec is not None and candidate_fvec is not None
            and DescriptorKind.of(query.descriptors, "query descriptors").kind == "float"
            and _one_node(query_fvec) and _one_node(candidate_fvec)):
        query_fvec = candidate_fvec = None  # every pair compared: brute force, not N x M pair lists
    if query_fvec is not None and candidate_fvec is not None:
        best_j, best, second, has, back = _best_two_indexed(query, candidate, query_fvec, candidate_fvec,
                                                            cross_check, engine)
    elif DescriptorKind.of(query.descriptors, "query descriptors").kind == "float":
        best_j, best, second, nearest = _best_two_float(query.descriptors, candidate.descriptors, cross_check)
        has = np.ones(n, bool)
        if cross_check:
            mutual = nearest
    else:
        d = scaled_distances(query.descriptors, candidate.descriptors)
        best_j = np.argmin(d, axis=1).astype(np.int64)
        best = d[np.arange(n), best_j].astype(np.int64)
        second = np.partition(d, 1, axis=1)[:, 1].astype(np.int64) if m >= 2 else np.full(n, _NONE, np.int64)
        has = np.ones(n, bool)
        if cross_check:
            back = np.argmin(d, axis=0).astype(np.int64)
    if back is not None:
        mutual = back[np.clip(best_j, 0, m - 1)] == np.arange(n)

    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(second > 0, best / np.maximum(second, 1), 1.0)
    keep = has & (best <= max_distance) & (best < ratio * second)
    keep &= mutual
    qidx = np.flatnonzero(keep)
    cidx = best_j[qidx]
    bd = best[qidx]
    br = r[qidx]
    # one-to-one: closest query feature keeps a candidate feature (ties: lower ratio, lower index)
    order = np.lexsort((qidx, br, bd))
    qidx, cidx, bd, br = qidx[order], cidx[order], bd[order], br[order]
    _, first = np.unique(cidx, return_index=True)
    first.sort()
    return Matches(
        query=qidx[first].astype(np.int32),
        candidate=cidx[first].astype(np.int32),
        distance=bd[first].astype(np.int32),
        ratio=br[first].astype(np.float32),
    )
