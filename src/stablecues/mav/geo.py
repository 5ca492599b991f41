"""Frames and rotations for flight data: geodetic <-> local ENU, quaternions, Euler angles.

Conventions used throughout :mod:`stablecues.mav`:

* World frame: local East-North-Up (ENU) metres about an origin ``(lat, lon, alt)``
  (degrees, degrees, metres above mean sea level), through :mod:`pymap3d` on the WGS84
  ellipsoid. Autopilots log North-East-Down (NED); :data:`R_ENU_NED` converts.
* Body frame: the autopilots' Forward-Right-Down (FRD).
* Quaternions: Hamilton, scalar first ``(w, x, y, z)``, rotating body vectors into the world
  frame (``v_world = R(q) @ v_body``).
* Euler angles: aerospace roll, pitch, yaw (ZYX) of the body relative to NED, radians, yaw in
  (-pi, pi] clockwise from north -- what ArduPilot and PX4 log as Roll/Pitch/Yaw.
"""

from __future__ import annotations

from typing import Any

import numpy as np

# NED vector -> ENU vector (a proper rotation: 180 degrees about (1, 1, 0)/sqrt(2)).
R_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_Q_ENU_NED = np.array([0.0, np.sqrt(0.5), np.sqrt(0.5), 0.0])

MAV_EXTRA_HINT = 'pip install "stablecues[mav]"'


def import_pymap3d() -> Any:
    """Import :mod:`pymap3d` or raise ImportError with the install hint."""
    try:
        import pymap3d
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(f"geodetic conversions need pymap3d: {MAV_EXTRA_HINT}") from exc
    return pymap3d


def geodetic_to_enu(
    lat: np.ndarray, lon: np.ndarray, alt: np.ndarray, origin: tuple[float, float, float]
) -> np.ndarray:
    """Geodetic coordinates to local ENU metres about ``origin``.

    Args:
        lat, lon: (N,) float64 degrees.
        alt: (N,) float64 metres (same vertical datum as ``origin[2]``).
        origin: (lat deg, lon deg, alt m).

    Returns:
        (N, 3) float64 east, north, up in metres.
    """
    pm = import_pymap3d()
    e, n, u = pm.geodetic2enu(
        np.asarray(lat, dtype=np.float64),
        np.asarray(lon, dtype=np.float64),
        np.asarray(alt, dtype=np.float64),
        origin[0],
        origin[1],
        origin[2],
    )
    return np.stack([np.asarray(e), np.asarray(n), np.asarray(u)], axis=-1).reshape(-1, 3)


def enu_to_geodetic(enu: np.ndarray, origin: tuple[float, float, float]) -> np.ndarray:
    """Local ENU metres about ``origin`` to geodetic.

    Args:
        enu: (N, 3) float64 east, north, up metres.
        origin: (lat deg, lon deg, alt m).

    Returns:
        (N, 3) float64 latitude deg, longitude deg, altitude m.
    """
    pm = import_pymap3d()
    enu = np.asarray(enu, dtype=np.float64).reshape(-1, 3)
    lat, lon, alt = pm.enu2geodetic(enu[:, 0], enu[:, 1], enu[:, 2], origin[0], origin[1], origin[2])
    return np.stack([np.asarray(lat), np.asarray(lon), np.asarray(alt)], axis=-1).reshape(-1, 3)


# ---------------------------------------------------------------------------------------------
# Quaternions (w, x, y, z), vectorised over leading dimensions.


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of (..., 4) quaternions."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternions with a non-negative scalar part; (..., 4) float64."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quat_from_rotvec(v: np.ndarray) -> np.ndarray:
    """Quaternion of the rotation vector ``v`` (axis * angle, radians); (..., 3) -> (..., 4)."""
    v = np.asarray(v, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(x/2)/x with its series near zero
    small = angle < 1e-8
    k = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    return np.concatenate([np.cos(half), k * v], axis=-1)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of (..., 4) unit quaternions; returns (..., 3, 3)."""
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternions (w >= 0) of (..., 3, 3) rotation matrices."""
    from scipy.spatial.transform import Rotation

    r = np.asarray(r, dtype=np.float64)
    flat = r.reshape(-1, 3, 3)
    xyzw = Rotation.from_matrix(flat).as_quat()
    q = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    return quat_normalize(q).reshape(r.shape[:-2] + (4,))


def euler_to_quat(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Quaternion body->NED from aerospace ZYX Euler angles in radians; (N,) each -> (N, 4)."""
    cr, sr = np.cos(0.5 * np.asarray(roll)), np.sin(0.5 * np.asarray(roll))
    cp, sp = np.cos(0.5 * np.asarray(pitch)), np.sin(0.5 * np.asarray(pitch))
    cy, sy = np.cos(0.5 * np.asarray(yaw)), np.sin(0.5 * np.asarray(yaw))
    return np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )


def quat_to_euler(q_ned: np.ndarray) -> np.ndarray:
    """Aerospace roll, pitch, yaw (radians) of (..., 4) body->NED quaternions; returns (..., 3)."""
    q = np.asarray(q_ned, dtype=np.float64)
    w, x, y, z = np.moveaxis(q, -1, 0)
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=-1)


def ned_to_enu_quat(q_ned: np.ndarray) -> np.ndarray:
    """Body->NED quaternions to body->ENU quaternions; (..., 4) -> (..., 4)."""
    return quat_normalize(quat_multiply(np.broadcast_to(_Q_ENU_NED, np.shape(q_ned)), q_ned))


def enu_to_ned_quat(q_enu: np.ndarray) -> np.ndarray:
    """Body->ENU quaternions to body->NED quaternions; (..., 4) -> (..., 4)."""
    conj = _Q_ENU_NED * np.array([1.0, -1.0, -1.0, -1.0])
    return quat_normalize(quat_multiply(np.broadcast_to(conj, np.shape(q_enu)), q_enu))


def quat_slerp(times: np.ndarray, quats: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Spherical interpolation of a quaternion track.

    Args:
        times: (M,) float64 increasing sample times.
        quats: (M, 4) unit quaternions (w, x, y, z) at ``times``.
        query: (N,) float64 times inside ``[times[0], times[-1]]``.

    Returns:
        (N, 4) float64 unit quaternions (w >= 0).
    """
    times = np.asarray(times, dtype=np.float64)
    quats = quat_normalize(np.asarray(quats, dtype=np.float64))
    query = np.asarray(query, dtype=np.float64)
    if len(times) == 1:
        return np.repeat(quats, len(query), axis=0)
    i = np.clip(np.searchsorted(times, query, side="right") - 1, 0, len(times) - 2)
    span = times[i + 1] - times[i]
    u = np.clip((query - times[i]) / np.where(span > 0, span, 1.0), 0.0, 1.0)[:, None]
    a, b = quats[i], quats[i + 1]
    dot = np.sum(a * b, axis=1, keepdims=True)
    b = np.where(dot < 0, -b, b)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_t = np.sin(theta)
    near = sin_t < 1e-9
    wa = np.where(near, 1.0 - u, np.sin((1.0 - u) * theta) / np.where(near, 1.0, sin_t))
    wb = np.where(near, u, np.sin(u * theta) / np.where(near, 1.0, sin_t))
    return quat_normalize(wa * a + wb * b)


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + np.pi) % (2.0 * np.pi) - np.pi
