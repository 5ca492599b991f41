"""Rotations and quaternions: the one place stablecues converts between them.

**Quaternion order: (x, y, z, w), scalar last**, everywhere in stablecues: as SciPy's
``Rotation``, ROS messages, Eigen's ``coeffs()`` and the TUM trajectory format store them.
Files that store another order (EuRoC's ``w x y z`` ground truth) are converted where they are
read or written, with :func:`wxyz_to_xyzw` / :func:`xyzw_to_wxyz`. Every function takes
(..., 4) arrays and works over the leading dimensions.

SciPy's :class:`~scipy.spatial.transform.Rotation` does the conversions (matrices, Euler angles,
rotation vectors, interpolation). The Hamilton product and the quaternion-to-matrix formula are
written out, and one quaternion or rotation vector takes a Python-float path, because the EKF
calls them once per IMU sample, where SciPy's and NumPy's per-call overhead (~10-20 us) would
dominate; tests check every path against SciPy. SciPy is imported when one of its
conversions is first used (its import takes 0.3 s, most of a process's start).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from ..errors import InputError

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation

__all__ = [
    "euler_zyx_to_quat",
    "matrix_to_quat",
    "quat_conjugate",
    "quat_from_rotvec",
    "quat_multiply",
    "quat_normalize",
    "quat_slerp",
    "quat_to_euler_zyx",
    "quat_to_matrix",
    "quat_to_rotvec",
    "wxyz_to_xyzw",
    "xyzw_to_wxyz",
    "yaw_of",
]

_MIN_NORM = 1e-12
_ZERO_QUAT = "quaternions: found one of zero or non-finite norm, which is no rotation"

_T = TypeVar("_T", float, np.ndarray)  # one quaternion's components, or arrays of them


def _rotation() -> type[Rotation]:
    """SciPy's ``Rotation``, imported on first use."""
    from scipy.spatial.transform import Rotation

    return Rotation


def _as_quat(q: np.ndarray, name: str = "quaternions") -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1:] != (4,):
        raise InputError(f"{name}: expected shape (..., 4) (x, y, z, w), got {q.shape}")
    return q


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternions with a non-negative scalar part, (..., 4) float64.

    Raises:
        InputError: a quaternion of zero (or non-finite) norm: it is no rotation.
    """
    q = _as_quat(q)
    if q.ndim == 1:  # one quaternion (the EKF's case): Python floats, ~10x faster
        x, y, z, w = q.tolist()
        n = math.sqrt(x * x + y * y + z * z + w * w)
        if not (math.isfinite(n) and n > _MIN_NORM):
            raise InputError(_ZERO_QUAT)
        return np.array([x / n, y / n, z / n, w / n] if w >= 0 else [-x / n, -y / n, -z / n, -w / n])
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if not (np.isfinite(norm).all() and (norm > _MIN_NORM).all()):
        raise InputError(_ZERO_QUAT)
    q = q / norm
    return np.where(q[..., 3:] < 0, -q, q)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` (apply ``b`` first, then ``a``) of (..., 4) quaternions."""
    a, b = _as_quat(a), _as_quat(b)
    if a.ndim == 1 and b.ndim == 1:  # one pair (the EKF's case): Python floats, ~10x faster
        return np.array(_mul4(*a.tolist(), *b.tolist()))
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack(_mul4(ax, ay, az, aw, bx, by, bz, bw), axis=-1)


def _mul4(ax: _T, ay: _T, az: _T, aw: _T, bx: _T, by: _T, bz: _T, bw: _T) -> list[_T]:
    return [
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ]


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """The inverse rotation of (..., 4) unit quaternions."""
    return _as_quat(q) * np.array([-1.0, -1.0, -1.0, 1.0])


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions -> (..., 3, 3) rotation matrices (normalised first).

    Raises:
        InputError: a zero or non-finite quaternion.
    """
    q = quat_normalize(q)
    if q.ndim == 1:  # one quaternion (the EKF's case): Python floats, ~10x faster
        return np.array(_matrix_rows(*q.tolist()))
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([np.stack(row, axis=-1) for row in _matrix_rows(x, y, z, w)], axis=-2)


def _matrix_rows(x: _T, y: _T, z: _T, w: _T) -> list[list[_T]]:
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions with w >= 0."""
    r = np.asarray(r, dtype=np.float64)
    if r.shape[-2:] != (3, 3):
        raise InputError(f"rotation matrices: expected shape (..., 3, 3), got {r.shape}")
    q = _rotation().from_matrix(r.reshape(-1, 3, 3)).as_quat()
    return quat_normalize(q).reshape(r.shape[:-2] + (4,))


