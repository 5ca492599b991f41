"""stablecues.evaluation.evaluate: scoring a run directory against a ground truth."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from stablecues.errors import DatasetError
from stablecues.evaluation.evaluate import eval_file_name, evaluate_run
from stablecues.groundtruth import GroundTruth
from stablecues.runs import RunWriter, load_run

STAGES = ["features", "bow", "verify"]


def _write(path: Path, n: int = 6) -> None:
    """The run of tests/runs/test_runs_store.py: frames 3..5 detect frame i - 3, odd ones accepted."""
    w = RunWriter(path, {"preset": "bow", "k": 10}, {"dataset": "/data/x", "format": "folder"}, stages=STAGES)
    for i in range(n):
        cand = i - 3 if i >= 3 else -1
        w.add(
            i,
            0.1 * i,
            "accepted" if i % 2 else "low_score",
            cand,
            0.5 + 0.05 * i if cand >= 0 else math.nan,
            0.01 * i,
            bool(i % 2) and cand >= 0,
            {"features": 1.0 + i, "bow": 0.5} if i != 4 else {"features": 2.0},
            {"n_keypoints": 100 + i} if i == 2 else None,
        )
    w.set_similarity(np.tril(np.full((n, n), 0.25)))
    w.close()


def test_evaluate_run(tmp_path: Path) -> None:
    _write(tmp_path / "run")
    run = load_run(tmp_path / "run")
    gt = np.zeros((8, 8), bool)
    gt[3, 0] = gt[5, 2] = gt[4, 0] = True
    ev, doc = evaluate_run(run, GroundTruth(gt), protocol="exact", exclude=1)
    # accepted detections: 3->0 (right), 5->2 (right); 4->1 not accepted; queries 0..5
    assert (ev.positives, ev.tp, ev.fp, ev.fn) == (3, 2, 0, 1)
    assert doc["recall_at_100p"] == pytest.approx(2 / 3)
    for key in (
        "auc",
        "gt_sha256",
        "gt_file",
        "tolerance",
        "exclude",
        "timing_ms",
        "pr_curve",
        "status_counts",
    ):
        assert key in doc
    ev_all, _ = evaluate_run(run, GroundTruth(gt), detections="all", exclude=1)
    assert (ev_all.tp, ev_all.fp) == (2, 1)
    with pytest.raises(DatasetError, match="covers 4 frames"):
        evaluate_run(run, GroundTruth(np.zeros((4, 4), bool)))
    assert eval_file_name("exact", 0) == "eval_exact.json"
    assert eval_file_name("ibow", 2) == "eval_ibow_2.json"


def test_a_ground_truth_of_another_size_than_the_dataset_is_refused(tmp_path: Path) -> None:
    w = RunWriter(tmp_path / "run", {}, {"dataset_frames": 6}, stages=["total"])
    for i in range(6):
        w.add(i, float(i), "x", -1, math.nan, math.nan, False, {"total": 1.0})
    w.close()
    run = load_run(tmp_path / "run")
    with pytest.raises(DatasetError, match="covers 40 frames, but the run's dataset has 6"):
        evaluate_run(run, GroundTruth(np.zeros((40, 40), bool)))
    ev, _ = evaluate_run(run, GroundTruth(np.zeros((6, 6), bool)))
    assert ev.queries == 6


def test_detections_outside_the_queries_are_counted(tmp_path: Path) -> None:
    from stablecues.evaluation.metrics import evaluate_detections

    gt = np.zeros((6, 6), bool)
    gt[4, 1] = gt[5, 2] = True
    mask = np.array([False, False, False, True, True, True])
    ev = evaluate_detections(gt, np.arange(6), np.array([-1, -1, 0, 1, 1, 2]), np.ones(6), query_mask=mask)
    assert ev.unscored == 1 and ev.detections == 3 and ev.to_dict()["unscored_detections"] == 1


def test_evaluation_documents_are_checked(tmp_path: Path) -> None:
    from stablecues.evaluation.evaluate import check_evaluation

    good = {"protocol": "exact", "recall_at_100p": 0.5, "auc": 0.4, "tp": 1, "fp": 0, "fn": 1, "positives": 2}
    assert check_evaluation(dict(good), "e.json") == good
    for key, value in (("tolerance", "x"), ("auc", "high"), ("protocol", "fuzzy"), ("tp", -1),
                       ("pr_curve", {"recall": [0.1], "precision": []})):
        with pytest.raises(DatasetError, match=f"e.json: evaluation '{key}' should be"):
            check_evaluation({**good, key: value}, "e.json")
