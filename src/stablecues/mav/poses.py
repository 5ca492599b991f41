"""A camera pose per frame, interpolated from a navigation solution.

Poses are camera-to-world in the solution's ENU frame (metres about its origin); orientations
are quaternions (x, y, z, w), scalar last, as everywhere in stablecues. The camera's mounting
on the body (:data:`MOUNTS`) is applied after the body's attitude.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..errors import InputError, check_array
from ..geometry.rotations import matrix_to_quat, quat_multiply, quat_normalize, quat_to_matrix
from . import geo
from .clock import Clock, estimate_clock_offset, frame_log_times
from .flightlog import FlightLog, NavSolution
from .frames import FrameSet
from .solutions import gnss_solution

logger = logging.getLogger(__name__)

__all__ = ["MOUNTS", "FramePoses", "Mount", "pose_matrices", "poses_for_frames"]

Mount = Literal["body", "forward", "nadir"]

# Camera axes (optical: x right, y down, z forward) as columns in the body frame (FRD).
MOUNTS: dict[str, np.ndarray] = {
    "body": np.eye(3),
    "forward": np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
    "nadir": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}


def pose_matrices(positions: np.ndarray, quaternions: np.ndarray) -> np.ndarray:
    """(N, 4, 4) float64 homogeneous poses from positions and (x, y, z, w) orientations.

    Args:
        positions: (N, 3) float64 translations.
        quaternions: (N, 4) float64 rotations (x, y, z, w), normalised here.

    Returns:
        (N, 4, 4) float64; every entry NaN where the position or the orientation is not
        finite (or the quaternion is zero), so trajectory writers skip those rows.
    """
    positions = np.asarray(positions, dtype=np.float64)
    quaternions = np.asarray(quaternions, dtype=np.float64)
    n = positions.shape[0] if positions.ndim == 2 else -1
    check_array("positions", positions, shape=(None, 3))
    check_array("quaternions", quaternions, shape=(n, 4))
    ok = np.isfinite(positions).all(axis=1) & geo.known_attitude(quaternions)
    poses = np.full((n, 4, 4), np.nan)
    poses[ok] = np.eye(4)
    if ok.any():
        poses[ok, :3, :3] = quat_to_matrix(quaternions[ok])
        poses[ok, :3, 3] = positions[ok]
    return poses


@dataclass(frozen=True, eq=False)
class FramePoses:
    """A pose per camera frame.

    Attributes:
        names: image file names.
        frame_times: (N,) float64 capture times in the frames' clock (s).
        log_times: (N,) float64 the same on the log's clock (s since log start), offset included.
        positions: (N, 3) float64 camera positions, ENU metres about ``origin``; NaN outside the
            solution's span.
        quaternions: (N, 4) float64 camera-to-world rotations (x, y, z, w), scalar last; NaN
            outside the span.
        valid: (N,) bool frames inside the solution's span.
        origin: (lat, lon, alt) of the ENU frame.
        source: the solution's name.
        offset: clock offset applied, s.
        has_attitude: False when the solution had no attitude (level, north-facing body assumed).
        mount: camera mounting ("body", "forward", "nadir").
    """

    names: tuple[str, ...]
    frame_times: np.ndarray
    log_times: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    valid: np.ndarray
    origin: tuple[float, float, float]
    source: str
    offset: float
    has_attitude: bool
    mount: str

    @property
    def yaws(self) -> np.ndarray:
        """(N,) heading of each camera pose: ZYX yaw of its rotation in the ENU frame, radians
        (NaN for frames without a pose)."""
        return geo.known_yaw(self.quaternions)

    @property
    def matrices(self) -> np.ndarray:
        """(N, 4, 4) float64 camera-to-world poses, NaN for frames without a pose."""
        return pose_matrices(self.positions, self.quaternions)


def _clock_offset(
    frames: FrameSet, log: FlightLog, t_log: np.ndarray, offset: float | Literal["estimate"]
) -> float:
    """``offset`` in seconds, or estimated from the frames' geotags against the GNSS track."""
    if not isinstance(offset, str):
        return float(offset)
    if offset != "estimate":
        raise InputError(f"offset: expected seconds or 'estimate', got {offset!r}")
    if frames.geotags is None:
        raise InputError("offset 'estimate' needs geotagged frames (lat/lon columns in the times CSV)")
    off, rms = estimate_clock_offset(t_log, frames.geotags, gnss_solution(log))
    logger.info("estimated clock offset %.3f s (geotag residual %.2f m RMS)", off, rms)
    return off


def _camera_quaternions(body: np.ndarray, valid: np.ndarray, has_attitude: bool, mount: str) -> np.ndarray:
    """Camera-to-world quaternions: the body's (level and north-facing when the solution has no
    attitude) times the mounting; NaN for invalid frames."""
    quat = body.copy()
    if not has_attitude:
        quat[valid] = matrix_to_quat(geo.R_ENU_NED)
    q_mount = matrix_to_quat(MOUNTS[mount])
    camera = geo.map_known(
        lambda q: quat_normalize(quat_multiply(q, np.broadcast_to(q_mount, q.shape))), quat, 4
    )
    return np.where(valid[:, None], camera, np.nan)


def poses_for_frames(
    frames: FrameSet,
    log: FlightLog,
    solution: NavSolution,
    *,
    clock: Clock = "auto",
    offset: float | Literal["estimate"] = 0.0,
    mount: Mount = "body",
) -> FramePoses:
    """Interpolate a pose for every frame.

    Args:
        frames: the recording's frames.
        log: the flight log (for its clocks).
        solution: the navigation solution (see :func:`stablecues.mav.solutions.log_solution`).
        clock: the frames' clock (see :func:`stablecues.mav.clock.frame_log_times`).
        offset: seconds added to the mapped frame times, or "estimate" to fit it from the
            frames' geotags against the log's GNSS track
            (:func:`stablecues.mav.clock.estimate_clock_offset`).
        mount: camera mounting on the body: "body" (camera frame = body FRD), "forward"
            (optical frame looking forward), "nadir" (optical frame looking down, image top
            towards the nose).

    Raises:
        DatasetError / InputError: clock mapping impossible, unknown mount, or "estimate"
            without geotags.
    """
    if mount not in MOUNTS:
        raise InputError(f"mount: expected one of {sorted(MOUNTS)}, got {mount!r}")
    t_log = frame_log_times(frames, log, clock=clock, offset=0.0)
    off = _clock_offset(frames, log, t_log, offset)
    t_log = t_log + off
    at = solution.interpolate(t_log)
    valid = np.isfinite(at.position).all(axis=1)
    has_att = bool(solution.has_attitude)
    quat = _camera_quaternions(at.quaternion, valid, has_att, mount)
    if not valid.all():
        logger.warning(
            "%d of %d frames fall outside the %s solution (%.1f-%.1f s); they get no pose",
            int((~valid).sum()),
            len(valid),
            solution.name,
            solution.t[0] if len(solution) else float("nan"),
            solution.t[-1] if len(solution) else float("nan"),
        )
    return FramePoses(
        names=tuple(p.name for p in frames.paths),
        frame_times=frames.times.copy(),
        log_times=t_log,
        positions=at.position,
        quaternions=quat,
        valid=valid,
        origin=solution.origin,
        source=solution.name,
        offset=off,
        has_attitude=has_att,
        mount=mount,
    )
