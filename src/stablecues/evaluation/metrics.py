"""Loop-closure metrics under the published ground-truth protocols, side by side.

Input: for each evaluated query frame ``i`` at most one detection, a candidate frame ``c < i``
and a score (higher = more confident); ``c = -1`` means no detection. The ground truth follows
the project convention (``gt[i, j]``: query ``i`` closes a loop with earlier frame ``j``).

**Exclusion window.** The ``exclude`` frames just before a query are never loops: frame ``j`` is
*eligible* for query ``i`` only when ``i - j > exclude`` (and, when ``exclude_s > 0``, when
``times[i] - times[j] > exclude_s``). Ground-truth loops with ineligible frames are ignored, and
a detection of an ineligible frame is a false positive.

**Protocols** (``n`` = ``tolerance``; with ``n = 0`` both tolerant protocols equal "exact"):

* ``exact``: a detection ``(i, c)`` is correct when ``gt[i, c]``. A query is *positive* when its
  row has an eligible loop.
* ``ibow`` (iBoW-LCD): one candidate per query; correct when row ``i`` has an eligible loop at
  some ``j`` with ``|j - c| <= n``. Positives as in ``exact``.
* ``tolerance``: the ground truth is widened by ``n`` frames on both axes: correct when some
  eligible loop ``(i', j)`` has ``|i' - i| <= n`` and ``|j - c| <= n``. A query is positive when
  its row of the widened matrix has an eligible cell, i.e. when such a detection was possible.

**Counting.** At a score threshold ``t`` the accepted detections are those with ``score >= t``.
TP = accepted and correct. FP = accepted and wrong; this includes a wrong detection made by a
positive query: that query then ALSO counts as a false negative, because its loop was missed.
FN = positives - TP. Precision = TP / (TP + FP) (1 when nothing is accepted), recall =
TP / positives (0 when there are no positives).

**Sweep.** Every distinct detection score is a threshold (never a fixed grid). Recall at 100 %
precision (R@100P) is the largest recall over thresholds with FP = 0. The area under the PR
curve is the step-wise average precision ``sum_k (R_k - R_{k-1}) P_k`` over thresholds in
decreasing order (as scikit-learn's ``average_precision_score``), so a curve that never reaches
a recall ``r`` contributes nothing beyond it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from ..errors import InputError, check_array

ProtocolName = Literal["exact", "tolerance", "ibow"]
PROTOCOLS: tuple[str, ...] = ("exact", "tolerance", "ibow")


@dataclass(frozen=True)
class PRCurve:
    """Precision and recall at every distinct score, thresholds decreasing.

    Attributes:
        thresholds: (K,) float64 distinct detection scores, decreasing.
        precision: (K,) float64 precision when accepting scores >= each threshold.
        recall: (K,) float64 recall at the same thresholds.
        tp: (K,) int64 true positives at each threshold.
        fp: (K,) int64 false positives at each threshold.
    """

    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    tp: np.ndarray
    fp: np.ndarray

    def to_dict(self) -> dict[str, list[float] | list[int]]:
        return {
            "thresholds": [float(v) for v in self.thresholds],
            "precision": [float(v) for v in self.precision],
            "recall": [float(v) for v in self.recall],
            "tp": [int(v) for v in self.tp],
            "fp": [int(v) for v in self.fp],
        }


@dataclass(frozen=True)
class Evaluation:
    """The metrics of one set of detections under one protocol.

    Attributes:
        protocol: "exact", "tolerance" or "ibow".
        tolerance: ``n`` of the tolerant protocols (0 for exact).
        exclude: exclusion window in frames.
        exclude_s: exclusion window in seconds (0: none).
        queries: number of evaluated query frames.
        detections: number of queries with a detection.
        positives: queries that have an eligible loop (see the module docstring).
        tp, fp, fn: counts when every detection is accepted (the detector's own decisions).
        precision, recall: at that same operating point.
        recall_at_100p: largest recall with no false positive, over every distinct score.
        threshold_at_100p: the score threshold reaching it, or None when it is 0.
        tp_at_100p: true positives at that threshold.
        auc: area under the precision-recall curve (step-wise average precision).
        curve: the whole precision-recall curve.
        correct: (M,) bool correctness of each detection, in the order of ``detection_frames``.
        detection_frames: (M,) int64 query frame of each detection.
        unscored: detections in frames that are not queries (``query_mask`` False: the
            reference pass of a two-pass set), left out of every count above.
    """

    protocol: str
    tolerance: int
    exclude: int
    exclude_s: float
    queries: int
    detections: int
    positives: int
    tp: int
    fp: int
    fn: int
    precision: float
    recall: float
    recall_at_100p: float
    threshold_at_100p: float | None
    tp_at_100p: int
    auc: float
    curve: PRCurve
    correct: np.ndarray = field(repr=False)
    detection_frames: np.ndarray = field(repr=False)
    unscored: int = 0

    def to_dict(self, *, curve: bool = True) -> dict[str, Any]:
        """JSON-ready summary (the PR curve included unless ``curve=False``)."""
        out: dict[str, Any] = {
            "protocol": self.protocol,
            "tolerance": self.tolerance,
            "exclude": self.exclude,
            "exclude_s": self.exclude_s,
            "queries": self.queries,
            "detections": self.detections,
            "positives": self.positives,
            "tp": self.tp,
            "fp": self.fp,
            "fn": self.fn,
            "precision": self.precision,
            "recall": self.recall,
            "recall_at_100p": self.recall_at_100p,
            "threshold_at_100p": self.threshold_at_100p,
            "tp_at_100p": self.tp_at_100p,
            "auc": self.auc,
            "unscored_detections": self.unscored,
        }
        if curve:
            out["pr_curve"] = self.curve.to_dict()
        return out


def eligible_limit(
    n: int, exclude: int = 0, *, exclude_s: float = 0.0, times: np.ndarray | None = None
) -> np.ndarray:
    """Largest eligible earlier frame for each query (see the module docstring).

    Args:
        n: number of frames.
        exclude: frames just before a query that are never loops (>= 0).
        exclude_s: seconds just before a query that are never loops (>= 0).
        times: (n,) float64 non-decreasing timestamps; needed when ``exclude_s > 0``.

    Returns:
        (n,) int64: frame ``j`` is eligible for query ``i`` iff ``j <= limit[i]`` (-1: none).
    """
    if exclude < 0 or exclude_s < 0:
        raise InputError(f"exclusion window must be >= 0, got exclude={exclude}, exclude_s={exclude_s}")
    idx = np.arange(n, dtype=np.int64)
    limit = idx - int(exclude) - 1
    if exclude_s > 0:
        if times is None:
            raise InputError(f"exclude_s={exclude_s} needs the frame timestamps")
        t = np.asarray(times, dtype=np.float64)
        check_array("times", t, shape=(n,))
        if not np.isfinite(t).all() or np.any(np.diff(t) < 0):
            raise InputError("times: exclude_s needs finite, non-decreasing timestamps for every frame")
        # last j with t[j] < t[i] - exclude_s
        by_time = np.searchsorted(t, t - exclude_s, side="left") - 1
        limit = np.minimum(limit, by_time)
    return np.maximum(limit, -1)


def evaluate_detections(
    gt: np.ndarray,
    queries: np.ndarray,
    candidates: np.ndarray,
    scores: np.ndarray,
    *,
    protocol: ProtocolName = "exact",
    tolerance: int = 0,
    exclude: int = 0,
    exclude_s: float = 0.0,
    times: np.ndarray | None = None,
    query_mask: np.ndarray | None = None,
) -> Evaluation:
    """Score one detection per query against a loop matrix under a protocol.

    Args:
        gt: (N, N) bool lower-triangular loop matrix (the project convention).
        queries: (M,) int frame index of each evaluated query, unique, in [0, N). Frames not
            listed (not processed) are neither queries nor positives.
        candidates: (M,) int detected earlier frame per query, -1 for none.
        scores: (M,) float confidence per detection (higher = more confident); ignored where
            the candidate is -1, must be finite elsewhere.
        protocol: "exact", "tolerance" or "ibow" (module docstring).
        tolerance: ``n`` frames for the tolerant protocols (ignored by "exact").
        exclude: exclusion window in frames.
        exclude_s: exclusion window in seconds (needs ``times``).
        times: (N,) float64 frame timestamps.
        query_mask: (N,) bool frames that count as queries (two-pass sets), or None for all.

    Returns:
        The :class:`Evaluation`.

    Raises:
        InputError: bad shapes, unknown protocol, duplicate queries, a candidate that is not
            an earlier frame, or a non-finite score of a detection.
    """
    check_array("ground truth", gt, dtype=bool, ndim=2)
    n = gt.shape[0]
    if gt.shape != (n, n):
        raise InputError(f"ground truth: expected a square matrix, got {gt.shape}")
    tol = _protocol_tolerance(protocol, tolerance)
    q, c, s = _check_detections(n, queries, candidates, scores)
    detected = c >= 0
    unscored = 0
    if query_mask is not None:
        check_array("query_mask", query_mask, dtype=bool, shape=(n,))
        keep = query_mask[q]
        unscored = int(np.count_nonzero(detected & ~keep))
        q, c, s, detected = q[keep], c[keep], s[keep], detected[keep]

    limit = eligible_limit(n, exclude, exclude_s=exclude_s, times=times)
    positives = int(_positive_rows(gt, limit, protocol, tol)[q].sum())
    dq, dc, ds = q[detected], c[detected], s[detected]
    correct = _correct_detections(gt, limit, dq, dc, protocol, tol)

    curve = pr_curve(ds, correct, positives)
    r100, t100, tp100 = recall_at_full_precision(curve)
    tp = int(correct.sum())
    fp = int(dq.size - tp)
    return Evaluation(
        protocol=protocol,
        tolerance=tol,
        exclude=int(exclude),
        exclude_s=float(exclude_s),
        queries=int(q.size),
        detections=int(dq.size),
        positives=positives,
        tp=tp,
        fp=fp,
        fn=positives - tp,
        precision=tp / (tp + fp) if tp + fp else 1.0,
        recall=tp / positives if positives else 0.0,
        recall_at_100p=r100,
        threshold_at_100p=t100,
        tp_at_100p=tp100,
        auc=average_precision(curve),
        curve=curve,
        correct=correct,
        detection_frames=dq,
        unscored=unscored,
    )


def _protocol_tolerance(protocol: str, tolerance: int) -> int:
    """The tolerance ``n`` the protocol uses (0 for "exact").

    Raises:
        InputError: an unknown protocol or a negative tolerance.
    """
    if protocol not in PROTOCOLS:
        raise InputError(f"protocol: expected one of {', '.join(PROTOCOLS)}, got {protocol!r}")
    tol = 0 if protocol == "exact" else int(tolerance)
    if tol < 0:
        raise InputError(f"tolerance: expected >= 0, got {tolerance}")
    return tol


def _check_detections(
    n: int, queries: np.ndarray, candidates: np.ndarray, scores: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Queries, candidates and scores as flat (M,) int64, int64 and float64 arrays, checked.

    Raises:
        InputError: unequal lengths, a query outside [0, n), duplicate queries, a candidate
            that is not an earlier frame (or -1), or a non-finite score of a detection.
    """
    q = np.asarray(queries, dtype=np.int64).ravel()
    c = np.asarray(candidates, dtype=np.int64).ravel()
    s = np.asarray(scores, dtype=np.float64).ravel()
    if not (q.shape == c.shape == s.shape):
        raise InputError(
            f"queries, candidates, scores: expected equal lengths, got {q.size}, {c.size}, {s.size}"
        )
    if q.size and (q.min() < 0 or q.max() >= n):
        raise InputError(f"queries: expected frame indices in [0, {n}), got range [{q.min()}, {q.max()}]")
    if np.unique(q).size != q.size:
        raise InputError("queries: each frame may be evaluated once, found duplicates")
    detected = c >= 0
    if np.any(c < -1) or np.any(c[detected] >= q[detected]):
        bad = int(np.flatnonzero((c < -1) | (detected & (c >= q)))[0])
        raise InputError(f"frame {q[bad]}: candidate {c[bad]} is not an earlier frame (or -1 for none)")
    if not np.isfinite(s[detected]).all():
        raise InputError("scores: every detection needs a finite score")
    return q, c, s


def _positive_rows(gt: np.ndarray, limit: np.ndarray, protocol: str, tol: int) -> np.ndarray:
    """(N,) bool: the frames that are positive queries under the protocol (module docstring)."""
    n = gt.shape[0]
    has_loop = gt.any(axis=1)
    first = np.where(has_loop, gt.argmax(axis=1), n)
    first_eligible = np.where(first <= limit, first, n)  # earliest eligible loop column per row
    if protocol == "tolerance" and tol > 0:
        # row i is positive iff some row i' within +-tol has an eligible loop j <= limit[i] + tol
        padded = np.concatenate([np.full(tol, n), first_eligible, np.full(tol, n)])
        windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * tol + 1)
        nearest_first = windows.min(axis=1)
        return (limit >= 0) & (nearest_first < n) & (nearest_first <= limit + tol)
    return first_eligible < n


