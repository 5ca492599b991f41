"""Loop ground truth from camera poses, in the project's convention.

The work is :func:`stablecues.groundtruth.loops_from_poses`'s; this module takes the headings
from pose quaternions (x, y, z, w) when an angle threshold is asked for.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..groundtruth import loops_from_poses
from . import geo

__all__ = ["loops_from_trajectory"]


def loops_from_trajectory(
    positions: np.ndarray,
    *,
    max_distance: float = 10.0,
    quaternions: np.ndarray | None = None,
    max_angle_deg: float | None = None,
    times: np.ndarray | None = None,
    min_gap_s: float = 0.0,
    min_gap_frames: int = 0,
) -> np.ndarray:
    """Loop ground truth from poses, in the project's convention.

    Wraps :func:`stablecues.groundtruth.loops_from_poses`, taking the headings from the pose
    quaternions (ZYX yaw about the world vertical) when an angle threshold is given.

    Args:
        positions: (N, 3) float positions, metres.
        max_distance: metres.
        quaternions: (N, 4) (x, y, z, w) orientations; needed with ``max_angle_deg``. A NaN row
            (no pose) closes no loop.
        max_angle_deg: largest heading difference of a loop, degrees, or None.
        times: (N,) seconds, for ``min_gap_s``.
        min_gap_s: smallest time between the two frames of a loop.
        min_gap_frames: smallest index difference.

    Returns:
        (N, N) bool, ``gt[i, j]`` True when frame ``i`` revisits the earlier frame ``j``.

    Raises:
        InputError: inconsistent options or shapes.
    """
    yaws = None
    if max_angle_deg is not None:
        if quaternions is None:
            raise InputError("max_angle_deg needs the pose orientations (quaternions)")
        yaws = geo.known_yaw(quaternions)
    return loops_from_poses(
        np.asarray(positions, dtype=np.float64),
        max_distance=max_distance,
        yaws=yaws,
        max_angle_deg=max_angle_deg,
        times=times,
        min_gap_s=min_gap_s,
        min_gap_frames=min_gap_frames,
    )
