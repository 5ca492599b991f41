"""Loop ground truth of a synthetic sequence, from the poses and from what each frame sees.

The rule (:class:`LoopTruthConfig`):

* **Same direction.** Frames ``i > j`` close a loop when the cameras are within ``max_distance``
  metres and their headings within ``max_angle_deg``, and ``i - j >= min_gap_frames``. This is
  what :func:`stablecues.groundtruth.loops_from_poses` computes.
* **Other headings** (``opposite``): a forward-looking camera driving a street the other way sees
  the other side of each facade's field of view: the buildings it sees at a given spot are mostly
  ones the first pass saw from behind its shoulder or at grazing angles, which no local-feature
  matcher can match. So pairs whose headings differ by more than ``max_angle_deg`` count only
  when their views share *matchable* static surface (``"covisible"``, the default): the static
  landmark surfaces (buildings, trees, poles, signs, fences; in 4 m pieces) seen in both frames,
  each seen from directions within ``max_view_angle_deg`` of each other and at distances within a
  factor of two, must cover at least ``min_covisible`` of the two frames' landmark pixels
  (geometric mean). ``"never"`` counts no such pair; ``"always"`` ignores headings altogether (a
  pose-only ground truth, as some benchmarks use).

The relation is symmetric in time; the matrix keeps its lower triangle (``gt[i, j]``, ``j < i``),
the project's convention.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..errors import ConfigError, InputError, check_array
from ..groundtruth import loops_from_poses

Opposite = Literal["never", "covisible", "always"]


@dataclass(frozen=True)
class LoopTruthConfig:
    """How loops are decided from poses and visibility.

    Attributes:
        max_distance: metres between the two camera centres (same-direction rule).
        max_angle_deg: largest heading difference of the same-direction rule.
        min_gap_frames: smallest index difference of a loop.
        opposite: pairs beyond ``max_angle_deg``: "never", "covisible" or "always".
        min_covisible: share of landmark pixels seen from matching viewpoints ("covisible").
        max_view_angle_deg: largest angle between the two sight lines to a shared surface.
        max_covisible_distance: metres between camera centres considered for "covisible".
    """

    max_distance: float = 6.0
    max_angle_deg: float = 35.0
    min_gap_frames: int = 20
    opposite: Opposite = "covisible"
    min_covisible: float = 0.25
    max_view_angle_deg: float = 40.0
    max_covisible_distance: float = 40.0

    def validate(self) -> None:
        if not self.max_distance >= 0 or not 0 <= self.max_angle_deg <= 180:
            raise ConfigError(
                "LoopTruthConfig: max_distance >= 0 and 0 <= max_angle_deg <= 180 expected, "
                f"got {self.max_distance}, {self.max_angle_deg}"
            )
        if self.min_gap_frames < 0:
            raise ConfigError(f"LoopTruthConfig: min_gap_frames >= 0 expected, got {self.min_gap_frames}")
        if self.opposite not in ("never", "covisible", "always"):
            raise ConfigError(
                f"LoopTruthConfig: opposite must be 'never', 'covisible' or 'always', got {self.opposite!r}"
            )
        if not 0 < self.min_covisible <= 1:
            raise ConfigError(f"LoopTruthConfig: min_covisible in (0, 1] expected, got {self.min_covisible}")


@dataclass(frozen=True)
class Visibility:
    """What static landmark surfaces each frame sees.

    Attributes:
        ids: per frame, (k,) int32 sorted ids of the surfaces seen.
        counts: per frame, (k,) float apparent size of each, pixels.
        centres: (Q, 3) float world centre of every surface id.
    """

    ids: list[np.ndarray]
    counts: list[np.ndarray]
    centres: np.ndarray


def loop_truth(
    positions: np.ndarray,
    headings: np.ndarray,
    config: LoopTruthConfig = LoopTruthConfig(),  # noqa: B008 - frozen, immutable default
    visibility: Visibility | None = None,
) -> np.ndarray:
    """Loop matrix of a trajectory.

    Args:
        positions: (N, 3) float camera centres, metres.
        headings: (N,) float yaw of each camera's optical axis, radians.
        config: the rule.
        visibility: needed when ``config.opposite == "covisible"``.

    Returns:
        (N, N) bool, ``gt[i, j]`` True when frame i closes a loop with the earlier frame j.

    Raises:
        InputError: shapes disagree, or visibility is missing for "covisible".
    """
    config.validate()
    positions = np.asarray(positions, float)
    headings = np.asarray(headings, float)
    check_array("positions", positions, shape=(None, 3))
    n = positions.shape[0]
    check_array("headings", headings, shape=(n,))
    if config.opposite == "always":
        return loops_from_poses(
            positions, max_distance=config.max_distance, min_gap_frames=config.min_gap_frames
        )
    gt = loops_from_poses(
        positions,
        max_distance=config.max_distance,
        yaws=headings,
        max_angle_deg=config.max_angle_deg,
        min_gap_frames=config.min_gap_frames,
    )
    if config.opposite == "never" or n == 0:
        return gt
    if visibility is None:
        raise InputError("loop_truth: opposite='covisible' needs the frames' visibility")
    if len(visibility.ids) != n:
        raise InputError(f"loop_truth: visibility of {n} frames expected, got {len(visibility.ids)}")
    from scipy.spatial import cKDTree

    pairs = cKDTree(positions[:, :2]).query_pairs(config.max_covisible_distance, output_type="ndarray")
    if not len(pairs):
        return gt
    i_all = pairs.max(axis=1)
    j_all = pairs.min(axis=1)
    dyaw = np.abs((headings[i_all] - headings[j_all] + math.pi) % (2 * math.pi) - math.pi)
    keep = (dyaw > math.radians(config.max_angle_deg)) & (i_all - j_all >= config.min_gap_frames)
    cand_i, cand_j = i_all[keep], j_all[keep]
    cos_lim = math.cos(math.radians(config.max_view_angle_deg))
    totals = np.array([float(c.sum()) for c in visibility.counts])
    for i, j in zip(cand_i.tolist(), cand_j.tolist(), strict=True):
        if totals[i] <= 0 or totals[j] <= 0:
            continue
        common, ai, aj = np.intersect1d(
            visibility.ids[i], visibility.ids[j], assume_unique=True, return_indices=True
        )
        if not len(common):
            continue
        c = visibility.centres[common]
        vi = c - positions[i]
        vj = c - positions[j]
        ni = np.linalg.norm(vi, axis=1)
        nj = np.linalg.norm(vj, axis=1)
        cos = (vi * vj).sum(axis=1) / np.maximum(ni * nj, 1e-9)
        ratio = np.maximum(ni, nj) / np.maximum(np.minimum(ni, nj), 1e-9)
        ok = (cos >= cos_lim) & (ratio <= 2.0)
        shared = np.minimum(visibility.counts[i][ai], visibility.counts[j][aj])[ok].sum()
        if shared >= config.min_covisible * math.sqrt(totals[i] * totals[j]):
            gt[i, j] = True
    return gt
