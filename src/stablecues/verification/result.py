"""The one result type of every verifier: :class:`Verification`, with a :class:`Status` naming why."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from functools import cached_property

import numpy as np

from ..geometry.triangles import Triangle
from .matching import Matches

__all__ = ["Method", "Status", "Verification"]


class Method(StrEnum):
    """Which verifier decided."""

    TRIANGLES = "triangles"
    SIMILAR_TRIANGLES = "similar_triangles"  # monocular points: shapes compared, scale-free
    FUNDAMENTAL = "fundamental"
    PNP = "pnp"


class Status(StrEnum):
    """Why a loop was accepted or rejected (the stage that decided)."""

    ACCEPTED = "accepted"
    TOO_FEW_MATCHES = "too_few_matches"
    TOO_FEW_3D = "too_few_3d_points"
    TOO_FEW_TRIANGLES = "too_few_triangles"
    TRIANGLES_DISAGREE = "triangles_disagree"
    PNP_FAILED = "pnp_failed"
    TOO_FEW_PNP_INLIERS = "too_few_pnp_inliers"
    FUNDAMENTAL_FAILED = "fundamental_failed"
    TOO_FEW_FUNDAMENTAL_INLIERS = "too_few_fundamental_inliers"
    OUTRANKED = "outranked"  # fewer matches than an accepted candidate's inliers: not checked


def _list(a: np.ndarray | None) -> list[object] | None:
    return None if a is None else np.asarray(a).tolist()


#: inliers used for :attr:`Verification.scale_change` (the first, best-ranked ones)
SCALE_PAIRS_MAX = 200
#: pairs of points closer than this (pixels) in either image are left out of the scale
SCALE_MIN_PX = 3.0


@dataclass(frozen=True, eq=False)
class Verification:
    """Outcome of verifying one (query, candidate) pair.

    Attributes:
        accepted: whether the candidate is accepted as a loop.
        method: the verifier that decided (may differ from the configured one, see fallback).
        status: ``ACCEPTED`` or the reason of the rejection.
        reason: one line for people ("3 of 10 triangles agree, need 2; 87 PnP inliers").
        fallback: True when the configured verifier could not run for lack of 3D points and
            ``method`` is the one that stood in (PnP when only the candidate has 3D,
            the fundamental matrix when the candidate has none).
        matches: all ranked correspondences that were checked.
        matcher: the matcher that found them (``VerificationConfig.matcher``: "ratio", "mnn").
        inliers: (M,) bool over ``matches``: PnP inliers, fundamental-matrix inliers, or the
            vertices of agreeing triangles when no pose was estimated.
        triangles: every checked triangle (triangle verifier only).
        n_triangles_agree: how many of them agree.
        rotation: (3, 3) float64 rotation candidate camera -> query camera, or None.
        translation: (3,) float64 translation candidate -> query in metres, or None
            (``X_query = rotation @ X_candidate + translation``).
        rmse_px: reprojection RMSE of the PnP inliers (NaN without a pose).
        fundamental: (3, 3) fundamental matrix (``x_q^T F x_c = 0``), fundamental verifier only.
        timings: milliseconds per stage (``matching``, ``triangles``, ``pnp``, ``fundamental``,
            ``total``).
        pixels_query: (M, 2) float32 keypoint pixels of the matches in the query image, so that
            the result can be drawn without the features.
        pixels_candidate: (M, 2) float32 keypoint pixels of the matches in the candidate image.
    """

    accepted: bool
    method: Method
    status: Status
    reason: str
    matches: Matches
    inliers: np.ndarray
    fallback: bool = False
    matcher: str = "ratio"
    triangles: tuple[Triangle, ...] = ()
    n_triangles_agree: int = 0
    rotation: np.ndarray | None = None
    translation: np.ndarray | None = None
    rmse_px: float = float("nan")
    fundamental: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)
    pixels_query: np.ndarray | None = None
    pixels_candidate: np.ndarray | None = None

    @property
    def n_matches(self) -> int:
        return len(self.matches)

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    @cached_property  # O(inliers^2): the walk and the run's extras both read it
    def scale_change(self) -> float:
        """How much larger the scene looks in the query than in the candidate, as a log ratio:
        the median over pairs of inliers of log(distance in the query image / distance in the
        candidate image). 0 for the same viewpoint; negative when the candidate was taken
        closer to the scene (a camera that moved on along its way); NaN with fewer than 3
        inliers or without the match pixels. Rotations in the image plane leave it unchanged."""
        if self.pixels_query is None or self.pixels_candidate is None:
            return float("nan")
        idx = np.flatnonzero(self.inliers)[:SCALE_PAIRS_MAX]
        if idx.size < 3:
            return float("nan")
        pq = self.pixels_query[idx].astype(np.float64)
        pc = self.pixels_candidate[idx].astype(np.float64)
        i, j = np.triu_indices(idx.size, 1)
        dq = np.hypot(*(pq[i] - pq[j]).T)
        dc = np.hypot(*(pc[i] - pc[j]).T)
        ok = (dq > SCALE_MIN_PX) & (dc > SCALE_MIN_PX)
        if not ok.any():
            return float("nan")
        return float(np.median(np.log(dq[ok] / dc[ok])))

    @property
    def pose(self) -> np.ndarray | None:
        """(4, 4) float64 transform candidate -> query, or None."""
        if self.rotation is None or self.translation is None:
            return None
        out = np.eye(4)
        out[:3, :3] = self.rotation
        out[:3, 3] = self.translation
        return out

    def to_dict(self) -> dict[str, object]:
        """JSON-serialisable view (matches as ``[query, candidate, distance]`` rows)."""
        return {
            "accepted": self.accepted,
            "method": self.method.value,
            "status": self.status.value,
            "reason": self.reason,
            "fallback": self.fallback,
            "matcher": self.matcher,
            "n_matches": self.n_matches,
            "n_inliers": self.n_inliers,
            "n_triangles": len(self.triangles),
            "n_triangles_agree": self.n_triangles_agree,
            "matches": np.stack((self.matches.query, self.matches.candidate, self.matches.distance), axis=1)
            .astype(int)
            .tolist(),
            "inliers": np.flatnonzero(self.inliers).tolist(),
            "triangles": [t.to_dict() for t in self.triangles],
            "rotation": _list(self.rotation),
            "translation": _list(self.translation),
            "rmse_px": None if not np.isfinite(self.rmse_px) else self.rmse_px,
            "fundamental": _list(self.fundamental),
            "timings_ms": dict(self.timings),
        }