def quat_from_rotvec(v: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors (axis * angle, radians) -> (..., 4) quaternions."""
    v = np.asarray(v, dtype=np.float64)
    if v.shape == (3,):  # one vector (the EKF's case): SciPy's formula in Python floats
        x, y, z = v.tolist()
        angle = math.sqrt(x * x + y * y + z * z)
        if angle <= 1e-3:  # Taylor series of sin(angle / 2) / angle
            a2 = angle * angle
            scale = 0.5 - a2 / 48 + a2 * a2 / 3840
        else:
            scale = math.sin(angle / 2) / angle
        return np.array([x * scale, y * scale, z * scale, math.cos(angle / 2)])
    return _rotation().from_rotvec(v.reshape(-1, 3)).as_quat().reshape(v.shape[:-1] + (4,))


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions -> (..., 3) rotation vectors (axis * angle, radians)."""
    q = quat_normalize(q)
    return _rotation().from_quat(q.reshape(-1, 4)).as_rotvec().reshape(q.shape[:-1] + (3,))


def euler_zyx_to_quat(
    roll: np.ndarray | float, pitch: np.ndarray | float, yaw: np.ndarray | float
) -> np.ndarray:
    """Quaternions of aerospace Z-Y-X Euler angles (radians): ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

    Args:
        roll, pitch, yaw: arrays of one shape S (scalars allowed).

    Returns:
        (*S, 4) float64 quaternions.
    """
    r, p, y = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (roll, pitch, yaw)))
    angles = np.stack([y, p, r], axis=-1).reshape(-1, 3)
    return _rotation().from_euler("ZYX", angles).as_quat().reshape(r.shape + (4,))


def quat_to_euler_zyx(q: np.ndarray) -> np.ndarray:
    """Aerospace roll, pitch, yaw (radians) of (..., 4) quaternions; returns (..., 3)."""
    q = quat_normalize(q)
    x, y, z, w = np.moveaxis(q, -1, 0)
    # written out rather than Rotation.as_euler: SciPy warns (gimbal lock) at pitch = +-90 deg
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=-1)


def yaw_of(q: np.ndarray) -> np.ndarray:
    """Heading (rotation about the world z axis, ZYX yaw) of (..., 4) quaternions, radians.

    A rotation about the vertical by ``a`` adds ``a`` to this yaw whatever the body's roll and
    pitch, so yaw differences compare headings.
    """
    r = quat_to_matrix(q)
    return np.arctan2(r[..., 1, 0], r[..., 0, 0])


def quat_slerp(times: np.ndarray, quats: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of a quaternion track (SciPy's ``Slerp``).

    Args:
        times: (M,) float64 non-decreasing sample times, M >= 1; of samples sharing a time the
            last one is used (logs repeat stamps).
        quats: (M, 4) quaternions at ``times``.
        query: (N,) float64 times; those outside ``[times[0], times[-1]]`` are clamped to it.

    Returns:
        (N, 4) float64 unit quaternions (w >= 0).

    Raises:
        InputError: no sample, times and quaternions of different lengths, decreasing times, or
            a zero or non-finite quaternion.
    """
    times = np.asarray(times, dtype=np.float64)
    quats = quat_normalize(quats)
    query = np.asarray(query, dtype=np.float64)
    if times.ndim != 1 or len(times) == 0 or quats.shape != (len(times), 4):
        raise InputError(
            f"slerp: expected (M,) times and (M, 4) quaternions, M >= 1, got {times.shape} and {quats.shape}"
        )
    step = np.diff(times)
    if np.any(step < 0) or not np.isfinite(times).all():
        raise InputError("slerp: sample times must be finite and non-decreasing")
    last = np.r_[step > 0, True]  # the last sample of each run of equal times
    times, quats = times[last], quats[last]
    if len(times) == 1:
        return np.repeat(quats, len(query), axis=0)
    from scipy.spatial.transform import Slerp

    slerp = Slerp(times, _rotation().from_quat(quats))
    return quat_normalize(slerp(np.clip(query, times[0], times[-1])).as_quat())


def wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """Reorder (..., 4) quaternions stored scalar first (EuRoC, Eigen's constructor) to ours."""
    q = _as_quat(q)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """Reorder (..., 4) quaternions (x, y, z, w) to scalar first, for files that want it."""
    q = _as_quat(q)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)
