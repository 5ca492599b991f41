"""Rotations and quaternions: the one place stablecues converts between them.

**Quaternion order: (x, y, z, w), scalar last**, everywhere in stablecues: as SciPy's
``Rotation``, ROS messages, Eigen's ``coeffs()`` and the TUM trajectory format store them.
Files that store another order (EuRoC's ``w x y z`` ground truth) are converted where they are
read or written, with :func:`wxyz_to_xyzw` / :func:`xyzw_to_wxyz`. Every function takes
(..., 4) arrays and works over the leading dimensions.

SciPy's :class:`~scipy.spatial.transform.Rotation` does the conversions (matrices, Euler angles,
rotation vectors, interpolation). The Hamilton product and the quaternion-to-matrix formula are
written out because the EKF calls them once per IMU sample, where SciPy's per-call overhead
(~20 us) would dominate; tests check them against SciPy.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ..errors import InputError

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
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if not (np.isfinite(norm).all() and (norm > _MIN_NORM).all()):
        raise InputError("quaternions: found one of zero or non-finite norm, which is no rotation")
    q = q / norm
    return np.where(q[..., 3:] < 0, -q, q)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` (apply ``b`` first, then ``a``) of (..., 4) quaternions."""
    ax, ay, az, aw = np.moveaxis(_as_quat(a), -1, 0)
    bx, by, bz, bw = np.moveaxis(_as_quat(b), -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """The inverse rotation of (..., 4) unit quaternions."""
    return _as_quat(q) * np.array([-1.0, -1.0, -1.0, 1.0])


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions -> (..., 3, 3) rotation matrices (normalised first).

    Raises:
        InputError: a zero or non-finite quaternion.
    """
    x, y, z, w = np.moveaxis(quat_normalize(q), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions with w >= 0."""
    r = np.asarray(r, dtype=np.float64)
    if r.shape[-2:] != (3, 3):
        raise InputError(f"rotation matrices: expected shape (..., 3, 3), got {r.shape}")
    q = Rotation.from_matrix(r.reshape(-1, 3, 3)).as_quat()
    return quat_normalize(q).reshape(r.shape[:-2] + (4,))


def quat_from_rotvec(v: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors (axis * angle, radians) -> (..., 4) quaternions."""
    v = np.asarray(v, dtype=np.float64)
    return Rotation.from_rotvec(v.reshape(-1, 3)).as_quat().reshape(v.shape[:-1] + (4,))


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions -> (..., 3) rotation vectors (axis * angle, radians)."""
    q = quat_normalize(q)
    return Rotation.from_quat(q.reshape(-1, 4)).as_rotvec().reshape(q.shape[:-1] + (3,))


def euler_zyx_to_quat(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Quaternions of aerospace Z-Y-X Euler angles (radians): ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

    Args:
        roll, pitch, yaw: arrays of one shape S (scalars allowed).

    Returns:
        (*S, 4) float64 quaternions.
    """
    r, p, y = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (roll, pitch, yaw)))
    angles = np.stack([y, p, r], axis=-1).reshape(-1, 3)
    return Rotation.from_euler("ZYX", angles).as_quat().reshape(r.shape + (4,))


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
        times: (M,) float64 strictly increasing sample times.
        quats: (M, 4) quaternions at ``times``.
        query: (N,) float64 times; those outside ``[times[0], times[-1]]`` are clamped to it.

    Returns:
        (N, 4) float64 unit quaternions (w >= 0).
    """
    times = np.asarray(times, dtype=np.float64)
    quats = quat_normalize(quats)
    query = np.asarray(query, dtype=np.float64)
    if len(times) == 1:
        return np.repeat(quats, len(query), axis=0)
    slerp = Slerp(times, Rotation.from_quat(quats))
    return quat_normalize(slerp(np.clip(query, times[0], times[-1])).as_quat())


def wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """Reorder (..., 4) quaternions stored scalar first (EuRoC, Eigen's constructor) to ours."""
    q = _as_quat(q)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """Reorder (..., 4) quaternions (x, y, z, w) to scalar first, for files that want it."""
    q = _as_quat(q)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)
