"""Evaluating a run directory against a loop ground truth: the numbers behind ``stablecues eval``."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..errors import DatasetError, InputError
from ..groundtruth import GroundTruth
from ..runs import Run, read_json, write_json
from .metrics import PROTOCOLS, Evaluation, ProtocolName, evaluate_detections

DetectionChoice = Literal["accepted", "all"]
ScoreChoice = Literal["score", "raw_score"]


def run_detections(
    run: Run, *, detections: DetectionChoice = "accepted", score: ScoreChoice = "score"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (queries, candidates, scores) of a run that the metrics score.

    Args:
        run: the run.
        detections: "accepted" (a frame's candidate counts only when the detector accepted
            it) or "all" (every frame's candidate counts, whatever stage rejected it: the PR
            sweep then shows what a pure score threshold would give).
        score: which score column ranks detections: "score" (normalised) or "raw_score".

    Returns:
        (M,) int64 query frames, (M,) int64 candidates (-1 none), (M,) float64 scores.
    """
    if detections not in ("accepted", "all"):
        raise InputError(f"detections: expected 'accepted' or 'all', got {detections!r}")
    if score not in ("score", "raw_score"):
        raise InputError(f"score: expected 'score' or 'raw_score', got {score!r}")
    cands = run.candidates.copy()
    if detections == "accepted":
        cands[~run.accepted] = -1
    values = (run.scores if score == "score" else run.raw_scores).copy()
    bad = (cands >= 0) & ~np.isfinite(values)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise DatasetError(
            f"{run.path}: frame {run.frames[k]} has candidate {cands[k]} but no finite {score}"
        )
    return run.frames.copy(), cands, values


def evaluate_run(
    run: Run,
    gt: GroundTruth,
    *,
    protocol: ProtocolName = "exact",
    tolerance: int = 0,
    exclude: int = 0,
    exclude_s: float = 0.0,
    detections: DetectionChoice = "accepted",
    score: ScoreChoice = "score",
) -> tuple[Evaluation, dict[str, Any]]:
    """Evaluate a run: the metrics, and the JSON document ``stablecues eval`` writes.

    Only the frames the run processed are queries (a run stopped early is scored on its
    prefix); two-pass sets also restrict queries to the ground truth's ``query_mask``.

    Args:
        run: the run directory, loaded.
        gt: the ground truth; it must cover every frame of the run.
        protocol, tolerance, exclude, exclude_s: see :mod:`stablecues.evaluation.metrics`.
        detections, score: see :func:`run_detections`.

    Returns:
        (the :class:`Evaluation`, a JSON-ready dict with ``recall_at_100p``, ``auc``, ``tp``,
        ``fp``, ``fn``, ``positives``, ``protocol``, ``tolerance``, ``exclude``, ``gt_file``,
        ``gt_sha256``, ``timing_ms`` and ``pr_curve`` among others).

    Raises:
        DatasetError: the ground truth is too small for the run.
        InputError: bad settings.
    """
    if protocol not in PROTOCOLS:
        raise InputError(f"protocol: expected one of {', '.join(PROTOCOLS)}, got {protocol!r}")
    queries, cands, scores = run_detections(run, detections=detections, score=score)
    n_run = int(queries[-1]) + 1 if queries.size else 0
    if n_run > gt.n:
        hint = ""
        if gt.n * 2 == n_run or gt.n == n_run * 2:
            hint = " (an interleaved left/right release? choose a view of the ground truth)"
        raise DatasetError(
            f"{gt.path or 'ground truth'}: covers {gt.n} frames, but the run has frame {n_run - 1}{hint}"
        )
    matrix, mask, times = gt.matrix, gt.query_mask, None
    if exclude_s > 0:
        if not np.array_equal(queries, np.arange(n_run)) or not np.isfinite(run.timestamps).all():
            raise InputError("exclude_s needs a run with every frame 0..N-1 processed and timestamped")
        matrix, times = matrix[:n_run, :n_run], run.timestamps
        mask = None if mask is None else mask[:n_run]
    ev = evaluate_detections(
        matrix,
        queries,
        cands,
        scores,
        protocol=protocol,
        tolerance=tolerance,
        exclude=exclude,
        exclude_s=exclude_s,
        times=times,
        query_mask=mask,
    )
    doc: dict[str, Any] = {
        "run": str(run.path),
        **ev.to_dict(curve=False),
        **gt.provenance(),
        "detections_used": detections,
        "score_column": score,
        "run_frames": len(run),
        "run_complete": run.complete,
        "dataset": run.meta.get("dataset"),
        "preset": run.meta.get("preset"),
        "status_counts": run.status_counts(),
        "timing_ms": run.timings(),
        "pr_curve": ev.curve.to_dict(),
    }
    return ev, doc


def eval_file_name(protocol: str, tolerance: int) -> str:
    """Name of the evaluation file inside a run directory: ``eval_<protocol>[_<n>].json``.

    The exact protocol (and a tolerant one with n = 0) is ``eval_<protocol>.json``; a tolerant
    one keeps its n so that several tolerances can sit side by side.
    """
    return (
        f"eval_{protocol}.json"
        if tolerance == 0 or protocol == "exact"
        else f"eval_{protocol}_{tolerance}.json"
    )


def save_evaluation(doc: dict[str, Any], path: str | Path) -> Path:
    """Write an evaluation document as strict JSON (atomic)."""
    p = Path(path)
    write_json(p, doc)
    return p


def load_evaluation(path: str | Path) -> dict[str, Any]:
    """Read an evaluation JSON file written by :func:`save_evaluation`.

    Raises:
        DatasetError: missing or invalid file, or one without the expected keys.
    """
    doc = read_json(Path(path), "evaluation")
    for key in ("protocol", "recall_at_100p", "auc", "tp", "fp", "fn", "positives"):
        if key not in doc:
            raise DatasetError(f"{path}: evaluation file lacks {key!r}")
    return doc
