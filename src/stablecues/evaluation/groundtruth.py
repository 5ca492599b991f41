"""Loop ground truth: the project convention, and loop matrices from poses.

Convention for every loop ground truth in stablecues: an (N, N) ``bool`` array ``gt`` with
``gt[i, j]`` True when query frame ``i`` closes a loop with the EARLIER frame ``j`` (``j < i``),
so the matrix is strictly lower-triangular. It is saved as ``.npy``.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError, check_array

_ROW_BLOCK = 512  # rows per block when building matrices from poses (bounds the memory)


def loops_from_poses(
    positions: np.ndarray,
    *,
    max_distance: float,
    yaws: np.ndarray | None = None,
    max_angle_deg: float | None = None,
    times: np.ndarray | None = None,
    min_gap_s: float = 0.0,
    min_gap_frames: int = 0,
) -> np.ndarray:
    """Loop ground truth from camera positions: frames close in space but apart in time.

    ``gt[i, j]`` is True when ``j < i`` and all of these hold:

    * ``||positions[i] - positions[j]|| <= max_distance`` (Euclidean, in the positions' unit);
    * if ``yaws`` and ``max_angle_deg`` are given: the absolute yaw difference, wrapped to
      [0, 180] degrees, is ``<= max_angle_deg``;
    * if ``times`` is given: ``times[i] - times[j] >= min_gap_s``;
    * ``i - j >= min_gap_frames``.

    Frames with a NaN position (or NaN yaw / time when those are used) close no loop.

    Args:
        positions: (N, 3) float camera positions (any float dtype; ints are accepted too).
        max_distance: distance threshold, same unit as ``positions``; must be >= 0.
        yaws: (N,) float heading of each frame in RADIANS, or None to ignore orientation.
        max_angle_deg: largest yaw difference in degrees for a loop; needs ``yaws``.
        times: (N,) float timestamps in seconds, or None (then ``min_gap_s`` must be 0).
        min_gap_s: smallest time between the two frames of a loop, seconds.
        min_gap_frames: smallest index difference between the two frames of a loop.

    Returns:
        (N, N) bool strictly lower-triangular loop matrix.

    Raises:
        InputError: on wrong shapes, negative thresholds or inconsistent options.
    """
    positions = np.asarray(positions)
    check_array("positions", positions, shape=(None, 3))
    if not np.issubdtype(positions.dtype, np.number):
        raise InputError(f"positions: expected a numeric array, got dtype {positions.dtype}")
    n = positions.shape[0]
    if not np.isfinite(max_distance) or max_distance < 0:
        raise InputError(f"max_distance: expected a finite value >= 0, got {max_distance}")
    if min_gap_s < 0 or min_gap_frames < 0:
        raise InputError(f"min gaps must be >= 0, got min_gap_s={min_gap_s}, min_gap_frames={min_gap_frames}")
    if (yaws is None) != (max_angle_deg is None):
        raise InputError("yaws and max_angle_deg must be given together")
    if times is None and min_gap_s > 0:
        raise InputError(f"min_gap_s={min_gap_s} needs times")

    pos = positions.astype(np.float64)
    valid = np.all(np.isfinite(pos), axis=1)
    yaw_arr: np.ndarray | None = None
    cos_limit = -2.0
    if yaws is not None and max_angle_deg is not None:
        yaw_arr = np.asarray(yaws, dtype=np.float64)
        check_array("yaws", yaw_arr, shape=(n,))
        if not max_angle_deg >= 0:  # also rejects NaN
            raise InputError(f"max_angle_deg: expected >= 0, got {max_angle_deg}")
        valid &= np.isfinite(yaw_arr)
        # |wrapped difference| <= a  <=>  cos(difference) >= cos(a) for a in [0, 180]
        cos_limit = float(np.cos(np.radians(min(max_angle_deg, 180.0))))
    time_arr: np.ndarray | None = None
    if times is not None:
        time_arr = np.asarray(times, dtype=np.float64)
        check_array("times", time_arr, shape=(n,))
        valid &= np.isfinite(time_arr)

    gt = np.zeros((n, n), dtype=bool)
    if n == 0:
        return gt
    pos = np.where(valid[:, None], pos, 0.0)
    cols = np.arange(n)
    limit2 = float(max_distance) ** 2
    for start in range(0, n, _ROW_BLOCK):
        stop = min(start + _ROW_BLOCK, n)
        rows = np.arange(start, stop)
        diff = pos[start:stop, None, :] - pos[None, :stop, :]
        block = np.einsum("ijk,ijk->ij", diff, diff) <= limit2
        block &= rows[:, None] - cols[None, :stop] >= max(min_gap_frames, 1)
        block &= valid[start:stop, None] & valid[None, :stop]
        if yaw_arr is not None:
            block &= np.cos(yaw_arr[start:stop, None] - yaw_arr[None, :stop]) >= cos_limit - 1e-12
        if time_arr is not None:
            block &= time_arr[start:stop, None] - time_arr[None, :stop] >= min_gap_s
        gt[start:stop, :stop] = block
    return gt
