"""Where loops are lost: for every positive query, the stage at which its true loop was lost.

The detector's pipeline is a funnel: the database query returns the top-N entries, those under
``alpha`` are dropped, the rest are grouped into islands, the best island must be temporally
consistent, the best islands are verified, and an accepted loop counts in the recall at 100 %
precision only when its confidence is above the highest-scoring false positive. For each query
that has an eligible loop (a *positive* of :mod:`.metrics`), the first stage its true loop did
not pass is, in pipeline order:

=================== ==============================================================================
``excluded``        nothing could be proposed (no entry outside the exclusion window, no database
                    result, or no previous frame to normalise scores)
``not_retrieved``   no true loop among the top-N database results
``below_alpha``     true loops were retrieved, but none in an island that passed ``alpha``
``wrong_island``    a true loop was in an island that passed ``alpha``, but not in one that was
                    verified (or, with a temporal window, not in the best one)
``temporal``        the true island was there, but temporal consistency stopped the frame
``geometry``        a true loop was verified and rejected (by the geometry, or its confidence
                    was under the detector's ``min_confidence``), and nothing else was accepted
``wrong_accepted``  a wrong loop was accepted instead (a false positive of this query)
``below_threshold`` the true loop was accepted, below the 100 %-precision threshold
``found``           accepted above the threshold: counted in the recall at 100 % precision
=================== ==============================================================================

It reads what ``stablecues run`` keeps per frame in ``extra.jsonl`` (the results, the islands and
the checked candidates, as frame indices; see
:meth:`stablecues.detection.LoopDecision.extras`). Runs written before these were kept give
``unknown`` for the stages they need.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import DatasetError
from ..runs import Run
from .metrics import Evaluation, eligible_limit

__all__ = ["STAGES", "Funnel", "format_funnel", "loss_funnel"]

STAGES: tuple[str, ...] = (
    "excluded",
    "not_retrieved",
    "below_alpha",
    "wrong_island",
    "temporal",
    "geometry",
    "wrong_accepted",
    "below_threshold",
    "found",
)
"""The stages in pipeline order (``unknown`` is added when a run lacks the records)."""

_NOTHING_PROPOSED = {"close_matches_only", "no_db_results", "low_nss_factor"}


@dataclass(frozen=True)
class Funnel:
    """The loss funnel of one evaluated run.

    Attributes:
        counts: stage -> number of positive queries lost there (``found`` included).
        rows: positive query frame -> its stage.
        positives: number of positive queries (the sum of ``counts``).
    """

    counts: dict[str, int]
    rows: dict[int, str]
    positives: int

    def to_dict(self) -> dict[str, object]:
        """JSON-ready: ``{"counts": {stage: n}, "positives": n, "rows": {"frame": stage}}``."""
        return {"counts": dict(self.counts), "positives": self.positives,
                "rows": {str(k): v for k, v in sorted(self.rows.items())}}

    @classmethod
    def from_dict(cls, doc: object, source: object = "funnel") -> Funnel:
        """The funnel of an evaluation file's ``"funnel"`` object (see :meth:`to_dict`).

        Raises:
            DatasetError: naming ``source``: not an object, unknown stages, counts that are not
                whole numbers >= 0 or do not add up to ``positives``, or malformed rows.
        """
        if not isinstance(doc, Mapping):
            raise DatasetError(f"{source}: the funnel should be an object, found {doc!r:.40}")
        counts, positives, rows = doc.get("counts"), doc.get("positives"), doc.get("rows", {})
        known = (*STAGES, "unknown")
        if not isinstance(counts, Mapping) or not all(
            k in known and _count(v) for k, v in counts.items()
        ):
            raise DatasetError(f"{source}: funnel counts should map stages ({', '.join(known)}) "
                               f"to whole numbers >= 0, found {counts!r:.60}")
        if not _count(positives) or sum(counts.values()) != positives:
            raise DatasetError(f"{source}: funnel positives should be the sum of its counts "
                               f"({sum(counts.values())}), found {positives!r:.20}")
        if not isinstance(rows, Mapping) or not all(
            isinstance(k, str) and k.isdigit() and v in known for k, v in rows.items()
        ):
            raise DatasetError(f"{source}: funnel rows should map frame numbers to stages")
        return cls({str(k): int(v) for k, v in counts.items()},
                   {int(k): str(v) for k, v in rows.items()}, int(positives))


def _count(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def _truth_mask(gt: np.ndarray, limit: np.ndarray, i: int, tol: int) -> np.ndarray:
    """(N,) bool: the earlier frames that are a correct candidate for query ``i``."""
    n = gt.shape[0]
    rows = gt[max(0, i - tol): min(n, i + tol + 1)].copy()
    for k, r in enumerate(range(max(0, i - tol), min(n, i + tol + 1))):
        rows[k, max(int(limit[r]) + 1, 0):] = False
    hit: np.ndarray = np.asarray(rows.any(axis=0), dtype=bool)
    if tol > 0:
        idx = np.flatnonzero(hit)
        hit = np.zeros(n, bool)
        for j in idx:
            hit[max(0, j - tol): j + tol + 1] = True
    hit[max(int(limit[i]) + tol + 1, 0):] = False
    return hit


def _in_island(truth: np.ndarray, island: Sequence[float]) -> bool:
    first, last = int(island[0]), int(island[1])
    return bool(truth[max(first, 0): last + 1].any())


def _stage(status: str, extra: Mapping[str, object], truth: np.ndarray, accepted_ok: bool | None,
           above: bool) -> str:
    """The stage of one positive query, from its decision and its ``extra.jsonl`` record."""
    if accepted_ok is not None:
        if not accepted_ok:
            return "wrong_accepted"
        return "found" if above else "below_threshold"
    if status in _NOTHING_PROPOSED:
        return "excluded"
    results = extra.get("results")
    islands = extra.get("islands")
    checked = extra.get("checked")
    if not isinstance(results, list) or not isinstance(islands, list) or not isinstance(checked, list):
        return "unknown"
    if not any(truth[int(f)] for f, _ in results if 0 <= int(f) < truth.size):
        return "not_retrieved"
    true_islands = [k for k, isl in enumerate(islands) if _in_island(truth, isl)]
    if not true_islands:
        return "below_alpha"
    if status == "no_temporal_consistency":
        return "temporal" if 0 in true_islands else "wrong_island"
    if any(0 <= int(c[0]) < truth.size and truth[int(c[0])] for c in checked):
        return "geometry"
    return "wrong_island"


def loss_funnel(
    run: Run,
    gt: np.ndarray,
    ev: Evaluation,
    *,
    query_mask: np.ndarray | None = None,
    times: np.ndarray | None = None,
) -> Funnel:
    """The stage at which each positive query of an evaluated run lost its true loop.

    Args:
        run: the run (its decisions and ``extra.jsonl``).
        gt: (N, N) bool ground truth the run was evaluated against (project convention).
        ev: the evaluation (protocol, tolerance, exclusion, 100 %-precision threshold).
        query_mask: (N,) bool queries to count (two-pass sets), or None for all.
        times: (N,) float64 frame timestamps; needed when the evaluation excluded seconds
            (``ev.exclude_s > 0``).

    Returns:
        the :class:`Funnel`; when ``ev`` scored the accepted detections only (the default of
        :func:`~stablecues.evaluation.evaluate.run_detections`), its ``found`` count equals
        ``ev.tp_at_100p``.
    """
    n = gt.shape[0]
    limit = eligible_limit(n, ev.exclude, exclude_s=ev.exclude_s, times=times)
    tol = ev.tolerance if ev.protocol == "tolerance" else 0
    widen = ev.tolerance if ev.protocol == "ibow" else 0
    extras = {int(e.get("frame", -1)): e for e in run.extra()}
    correct_of = {int(f): bool(c) for f, c in zip(ev.detection_frames, ev.correct, strict=True)}
    threshold = ev.threshold_at_100p
    counts = dict.fromkeys(STAGES, 0)
    rows: dict[int, str] = {}
    for k, frame in enumerate(run.frames):
        i = int(frame)
        if i >= n or (query_mask is not None and not query_mask[i]):
            continue
        truth = _truth_mask(gt, limit, i, tol)
        if widen:  # iBoW-LCD: a candidate within +-n frames of a true loop is correct
            for j in np.flatnonzero(truth):
                truth[max(0, j - widen): j + widen + 1] = True
        if not truth.any():
            continue
        accepted_ok = correct_of.get(i) if bool(run.accepted[k]) else None
        above = threshold is not None and float(run.scores[k]) >= threshold
        stage = _stage(str(run.status[k]), extras.get(i, {}), truth, accepted_ok, above)
        counts[stage] = counts.get(stage, 0) + 1
        rows[i] = stage
    return Funnel(counts, rows, len(rows))


def format_funnel(funnel: Funnel) -> str:
    """The funnel as a small text table (stage, queries, share)."""
    lines = [f"{'where the true loop was lost':30s} {'queries':>7s} {'share':>6s}"]
    for stage, count in funnel.counts.items():
        share = count / funnel.positives if funnel.positives else 0.0
        lines.append(f"{stage:30s} {count:7d} {share:6.1%}")
    lines.append(f"{'positive queries':30s} {funnel.positives:7d}")
    return "\n".join(lines)
