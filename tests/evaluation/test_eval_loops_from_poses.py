"""loops_from_poses: hand-computed cases and a brute-force comparison."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues.errors import InputError
from stablecues.groundtruth import loops_from_poses


def test_square_path_hand_computed() -> None:
    # 0 -> 1 -> 2 -> 3 -> back near 0 (frame 4), then near 1 (frame 5)
    pos = np.array([[0, 0, 0], [5, 0, 0], [5, 5, 0], [0, 5, 0], [0.5, 0, 0], [5, 0.9, 0]], float)
    gt = loops_from_poses(pos, max_distance=1.0)
    expected = np.zeros((6, 6), bool)
    expected[4, 0] = True
    expected[5, 1] = True
    np.testing.assert_array_equal(gt, expected)
    assert gt.dtype == bool and not np.triu(gt).any()


def test_gaps_yaw_and_nan() -> None:
    pos = np.zeros((5, 3))
    gt = loops_from_poses(pos, max_distance=0.1, min_gap_frames=2)
    assert gt.sum() == 6  # pairs with i - j >= 2 among 5 frames: 3 + 2 + 1
    times = np.array([0.0, 1.0, 2.0, 3.0, 10.0])
    gt = loops_from_poses(pos, max_distance=0.1, times=times, min_gap_s=5.0)
    assert set(zip(*np.nonzero(gt), strict=True)) == {(4, 0), (4, 1), (4, 2), (4, 3)}
    yaws = np.radians([0.0, 170.0, -175.0, 10.0, 359.0])
    gt = loops_from_poses(pos, max_distance=0.1, yaws=yaws, max_angle_deg=20.0)
    pairs = set(zip(*np.nonzero(gt), strict=True))
    assert pairs == {(2, 1), (3, 0), (4, 0), (4, 3)}
    pos_nan = pos.copy()
    pos_nan[2] = np.nan
    gt = loops_from_poses(pos_nan, max_distance=0.1)
    assert not gt[2].any() and not gt[:, 2].any() and gt[3, 1]


def test_matches_brute_force_across_blocks() -> None:
    rng = np.random.default_rng(3)
    n = 700  # more than one row block
    pos = rng.uniform(0, 20, (n, 3))
    gt = loops_from_poses(pos, max_distance=1.5, min_gap_frames=10)
    d = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    i, j = np.indices((n, n))
    np.testing.assert_array_equal(gt, (d <= 1.5) & (i - j >= 10))


def test_bad_inputs() -> None:
    with pytest.raises(InputError):
        loops_from_poses(np.zeros((4, 2)), max_distance=1.0)
    with pytest.raises(InputError):
        loops_from_poses(np.zeros((4, 3)), max_distance=-1.0)
    with pytest.raises(InputError):
        loops_from_poses(np.zeros((4, 3)), max_distance=1.0, min_gap_s=1.0)
    with pytest.raises(InputError):
        loops_from_poses(np.zeros((4, 3)), max_distance=1.0, yaws=np.zeros(4))
    assert loops_from_poses(np.zeros((0, 3)), max_distance=1.0).shape == (0, 0)
