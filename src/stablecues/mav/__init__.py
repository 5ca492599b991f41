"""Drone (MAV) recordings: flight logs, sensor fusion into poses, camera sync, flight plots.

* :mod:`~stablecues.mav.logs` -- ArduPilot dataflash / PX4 ULog / GNSS CSV -> :class:`FlightLog`;
* :mod:`~stablecues.mav.ekf` -- an error-state EKF (IMU + GNSS + baro + compass) -> :class:`NavSolution`;
* camera frames: :mod:`~stablecues.mav.frames` (images and capture times),
  :mod:`~stablecues.mav.clock` (frame times on the log's clock, offsets),
  :mod:`~stablecues.mav.solutions` (EKF, onboard or GNSS solution), :mod:`~stablecues.mav.poses`
  (a pose per frame), :mod:`~stablecues.mav.loops` (loop ground truth),
  :mod:`~stablecues.mav.export` (TUM poses, the project's image-folder dataset);
  ``stablecues.mav.sync`` is their deprecated former home;
* :mod:`~stablecues.mav.plots` -- the paper's flight figures (trajectory, altitude with flight-mode
  bands, latitude/longitude/altitude panels, roll/pitch/yaw).

Frames and units: :mod:`~stablecues.mav.geo`. Quaternions are (x, y, z, w), scalar last, as
everywhere in stablecues (:mod:`stablecues.geometry.rotations`).

pymavlink, pyulog and pymap3d are optional (``pip install "stablecues[mav]"``); they are imported
only when a function needs them.
"""

from .ekf import EkfConfig, EkfReport, NavigationFilter, SolutionComparison, compare_solutions, run_ekf
from .flightlog import (
    AttitudeSeries,
    BaroSeries,
    FlightLog,
    GnssFixes,
    ImuSeries,
    MagSeries,
    ModeChange,
    ModeSpan,
    NavSolution,
    mode_spans,
)
from .logs import TruncatedLogWarning, detect_format, read_log

__all__ = [
    "AttitudeSeries",
    "BaroSeries",
    "EkfConfig",
    "EkfReport",
    "FlightLog",
    "GnssFixes",
    "ImuSeries",
    "MagSeries",
    "ModeChange",
    "ModeSpan",
    "NavSolution",
    "NavigationFilter",
    "SolutionComparison",
    "TruncatedLogWarning",
    "compare_solutions",
    "detect_format",
    "mode_spans",
    "read_log",
    "run_ekf",
]
