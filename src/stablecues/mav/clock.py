"""Camera clocks against a flight log's clock: mapping frame times, estimating an offset.

The log's clock is seconds since the log's first record. Frame times in UNIX seconds are mapped
through the log's GNSS time, times on the autopilot's boot clock through its boot offset; a
remaining camera clock error is either given or estimated from the frames' geotags against the
GNSS track (:func:`estimate_clock_offset`).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from ..errors import DatasetError, InputError, check_array
from . import geo
from .flightlog import FlightLog, NavSolution
from .frames import FrameSet

__all__ = ["Clock", "estimate_clock_offset", "frame_log_times"]

Clock = Literal["auto", "utc", "boot", "log"]


def frame_log_times(
    frames: FrameSet, log: FlightLog, *, clock: Clock = "auto", offset: float = 0.0
) -> np.ndarray:
    """The frames' capture times on the log's clock (seconds since log start).

    Args:
        frames: the frames.
        log: the flight log.
        clock: what the frame times are: "utc" (UNIX seconds, mapped through the log's GNSS
            time), "boot" (the autopilot's boot clock), "log" (already seconds since log start),
            or "auto" (UNIX when they look like it, else boot).
        offset: seconds added after the mapping (a known camera clock error).

    Returns:
        (N,) float64.

    Raises:
        DatasetError: UTC frame times but a log without GNSS time, or a boot-clock mapping
            for a log that has none.
    """
    if clock == "auto":
        clock = "utc" if frames.is_utc else "boot"
    if clock == "utc":
        if not np.isfinite(log.utc_offset):
            raise DatasetError(f"{log.path}: frame times are UTC but the log has no GNSS time to map them")
        base = frames.times - log.utc_offset
    elif clock == "boot":
        if not np.isfinite(log.boot_time_offset):
            raise DatasetError(f"{log.path}: frame times are on the boot clock but the log has no boot clock")
        base = frames.times - log.boot_time_offset
    elif clock == "log":
        base = frames.times.copy()
    else:
        raise InputError(f"clock: expected auto, utc, boot or log, got {clock!r}")
    return np.asarray(base + float(offset), dtype=np.float64)


def estimate_clock_offset(
    log_times: np.ndarray,
    geotags: np.ndarray,
    track: NavSolution,
    *,
    search_s: float = 30.0,
    step_s: float = 0.05,
) -> tuple[float, float]:
    """Clock offset that best places geotagged frames on a track.

    Searches ``offset`` in ``[-search_s, search_s]`` minimising the RMS horizontal distance between
    each frame's geotag and the track at ``log_times + offset`` (grid of ``step_s``, then a
    parabolic refinement). Frames whose shifted time leaves the track are ignored for that offset.

    Args:
        log_times: (N,) frame times on the log's clock, s.
        geotags: (N, 3) latitude, longitude, altitude (altitude unused).
        track: the solution to match against (GNSS track or EKF).

    Returns:
        (offset in seconds to add to ``log_times``, RMS horizontal residual in metres).

    Raises:
        InputError: fewer than 2 finite geotags, or no offset with enough overlap.
    """
    log_times = np.asarray(log_times, dtype=np.float64)
    geotags = np.asarray(geotags, dtype=np.float64)
    check_array("geotags", geotags, shape=(len(log_times), 3))
    ok = np.isfinite(geotags[:, :2]).all(axis=1) & np.isfinite(log_times)
    if ok.sum() < 2:
        raise InputError("estimating a clock offset needs at least 2 geotagged frames")
    tag_enu = geo.geodetic_to_enu(geotags[ok, 0], geotags[ok, 1], np.zeros(int(ok.sum())), track.origin)[
        :, :2
    ]
    ft = log_times[ok]
    need = max(2, int(0.5 * ok.sum()))

    def cost(off: float) -> float:
        tt = ft + off
        inside = (tt >= track.t[0]) & (tt <= track.t[-1])
        if inside.sum() < need:
            return np.inf
        e = np.interp(tt[inside], track.t, track.position[:, 0]) - tag_enu[inside, 0]
        n = np.interp(tt[inside], track.t, track.position[:, 1]) - tag_enu[inside, 1]
        return float(np.mean(e * e + n * n))

    grid = np.arange(-search_s, search_s + 0.5 * step_s, step_s)
    costs = np.array([cost(float(o)) for o in grid])
    if not np.any(np.isfinite(costs)):
        raise InputError("no clock offset within the search range overlaps frames and track")
    k = int(np.nanargmin(costs))
    best = float(grid[k])
    if 0 < k < len(grid) - 1 and np.all(np.isfinite(costs[k - 1 : k + 2])):
        c0, c1, c2 = costs[k - 1], costs[k], costs[k + 1]
        denom = c0 - 2 * c1 + c2
        if denom > 0:
            best += 0.5 * step_s * (c0 - c2) / denom
    return best, float(np.sqrt(cost(best)))
