"""Loop ground truth from poses, with and without a heading test (no shared data)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pymap3d")

from stablecues.errors import InputError  # noqa: E402
from stablecues.geometry.rotations import euler_zyx_to_quat  # noqa: E402
from stablecues.mav import geo  # noqa: E402
from stablecues.mav.loops import loops_from_trajectory  # noqa: E402


def test_loops_from_trajectory_with_heading() -> None:
    # out east along y=0, back west along y=2: revisits face the opposite way
    x = np.r_[np.arange(0, 50, 5.0), np.arange(45, -5, -5.0)]
    y = np.r_[np.zeros(10), np.full(10, 2.0)]
    pos = np.column_stack([x, y, np.zeros(20)])
    yaw_ned = np.r_[np.full(10, np.pi / 2), np.full(10, -np.pi / 2)]  # east, then west
    q = geo.ned_to_enu_quat(euler_zyx_to_quat(np.zeros(20), np.zeros(20), yaw_ned))
    times = np.arange(20.0)
    gt = loops_from_trajectory(pos, max_distance=3.0, times=times, min_gap_s=3.0)
    # return frame 10 + k is 2 m from outbound frame 9 - k, 2k + 1 s later: k = 0 is too recent
    assert gt[11, 8] and gt[19, 0] and not gt[10, 9] and not np.triu(gt).any()
    assert int(gt.sum()) == 9
    gt_heading = loops_from_trajectory(pos, max_distance=3.0, quaternions=q, max_angle_deg=45.0)
    assert not gt_heading[10:, :10].any()  # opposite headings: no loop
    with pytest.raises(InputError, match="quaternions"):
        loops_from_trajectory(pos, max_distance=3.0, max_angle_deg=45.0)


def test_frames_without_a_pose_close_no_loop() -> None:
    pos = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [np.nan] * 3, [0.5, 0.0, 0.0]])
    q = np.tile([0.0, 0.0, 0.0, 1.0], (4, 1))
    q[2] = np.nan
    gt = loops_from_trajectory(pos, max_distance=2.0, quaternions=q, max_angle_deg=30.0)
    assert gt[3, 0] and int(gt.sum()) == 1
