"""The loss funnel: each positive query lands in the stage that lost its true loop."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stablecues.evaluation import evaluate_detections
from stablecues.evaluation.funnel import STAGES, format_funnel, loss_funnel
from stablecues.runs import RunWriter, load_run

N = 20


def _write(tmp: Path, rows: list[tuple[int, str, int, float, bool, dict[str, object]]]) -> Path:
    w = RunWriter(tmp / "run", {}, {"dataset": "x"}, stages=["total"])
    for frame, status, cand, score, accepted, extra in rows:
        w.add(frame, float(frame), status, cand, score, score, accepted, {"total": 1.0}, extra)
    w.close()
    return tmp / "run"


def _extra(results: list[int], islands: list[tuple[int, int, int]], checked: list[int]) -> dict[str, object]:
    return {"results": [[f, 0.5] for f in results],
            "islands": [[a, b, c, 1.0] for a, b, c in islands],
            "checked": [[f, False, 5, 30] for f in checked]}


def test_every_stage_by_hand(tmp_path: Path) -> None:
    gt = np.zeros((N, N), bool)
    for q in range(10, 20):
        gt[q, q - 10] = True  # query q closes a loop with frame q - 10
    rows = [
        (10, "close_matches_only", -1, float("nan"), False, {}),                          # excluded
        (11, "no_geometrical_consistency", 5, 0.4, False, _extra([5, 6], [(5, 6, 5)], [5])),  # not retrieved
        (12, "low_scores", 7, 0.1, False, _extra([2, 7], [], [])),                         # below alpha
        (13, "no_geometrical_consistency", 7, 0.5, False,
         _extra([7, 3], [(7, 8, 7), (2, 4, 3)], [7])),                                     # wrong island
        (14, "no_temporal_consistency", 4, 0.6, False, _extra([4], [(3, 5, 4)], [])),     # temporal
        (15, "no_geometrical_consistency", 5, 0.6, False, _extra([5], [(5, 5, 5)], [5])),  # geometry
        (16, "loop_detected", 1, 50.0, True, _extra([1], [(1, 1, 1)], [1])),              # wrong accepted
        (17, "loop_detected", 7, 10.0, True, _extra([7], [(7, 7, 7)], [7])),              # below threshold
        (18, "loop_detected", 8, 60.0, True, _extra([8], [(8, 8, 8)], [8])),              # found
        (19, "loop_detected", 9, 70.0, True, _extra([9], [(9, 9, 9)], [9])),              # found
    ]
    run = load_run(_write(tmp_path, rows))
    acc = run.accepted.astype(bool)
    ev = evaluate_detections(gt, run.frames, np.where(acc, run.candidates, -1),
                             np.where(acc, run.scores, 0.0), protocol="exact")
    assert ev.tp_at_100p == 2 and ev.threshold_at_100p == 60.0
    funnel = loss_funnel(run, gt, ev)
    expected = dict(zip(range(10, 20), STAGES[:1] + STAGES[1:] + ("found",), strict=True))
    assert funnel.rows == expected
    assert funnel.counts["found"] == ev.tp_at_100p and funnel.positives == ev.positives == 10
    assert sum(funnel.counts.values()) == funnel.positives
    text = format_funnel(funnel)
    assert "wrong_island" in text and "positive queries" in text


def test_tolerance_widens_the_truth(tmp_path: Path) -> None:
    gt = np.zeros((N, N), bool)
    gt[15, 5] = True
    rows = [(15, "no_geometrical_consistency", 7, 0.5, False, _extra([7], [(7, 7, 7)], [7]))]
    run = load_run(_write(tmp_path, rows))
    cases = (("exact", 0, "not_retrieved"), ("ibow", 2, "geometry"), ("tolerance", 2, "geometry"))
    for protocol, tol, stage in cases:
        ev = evaluate_detections(gt, run.frames, np.array([-1]), np.array([0.0]),
                                 protocol=protocol, tolerance=tol)
        assert loss_funnel(run, gt, ev).rows == {15: stage}, protocol


def test_runs_without_records_say_unknown(tmp_path: Path) -> None:
    gt = np.zeros((N, N), bool)
    gt[15, 5] = True
    run = load_run(_write(tmp_path, [(15, "no_geometrical_consistency", 7, 0.5, False, {"n_features": 3})]))
    ev = evaluate_detections(gt, run.frames, np.array([-1]), np.array([0.0]), protocol="exact")
    assert loss_funnel(run, gt, ev).rows == {15: "unknown"}
