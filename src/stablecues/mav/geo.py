"""Frames for flight data: geodetic <-> local ENU, NED <-> ENU attitude, angles.

Conventions used throughout :mod:`stablecues.mav`:

* World frame: local East-North-Up (ENU) metres about an origin ``(lat, lon, alt)``
  (degrees, degrees, metres above mean sea level), through :mod:`pymap3d` on the WGS84
  ellipsoid. Autopilots log North-East-Down (NED); :data:`R_ENU_NED` converts.
* Body frame: the autopilots' Forward-Right-Down (FRD).
* Quaternions: Hamilton, **(x, y, z, w), scalar last**, as everywhere in stablecues
  (:mod:`stablecues.geometry.rotations` does all quaternion arithmetic), rotating body vectors
  into the world frame (``v_world = R(q) @ v_body``). A row of NaN is an unknown attitude
  (:class:`~stablecues.mav.flightlog.NavSolution` without one); the helpers here pass such rows
  through, where the rotations functions would reject them.
* Euler angles: aerospace roll, pitch, yaw (ZYX) of the body relative to NED, radians, yaw in
  (-pi, pi] clockwise from north -- what ArduPilot and PX4 log as Roll/Pitch/Yaw.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ..errors import InputError, MissingDependencyError
from ..geometry.rotations import quat_conjugate, quat_multiply, quat_normalize, quat_slerp, yaw_of

# NED vector -> ENU vector (a proper rotation: 180 degrees about (1, 1, 0)/sqrt(2)).
R_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
Q_ENU_NED = np.array([np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0])
"""The same rotation as a quaternion (x, y, z, w)."""

MAV_EXTRA_HINT = 'pip install "stablecues[mav]"'


def import_pymap3d() -> Any:
    """Import :mod:`pymap3d` or raise ImportError with the install hint."""
    try:
        import pymap3d
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingDependencyError(f"geodetic conversions need pymap3d: {MAV_EXTRA_HINT}") from exc
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
# Attitude with unknowns: NaN rows pass through


def known_attitude(q: np.ndarray) -> np.ndarray:
    """(...,) bool: the (..., 4) quaternions that are a rotation (finite, norm above 1e-12, as
    :func:`~stablecues.geometry.rotations.quat_normalize` demands): a known attitude."""
    q = np.asarray(q, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        return np.isfinite(q).all(axis=-1) & (np.linalg.norm(np.nan_to_num(q), axis=-1) > 1e-12)


def map_known(fn: Callable[[np.ndarray], np.ndarray], q: np.ndarray, width: int) -> np.ndarray:
    """``fn`` applied to the known rows of (N, 4) quaternions, NaN rows of ``width`` elsewhere.

    Args:
        fn: a vectorised function of (M, 4) quaternions returning (M, width) (a rotations
            function such as :func:`~stablecues.geometry.rotations.quat_to_euler_zyx`).
        q: (N, 4) float64 quaternions, NaN (or zero) where the attitude is unknown.
        width: the length of ``fn``'s rows.

    Returns:
        (N, width) float64.

    Raises:
        InputError: ``q`` is not (..., 4).
    """
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1:] != (4,):
        raise InputError(f"quaternions: expected shape (..., 4) (x, y, z, w), got {q.shape}")
    flat = q.reshape(-1, 4)
    out = np.full((flat.shape[0], width), np.nan)
    ok = known_attitude(flat)
    if ok.any():
        out[ok] = fn(flat[ok])
    return out.reshape(q.shape[:-1] + (width,))


def rotate_known(q_left: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``normalize(q_left * q)`` of (N, 4) quaternions ``q`` (NaN rows stay NaN); q_left (4,)."""
    left = np.asarray(q_left, dtype=np.float64)
    return map_known(lambda k: quat_normalize(quat_multiply(np.broadcast_to(left, k.shape), k)), q, 4)


def ned_to_enu_quat(q_ned: np.ndarray) -> np.ndarray:
    """Body->NED quaternions (x, y, z, w) to body->ENU ones; (N, 4) -> (N, 4), NaN rows stay."""
    return rotate_known(Q_ENU_NED, q_ned)


def enu_to_ned_quat(q_enu: np.ndarray) -> np.ndarray:
    """Body->ENU quaternions (x, y, z, w) to body->NED ones; (N, 4) -> (N, 4), NaN rows stay."""
    return rotate_known(quat_conjugate(Q_ENU_NED), q_enu)


def known_yaw(q: np.ndarray) -> np.ndarray:
    """Heading (ZYX yaw about the world vertical, radians) of (N, 4) quaternions; NaN where the
    attitude is unknown. See :func:`~stablecues.geometry.rotations.yaw_of`."""
    return map_known(lambda k: yaw_of(k)[..., None], q, 1)[..., 0]


def slerp_known(times: np.ndarray, quats: np.ndarray, query: np.ndarray) -> np.ndarray:
    """:func:`~stablecues.geometry.rotations.quat_slerp` over the known samples of a track.

    Args:
        times: (M,) float64 non-decreasing times.
        quats: (M, 4) quaternions (x, y, z, w), NaN or zero where unknown (those are skipped).
        query: (N,) float64 times.

    Returns:
        (N, 4) float64; all NaN when no sample is known.
    """
    ok = known_attitude(quats)
    query = np.asarray(query, dtype=np.float64)
    if not ok.any():
        return np.full((len(query), 4), np.nan)
    return quat_slerp(np.asarray(times, dtype=np.float64)[ok], np.asarray(quats)[ok], query)


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + np.pi) % (2.0 * np.pi) - np.pi
