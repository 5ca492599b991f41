"""Which navigation solution camera poses come from: this package's EKF, the autopilot's, or GNSS.

Every solution is a :class:`~stablecues.mav.flightlog.NavSolution` in ENU metres; quaternions
are (x, y, z, w), NaN rows where the attitude is unknown.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from ..errors import InputError
from ..geometry.rotations import euler_zyx_to_quat
from . import geo
from .ekf import EkfConfig, run_ekf
from .flightlog import FlightLog, NavSolution

__all__ = ["PoseSource", "gnss_solution", "log_solution", "resample_solution"]

PoseSource = Literal["auto", "ekf", "onboard", "gnss"]


def gnss_solution(log: FlightLog, *, min_fix: int = 3) -> NavSolution:
    """The GNSS track as a navigation solution (ENU about the first fix).

    Attitude comes from the log's own attitude estimate when it has one (NaN otherwise);
    velocity from the receiver (NaN when not reported).

    Raises:
        InputError: no fix of at least ``min_fix``.
    """
    g = log.gnss
    ok = (g.fix >= min_fix) & np.isfinite(g.lat) & np.isfinite(g.lon) & np.isfinite(g.alt)
    if not np.any(ok):
        raise InputError(f"{log.path}: no GNSS fix of type >= {min_fix}")
    g = g.subset(ok)
    order = np.argsort(g.t, kind="stable")
    g = g.subset(order)
    origin = (float(g.lat[0]), float(g.lon[0]), float(g.alt[0]))
    pos = geo.geodetic_to_enu(g.lat, g.lon, g.alt, origin)
    quat = np.full((len(g), 4), np.nan)
    att = log.attitude
    if len(att) >= 2:
        inside = (g.t >= att.t[0]) & (g.t <= att.t[-1])
        q_ned = euler_zyx_to_quat(att.rpy[:, 0], att.rpy[:, 1], att.rpy[:, 2])
        quat[inside] = geo.ned_to_enu_quat(geo.slerp_known(att.t, q_ned, g.t[inside]))
    return NavSolution("gnss", origin, g.t, pos, g.vel_ned @ geo.R_ENU_NED.T, quat, np.full_like(pos, np.nan))


def log_solution(
    log: FlightLog, source: PoseSource = "auto", ekf_config: object | None = None
) -> NavSolution:
    """The navigation solution poses are taken from.

    Args:
        log: the flight log.
        source: "ekf" (:func:`stablecues.mav.ekf.run_ekf`), "onboard" (the autopilot's EKF),
            "gnss" (:func:`gnss_solution`), or "auto": ekf when the log has IMU and GNSS, else
            onboard when present, else gnss.
        ekf_config: an :class:`~stablecues.mav.ekf.EkfConfig` for the "ekf" source.

    Raises:
        InputError: the chosen source is not available in this log.
    """
    if source == "auto":
        has_fix = bool(np.any(log.gnss.fix >= 3))
        source = (
            "ekf" if len(log.imu) >= 2 and has_fix else ("onboard" if log.onboard is not None else "gnss")
        )
    if source == "ekf":
        cfg = ekf_config if isinstance(ekf_config, EkfConfig) else None
        solution, _ = run_ekf(log, cfg)
        return solution
    if source == "onboard":
        if log.onboard is None:
            raise InputError(f"{log.path}: the log has no onboard navigation solution")
        return log.onboard
    if source == "gnss":
        return gnss_solution(log)
    raise InputError(f"source: expected auto, ekf, onboard or gnss, got {source!r}")


def resample_solution(solution: NavSolution, rate_hz: float) -> NavSolution:
    """The solution at a regular rate over its span (for poses without camera frames).

    Raises:
        InputError: non-positive rate.
    """
    if not rate_hz > 0:
        raise InputError(f"rate_hz: expected > 0, got {rate_hz}")
    if len(solution) == 0:
        return solution
    t = np.arange(solution.t[0], solution.t[-1] + 1e-9, 1.0 / rate_hz)
    return solution.interpolate(t)
