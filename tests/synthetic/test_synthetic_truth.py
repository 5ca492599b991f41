"""Loop ground truth of synthetic sequences: convention, gaps, time symmetry, the opposite rule."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stablecues.errors import ConfigError, InputError
from stablecues.synthetic import (
    LoopTruthConfig,
    SyntheticTown,
    SyntheticTownConfig,
    Visibility,
    loop_truth,
)


def _straight(
    n: int, y: float, heading: float, x0: float = 0.0, step: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    d = np.array([math.cos(heading), math.sin(heading), 0.0])
    pos = np.array([x0, y, 1.5]) + np.arange(n)[:, None] * step * d
    return pos, np.full(n, heading)


def test_hand_made_revisit() -> None:
    """Frames 10..19 drive the road of frames 0..9 again, 1 m to the side; 20..29 go the other way."""
    p0, h0 = _straight(10, 0.0, 0.0)
    p1, h1 = _straight(10, 1.0, 0.0)
    p2, h2 = _straight(10, 0.0, math.pi, x0=9.0)
    pos = np.vstack([p0, p1, p2])
    head = np.concatenate([h0, h1, h2])
    cfg = LoopTruthConfig(max_distance=1.5, max_angle_deg=30.0, min_gap_frames=5, opposite="never")
    gt = loop_truth(pos, head, cfg)
    assert gt.shape == (30, 30) and gt.dtype == bool
    # same direction: frame 10 + k is within 1.5 m of frames k-1, k, k+1 (1 m aside)
    for k in range(10):
        want = {j for j in (k - 1, k, k + 1) if 0 <= j < 10}
        assert set(np.nonzero(gt[10 + k])[0].tolist()) == want
    assert not gt[20:].any()  # the other way: not loops under "never"
    always = loop_truth(
        pos, head, LoopTruthConfig(max_distance=1.5, max_angle_deg=30.0, min_gap_frames=5, opposite="always")
    )
    assert always[20:, :10].any()  # distance only


def test_convention_and_min_gap() -> None:
    town = SyntheticTown(SyntheticTownConfig(frames=60, width=64, height=48, loops=2, seed=2))
    cfg = LoopTruthConfig(min_gap_frames=15)
    gt = town.ground_truth(cfg)
    n = len(town)
    assert gt.shape == (n, n) and gt.dtype == bool
    assert not np.triu(gt).any()  # strictly lower-triangular: gt[i, j] only for j < i
    i, j = np.nonzero(gt)
    assert len(i) > 0
    assert np.all(i - j >= 15)
    # revisit laps hold loops, the first lap (before it closes) none
    assert gt[town.lap_of == 1].any()


def test_symmetric_in_time() -> None:
    """Reversing time gives the transposed relation: gt_rev[n-1-j, n-1-i] == gt[i, j]."""
    town = SyntheticTown(SyntheticTownConfig(frames=60, width=64, height=48, loops=2, seed=7))
    vis = town.visibility()
    cfg = LoopTruthConfig(min_gap_frames=10)
    gt = loop_truth(town.positions, town.headings, cfg, vis)
    rev_vis = Visibility(vis.ids[::-1], vis.counts[::-1], vis.centres)
    rev = loop_truth(town.positions[::-1], town.headings[::-1], cfg, rev_vis)
    np.testing.assert_array_equal(rev[::-1, ::-1].T, gt)


def test_opposite_rules_are_nested() -> None:
    town = SyntheticTown(SyntheticTownConfig(frames=80, width=64, height=48, loops=2, seed=1))
    vis = town.visibility()
    never = loop_truth(town.positions, town.headings, LoopTruthConfig(opposite="never"), vis)
    cov = loop_truth(town.positions, town.headings, LoopTruthConfig(opposite="covisible"), vis)
    always = loop_truth(town.positions, town.headings, LoopTruthConfig(opposite="always"), vis)
    assert np.all(cov >= never)
    # the opposite-direction lap is within the distance of the first one, so "always" adds it
    assert always[town.lap_of == 2].sum() > never[town.lap_of == 2].sum()
    # every pair "covisible" adds has a heading difference above the limit
    extra = np.argwhere(cov & ~never)
    for a, b in extra:
        d = abs((town.headings[a] - town.headings[b] + math.pi) % (2 * math.pi) - math.pi)
        assert math.degrees(d) > 35.0


def test_bad_inputs() -> None:
    pos, head = _straight(5, 0.0, 0.0)
    with pytest.raises(InputError, match="visibility"):
        loop_truth(pos, head, LoopTruthConfig(opposite="covisible"))
    with pytest.raises(InputError):
        loop_truth(pos, head[:3], LoopTruthConfig(opposite="never"))
    with pytest.raises(ConfigError):
        loop_truth(pos, head, LoopTruthConfig(opposite="sometimes"))  # type: ignore[arg-type]
    with pytest.raises(ConfigError):
        loop_truth(pos, head, LoopTruthConfig(min_gap_frames=-1))
    empty = loop_truth(np.zeros((0, 3)), np.zeros(0), LoopTruthConfig(opposite="covisible"))
    assert empty.shape == (0, 0)
