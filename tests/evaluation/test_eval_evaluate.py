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
