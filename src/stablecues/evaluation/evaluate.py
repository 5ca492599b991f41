"""Evaluating a run directory against a loop ground truth: the numbers behind ``stablecues eval``."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..errors import DatasetError, InputError
from ..groundtruth import GroundTruth
from ..runs import Run, read_json, write_json
from .funnel import Funnel, loss_funnel
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
        ``gt_sha256``, ``timing_ms``, ``pr_curve`` and ``funnel`` among others; ``funnel`` is
        :meth:`stablecues.evaluation.funnel.Funnel.to_dict`: for each positive query, the
        stage where its true loop was lost).

    Raises:
        DatasetError: the ground truth is too small for the run, or (when the run's meta
            records ``dataset_frames``) not of the dataset's size.
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
    n_data = run.meta_int("dataset_frames")
    if n_data is not None and gt.n != n_data:
        raise DatasetError(
            f"{gt.path or 'ground truth'}: covers {gt.n} frames, but the run's dataset has {n_data} "
            "(a ground truth of another sequence, or of another view?)"
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
    funnel = loss_funnel(run, matrix, ev, query_mask=mask, times=times)
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
        "funnel": funnel.to_dict(),
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
    return check_evaluation(read_json(Path(path), "evaluation"), path)


def _number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _count(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def _curve(v: object) -> bool:
    if not isinstance(v, dict):
        return False
    r, p = v.get("recall"), v.get("precision")
    return (
        isinstance(r, list) and isinstance(p, list) and len(r) == len(p) and all(map(_number, r + p))
    )


# key -> (check of a value that is present and not null, what it should be)
_EVALUATION_KEYS: dict[str, tuple[Any, str]] = {
    "protocol": (lambda v: v in PROTOCOLS, f"one of {', '.join(PROTOCOLS)}"),
    **{
        k: (_number, "a finite number")
        for k in ("recall_at_100p", "auc", "precision", "recall", "exclude_s")
    },
    **{
        k: (_count, "a whole number >= 0")
        for k in ("tp", "fp", "fn", "positives", "queries", "detections", "tolerance", "exclude")
    },
    **{k: (lambda v: isinstance(v, str), "text") for k in ("gt_file", "gt_sha256", "gt_view", "gt_variable")},
    "detections_used": (lambda v: v in ("accepted", "all"), "'accepted' or 'all'"),
    "score_column": (lambda v: v in ("score", "raw_score"), "'score' or 'raw_score'"),
    "pr_curve": (_curve, "recall and precision lists of numbers of one length"),
    "gt_notes": (lambda v: isinstance(v, dict), "an object"),
}


def check_evaluation(doc: dict[str, Any], source: object) -> dict[str, Any]:
    """``doc`` after checking it is an evaluation document: the keys that tables and reports
    read, of the types they expect.

    Raises:
        DatasetError: naming ``source`` and the first key that is missing or of another type.
    """
    for key in ("protocol", "recall_at_100p", "auc", "tp", "fp", "fn", "positives"):
        if key not in doc:
            raise DatasetError(f"{source}: evaluation file lacks {key!r}")
    for key, (ok, want) in _EVALUATION_KEYS.items():
        if doc.get(key) is not None and not ok(doc[key]):
            raise DatasetError(f"{source}: evaluation {key!r} should be {want}, found {doc[key]!r:.40}")
    if doc.get("funnel") is not None:
        Funnel.from_dict(doc["funnel"], source)
    return doc


def evaluation_funnel(doc: dict[str, Any]) -> Funnel | None:
    """The loss funnel of an evaluation document, or None for one written before it was kept.

    Raises:
        DatasetError: a malformed ``funnel``.
    """
    value = doc.get("funnel")
    return None if value is None else Funnel.from_dict(value, doc.get("run", "evaluation"))


def run_evaluations(run: Run) -> dict[str, dict[str, Any]]:
    """The run's ``eval_*.json`` documents (file stem -> document), each checked.

    Raises:
        DatasetError: a file that is not an evaluation document.
    """
    return {
        stem: check_evaluation(doc, run.path / f"{stem}.json") for stem, doc in run.evaluations().items()
    }
