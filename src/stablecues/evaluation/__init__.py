"""Evaluation: loop ground truth, protocols and metrics, timing tables, run directories,
plots and reports.

Typical use::

    from stablecues.evaluation import load_ground_truth, load_run, evaluate_run

    gt = load_ground_truth("NewCollegeGroundTruth.mat", view="left")
    ev, doc = evaluate_run(load_run("runs/nc"), gt, protocol="ibow", tolerance=2, exclude=40)
    print(ev.recall_at_100p, ev.auc, ev.tp, ev.fp, ev.fn, ev.positives)
"""

from __future__ import annotations

from ..groundtruth import (
    GroundTruth,
    check_loop_matrix,
    fit_view,
    ground_truth_from_poses,
    load_ground_truth,
    loops_from_poses,
    orient,
    save_ground_truth,
    select_view,
    sha256_file,
    vprbench_matrix,
)
from ..runs import Run, RunWriter, format_timing_table, load_run, timing_table
from .evaluate import eval_file_name, evaluate_run, load_evaluation, run_detections, save_evaluation
from .metrics import (
    PROTOCOLS,
    Evaluation,
    PRCurve,
    average_precision,
    eligible_limit,
    evaluate_detections,
    pr_curve,
    recall_at_full_precision,
)

__all__ = [
    "PROTOCOLS",
    "Evaluation",
    "GroundTruth",
    "PRCurve",
    "Run",
    "RunWriter",
    "average_precision",
    "check_loop_matrix",
    "eligible_limit",
    "eval_file_name",
    "fit_view",
    "evaluate_detections",
    "evaluate_run",
    "format_timing_table",
    "ground_truth_from_poses",
    "load_evaluation",
    "load_ground_truth",
    "load_run",
    "loops_from_poses",
    "orient",
    "pr_curve",
    "recall_at_full_precision",
    "run_detections",
    "save_evaluation",
    "save_ground_truth",
    "select_view",
    "sha256_file",
    "timing_table",
    "vprbench_matrix",
]
