"""Protocols against hand-computed counts; R@100P and AUC against brute force."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues.errors import InputError
from stablecues.evaluation.metrics import eligible_limit, evaluate_detections


def _small() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    gt = np.zeros((8, 8), bool)
    for i, j in [(5, 1), (6, 2), (6, 3), (7, 0), (3, 2)]:
        gt[i, j] = True
    queries = np.arange(8)
    cand = np.full(8, -1)
    score = np.full(8, np.nan)
    # q2 -> 0: row 2 has no loop.          q3 -> 2: inside the exclusion window (exclude=1).
    # q5 -> 1: exact hit.                  q6 -> 0: wrong, though row 6 has loops at 2 and 3.
    # q7 -> 2: 2 frames off its loop at 0. q4: no detection.
    for q, c, s in [(2, 0, 0.9), (3, 2, 0.6), (5, 1, 0.8), (6, 0, 0.7), (7, 2, 0.95)]:
        cand[q], score[q] = c, s
    return gt, queries, cand, score


def test_exact_hand_computed() -> None:
    gt, q, c, s = _small()
    ev = evaluate_detections(gt, q, c, s, protocol="exact", exclude=1)
    assert (ev.positives, ev.tp, ev.fp, ev.fn) == (3, 1, 4, 2)  # q6: FP and its loop an FN
    assert ev.detections == 5 and ev.queries == 8
    assert ev.recall_at_100p == 0.0 and ev.threshold_at_100p is None  # top score (q7) is wrong
    np.testing.assert_allclose(ev.curve.thresholds, [0.95, 0.9, 0.8, 0.7, 0.6])
    np.testing.assert_array_equal(ev.curve.tp, [0, 0, 1, 1, 1])
    np.testing.assert_array_equal(ev.curve.fp, [1, 2, 2, 3, 4])
    assert ev.auc == pytest.approx(1 / 9)
    assert ev.precision == pytest.approx(0.2) and ev.recall == pytest.approx(1 / 3)
    # without an exclusion window, (3, 2) is a loop and q3's detection is right
    ev0 = evaluate_detections(gt, q, c, s, protocol="exact", exclude=0)
    assert (ev0.positives, ev0.tp, ev0.fp, ev0.fn) == (4, 2, 3, 2)


def test_ibow_hand_computed() -> None:
    gt, q, c, s = _small()
    ev = evaluate_detections(gt, q, c, s, protocol="ibow", tolerance=2, exclude=1)
    assert (ev.positives, ev.tp, ev.fp, ev.fn) == (3, 3, 2, 0)
    np.testing.assert_array_equal(ev.curve.tp, [1, 1, 2, 3, 3])
    assert ev.recall_at_100p == pytest.approx(1 / 3) and ev.threshold_at_100p == 0.95
    assert ev.auc == pytest.approx(29 / 36)
    # tolerance 1: q7's candidate (2 off) and q6's (2 off) are wrong again
    ev1 = evaluate_detections(gt, q, c, s, protocol="ibow", tolerance=1, exclude=1)
    assert (ev1.positives, ev1.tp, ev1.fp, ev1.fn) == (3, 1, 4, 2)


def test_tolerance_hand_computed() -> None:
    gt, q, c, s = _small()
    ev = evaluate_detections(gt, q, c, s, protocol="tolerance", tolerance=1, exclude=1)
    # widened by one row: query 4 becomes positive (row 5 has a loop at 1)
    assert (ev.positives, ev.tp, ev.fp, ev.fn) == (4, 3, 2, 1)
    np.testing.assert_allclose(ev.curve.recall, [0.25, 0.25, 0.5, 0.75, 0.75])
    assert ev.recall_at_100p == pytest.approx(0.25)
    assert ev.auc == pytest.approx(29 / 48)
    ev0 = evaluate_detections(gt, q, c, s, protocol="tolerance", tolerance=0, exclude=1)
    ex = evaluate_detections(gt, q, c, s, protocol="exact", exclude=1)
    assert ev0.to_dict() == ex.to_dict() | {"protocol": "tolerance"}


def test_query_mask_and_subset_of_frames() -> None:
    gt, q, c, s = _small()
    mask = np.arange(8) >= 5
    ev = evaluate_detections(gt, q, c, s, protocol="exact", exclude=1, query_mask=mask)
    assert (ev.queries, ev.positives, ev.tp, ev.fp, ev.fn) == (3, 3, 1, 2, 2)
    # a run that stopped after frame 5: later frames are not queries
    ev = evaluate_detections(gt, q[:6], c[:6], s[:6], protocol="exact", exclude=1)
    assert (ev.queries, ev.positives, ev.tp, ev.fp) == (6, 1, 1, 2)


def test_no_detections_and_no_positives() -> None:
    gt = np.zeros((4, 4), bool)
    ev = evaluate_detections(gt, np.arange(4), np.full(4, -1), np.zeros(4))
    assert (ev.positives, ev.tp, ev.fp, ev.fn, ev.recall_at_100p, ev.auc) == (0, 0, 0, 0, 0.0, 0.0)
    assert ev.curve.thresholds.size == 0 and ev.precision == 1.0
    ev = evaluate_detections(gt, np.zeros(0, int), np.zeros(0, int), np.zeros(0))
    assert ev.queries == 0


def test_bad_inputs() -> None:
    gt, q, c, s = _small()
    bad = c.copy()
    bad[5] = 5
    with pytest.raises(InputError, match="not an earlier frame"):
        evaluate_detections(gt, q, bad, s)
    with pytest.raises(InputError, match="duplicates"):
        evaluate_detections(gt, np.zeros(8, int), c, s)
    with pytest.raises(InputError, match="protocol"):
        evaluate_detections(gt, q, c, s, protocol="fuzzy")  # type: ignore[arg-type]
    nan = s.copy()
    nan[5] = np.nan
    with pytest.raises(InputError, match="finite"):
        evaluate_detections(gt, q, c, nan)
    with pytest.raises(InputError, match="timestamps"):
        evaluate_detections(gt, q, c, s, exclude_s=1.0)


def test_exclusion_in_seconds() -> None:
    times = np.array([0.0, 0.1, 0.2, 5.0, 5.1, 9.0])
    limit = eligible_limit(6, 0, exclude_s=1.0, times=times)
    assert limit.tolist() == [-1, -1, -1, 2, 2, 4]
    assert eligible_limit(4, 2).tolist() == [-1, -1, -1, 0]


def _brute_force(gt: np.ndarray, c: np.ndarray, s: np.ndarray, exclude: int) -> tuple[float, float]:
    n = gt.shape[0]
    rows = np.arange(n)
    eligible = rows[None, :] < (rows[:, None] - exclude)
    positives = (gt & eligible).any(axis=1).sum()
    det = c >= 0
    right = np.zeros(n, bool)
    right[det] = gt[rows[det], c[det]] & (rows[det] - c[det] > exclude)
    best, points = 0.0, []
    for t in sorted(set(s[det].tolist()), reverse=True):
        acc = det & (s >= t)
        tp, fp = int((acc & right).sum()), int((acc & ~right).sum())
        rec = tp / positives
        points.append((rec, tp / (tp + fp)))
        if fp == 0:
            best = max(best, rec)
    ap, prev = 0.0, 0.0
    for rec, prec in points:
        ap += (rec - prev) * prec
        prev = rec
    return best, ap


@pytest.mark.parametrize("seed", range(5))
def test_r100p_equals_brute_force_sweep(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 120
    gt = np.tril(rng.random((n, n)) < 0.03, -1)
    c = np.array([rng.integers(0, i) if i > 0 and rng.random() < 0.7 else -1 for i in range(n)])
    for i in np.flatnonzero(gt[:, :-4].any(axis=1)):  # half the looping rows detect a loop
        loops = np.flatnonzero(gt[i, : max(i - 3, 0)])
        if loops.size and rng.random() < 0.5:
            c[i] = rng.choice(loops)
    # scores with ties; correct detections tend to score higher
    s = np.round(rng.random(n), 1)
    hit = (c >= 0) & gt[np.arange(n), np.maximum(c, 0)]
    s[hit] += 0.5
    ev = evaluate_detections(gt, np.arange(n), c, s, protocol="exact", exclude=3)
    best, ap = _brute_force(gt, c, s, 3)
    assert ev.tp > 10 and 0 < best < 1  # a meaningful case
    assert ev.recall_at_100p == pytest.approx(best)
    assert ev.auc == pytest.approx(ap)
