"""What the loop detector says about each frame."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np

from ..verification.result import Verification


class Status(enum.StrEnum):
    """The stage that decided (DLoopDetector's ``DetectionStatus``, plus semantics)."""

    LOOP_DETECTED = "loop_detected"
    CLOSE_MATCHES_ONLY = "close_matches_only"  # nothing outside the exclusion window yet
    NO_DB_RESULTS = "no_db_results"  # no stored entry shares a word
    LOW_NSS_FACTOR = "low_nss_factor"  # previous-frame score too low to normalise
    LOW_SCORES = "low_scores"  # every candidate under alpha
    NO_TEMPORAL_CONSISTENCY = "no_temporal_consistency"
    NO_GEOMETRICAL_CONSISTENCY = "no_geometrical_consistency"
    LOW_CONFIDENCE = "low_confidence"  # verified, but its confidence is under min_confidence


@dataclass(frozen=True)
class Island:
    """A group of database entries with nearby ids, proposed together.

    Attributes:
        first: first entry id.
        last: last entry id.
        best: entry id with the highest score.
        best_score: its (normalised) score.
        score: the island's score (sum of its entries' scores).
    """

    first: int
    last: int
    best: int
    best_score: float
    score: float


@dataclass(frozen=True, eq=False)
class Checked:
    """One candidate that geometric verification looked at.

    Attributes:
        island: the island it is the best entry of.
        frame: the frame index stored with that entry.
        verification: the result.
    """

    island: Island
    frame: int
    verification: Verification


@dataclass(frozen=True, eq=False)
class LoopDecision:
    """The detector's answer for one frame.

    Attributes:
        frame_index: the frame's index in its sequence.
        entry_id: the database entry the frame was stored as.
        status: the stage that decided.
        candidate: entry id of the proposed loop (the best entry of the best island), -1 if none.
        candidate_frame: the frame index stored with that entry, -1 if none.
        raw_score: the candidate's BoW score.
        score: the candidate's normalised score (= raw without normalisation).
        confidence: what ranks this detection against others (see DetectorConfig.confidence).
        nss_factor: score between the frame and the previous one (NaN before there is one).
        island: the best island, or None.
        consistent: consecutive temporally consistent frames including this one.
        verification: the geometric check's result for ``candidate``, when it ran.
        results: ``(frame, normalised score)`` of the database results the query considered,
            best first (before ``alpha``).
        islands: the islands that passed ``alpha``, best first, as ``(first frame, last frame,
            best frame, island score)``.
        checked: every candidate verified (the best ``islands_verified`` islands), in order.
        points_source: where this frame's 3D points came from ("map", "stereo", "depth",
            "mono", "mono-guessed-focal"), or None without 3D.
        n_features: features extracted.
        n_kept: features kept after semantic masking (= n_features without masking).
        mask_fallback: masking kept too few, so every feature was kept.
        timings: milliseconds per stage.
        sequence_score: the candidate's sequence score (``query.sequence`` >= 2), else NaN.
    """

    frame_index: int
    entry_id: int
    status: Status
    candidate: int = -1
    candidate_frame: int = -1
    raw_score: float = 0.0
    score: float = 0.0
    confidence: float = 0.0
    nss_factor: float = math.nan
    island: Island | None = None
    consistent: int = 0
    verification: Verification | None = None
    results: tuple[tuple[int, float], ...] = ()
    islands: tuple[tuple[int, int, int, float], ...] = ()
    checked: tuple[Checked, ...] = ()
    points_source: str | None = None
    n_features: int = 0
    n_kept: int = 0
    mask_fallback: bool = False
    timings: dict[str, float] = field(default_factory=dict)
    sequence_score: float = math.nan

    @property
    def accepted(self) -> bool:
        return self.status == Status.LOOP_DETECTED

    @property
    def relative_pose(self) -> np.ndarray | None:
        """(4, 4) transform from the candidate's camera to this frame's camera, when known."""
        v = self.verification
        if v is None or v.rotation is None or v.translation is None:
            return None
        t = np.eye(4)
        t[:3, :3] = v.rotation
        t[:3, 3] = v.translation
        return t

    def extras(self) -> dict[str, object]:
        """JSON-ready details of the decision for a run's ``extra.jsonl`` (read by the loss funnel
        of :mod:`stablecues.evaluation.funnel`)."""
        out: dict[str, object] = {
            "n_features": self.n_features,
            "n_kept": self.n_kept,
            "mask_fallback": self.mask_fallback,
            "consistent": self.consistent,
            "nss": self.nss_factor,
            "points": self.points_source,
            "results": [[f, round(s, 6)] for f, s in self.results],
            "islands": [[a, b, c, round(s, 6)] for a, b, c, s in self.islands],
            "checked": [[c.frame, c.verification.accepted, c.verification.n_inliers, c.verification.n_matches]
                        for c in self.checked],
        }
        if math.isfinite(self.sequence_score):
            out["sequence_score"] = round(self.sequence_score, 6)
        v = self.verification
        if v is not None:
            out.update(
                verifier=str(v.method),
                matcher=v.matcher,
                verification=str(v.status),
                reason=v.reason,
                inliers=v.n_inliers,
                triangles_agree=v.n_triangles_agree,
            )
            scale = v.scale_change
            if math.isfinite(scale):
                out["scale_change"] = round(scale, 4)
            pose = self.relative_pose
            if pose is not None:
                out["relative_pose"] = pose.tolist()
        return out
