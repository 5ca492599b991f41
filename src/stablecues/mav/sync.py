"""Deprecated: the old home of camera sync, kept for one release (0.2.x); goes in 0.3.

Importing it warns (DeprecationWarning). It was split by responsibility; import from:

====================================  ==========================================================
:mod:`stablecues.mav.frames`          ``FrameSet``, ``read_frames``
:mod:`stablecues.mav.clock`           ``Clock``, ``frame_log_times``, ``estimate_clock_offset``
:mod:`stablecues.mav.solutions`       ``PoseSource``, ``gnss_solution``, ``log_solution``,
                                      ``resample_solution``
:mod:`stablecues.mav.poses`           ``Mount``, ``MOUNTS``, ``FramePoses``, ``poses_for_frames``,
                                      ``pose_matrices``
:mod:`stablecues.mav.loops`           ``loops_from_trajectory``
:mod:`stablecues.mav.export`          ``write_image_folder``, ``write_poses``, ``tum_comments``
:mod:`stablecues.trajectory`          ``read_tum`` / ``write_tum`` ((M, 4, 4) poses)
:mod:`stablecues.imageio`             ``IMAGE_SUFFIXES``
:mod:`stablecues.geometry.rotations`  ``yaw_of`` (NaN-tolerant: :func:`stablecues.mav.geo.known_yaw`)
====================================  ==========================================================

Quaternions are (x, y, z, w), scalar last, everywhere now, also in the old names kept here
(``FramePoses.quaternions`` and this module's :func:`read_tum` / :func:`write_tum` were
(w, x, y, z) before).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from .. import trajectory
from ..geometry.rotations import matrix_to_quat
from ..imageio import IMAGE_SUFFIXES
from .clock import Clock, estimate_clock_offset, frame_log_times
from .export import tum_comments, write_image_folder
from .frames import FrameSet, read_frames
from .geo import known_yaw as yaw_of
from .loops import loops_from_trajectory
from .poses import MOUNTS, FramePoses, Mount, pose_matrices, poses_for_frames
from .solutions import PoseSource, gnss_solution, log_solution, resample_solution

__all__ = [
    "IMAGE_SUFFIXES",
    "MOUNTS",
    "Clock",
    "FramePoses",
    "FrameSet",
    "Mount",
    "PoseSource",
    "estimate_clock_offset",
    "frame_log_times",
    "gnss_solution",
    "log_solution",
    "loops_from_trajectory",
    "poses_for_frames",
    "read_frames",
    "read_tum",
    "resample_solution",
    "tum_comments",
    "write_image_folder",
    "write_tum",
    "yaw_of",
]

warnings.warn(
    "stablecues.mav.sync is deprecated and goes in 0.3: import from stablecues.mav.frames, clock, "
    "solutions, poses, loops, export, and stablecues.trajectory for TUM files",
    DeprecationWarning,
    stacklevel=2,
)


def write_tum(
    path: str | Path,
    times: np.ndarray,
    positions: np.ndarray,
    quaternions: np.ndarray,
    *,
    comments: tuple[str, ...] = (),
) -> int:
    """Deprecated: :func:`stablecues.trajectory.write_tum` of :func:`~stablecues.mav.poses.pose_matrices`.

    Args:
        path: output file.
        times: (N,) float64 seconds.
        positions: (N, 3) float64.
        quaternions: (N, 4) float64 (x, y, z, w).
        comments: lines written first, each prefixed with ``# ``.

    Returns:
        The number of poses written (rows with a NaN are skipped).
    """
    return trajectory.write_tum(path, times, pose_matrices(positions, quaternions), comments=comments)


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Deprecated: :func:`stablecues.trajectory.read_tum`, split into positions and quaternions.

    Returns:
        times (N,) float64, positions (N, 3) float64, quaternions (N, 4) float64 (x, y, z, w).
    """
    times, poses = trajectory.read_tum(path)
    quats = matrix_to_quat(poses[:, :3, :3]) if len(poses) else np.zeros((0, 4))
    return times, poses[:, :3, 3].copy(), quats