def _correct_detections(
    gt: np.ndarray, limit: np.ndarray, dq: np.ndarray, dc: np.ndarray, protocol: str, tol: int
) -> np.ndarray:
    """(M,) bool: whether detection ``(dq[k], dc[k])`` is correct under the protocol."""
    correct = np.zeros(dq.size, dtype=bool)
    for k, (i, j) in enumerate(zip(dq.tolist(), dc.tolist(), strict=True)):
        if j > limit[i]:
            continue
        if tol == 0:
            correct[k] = gt[i, j]
        elif protocol == "ibow":
            correct[k] = gt[i, max(0, j - tol) : min(j + tol, int(limit[i])) + 1].any()
        else:
            correct[k] = _near_widened_loop(gt, limit, i, j, tol)
    return correct


def _near_widened_loop(gt: np.ndarray, limit: np.ndarray, i: int, j: int, tol: int) -> bool:
    """Whether some eligible loop ``(r, j')`` has ``|r - i| <= tol`` and ``|j' - j| <= tol``."""
    n = gt.shape[0]
    for r in range(max(0, i - tol), min(n, i + tol + 1)):
        hi = min(j + tol, int(limit[r]))
        if hi >= max(0, j - tol) and gt[r, max(0, j - tol) : hi + 1].any():
            return True
    return False


def pr_curve(scores: np.ndarray, correct: np.ndarray, positives: int) -> PRCurve:
    """Precision and recall at every distinct score.

    Args:
        scores: (M,) float64 detection scores.
        correct: (M,) bool whether each detection is a true positive.
        positives: number of positive queries (the recall denominator).

    Returns:
        The :class:`PRCurve`, thresholds decreasing (empty when there is no detection).
    """
    s = np.asarray(scores, dtype=np.float64)
    ok = np.asarray(correct, dtype=bool)
    if s.shape != ok.shape:
        raise InputError(f"scores and correct: expected equal shapes, got {s.shape} and {ok.shape}")
    order = np.argsort(-s, kind="stable")
    s_sorted, ok_sorted = s[order], ok[order]
    cum_tp = np.cumsum(ok_sorted, dtype=np.int64)
    cum_fp = np.arange(1, s.size + 1, dtype=np.int64) - cum_tp
    # last index of each group of equal scores
    ends = np.flatnonzero(np.r_[s_sorted[1:] != s_sorted[:-1], True]) if s.size else np.zeros(0, np.int64)
    tp, fp = cum_tp[ends], cum_fp[ends]
    precision = tp / np.maximum(tp + fp, 1)
    recall = tp / positives if positives else np.zeros(tp.size)
    return PRCurve(s_sorted[ends], precision.astype(np.float64), np.asarray(recall, np.float64), tp, fp)


def recall_at_full_precision(curve: PRCurve) -> tuple[float, float | None, int]:
    """(R@100P, its threshold or None, its TP count): largest recall over thresholds with FP = 0."""
    clean = np.flatnonzero(curve.fp == 0)
    if clean.size == 0 or curve.tp[clean[-1]] == 0:
        return 0.0, None, 0
    k = int(clean[-1])  # FP grows as the threshold falls: the clean thresholds are a prefix
    return float(curve.recall[k]), float(curve.thresholds[k]), int(curve.tp[k])


def average_precision(curve: PRCurve) -> float:
    """Step-wise area under the PR curve: ``sum_k (R_k - R_{k-1}) P_k`` with ``R_0 = 0``."""
    if curve.recall.size == 0:
        return 0.0
    steps = np.diff(np.r_[0.0, curve.recall])
    return float(np.sum(steps * curve.precision))
