"""Drone (MAV) recordings: flight logs, sensor fusion into poses, camera sync, flight plots.

* :mod:`~stablecues.mav.logs` -- ArduPilot dataflash / PX4 ULog / GNSS CSV -> :class:`FlightLog`;
* :mod:`~stablecues.mav.ekf` -- an error-state EKF (IMU + GNSS + baro + compass) -> :class:`NavSolution`;
* :mod:`~stablecues.mav.sync` -- camera frames on the log's clock, a pose per frame, TUM files,
  loop ground truth, the project's image-folder dataset;
* :mod:`~stablecues.mav.plots` -- the paper's flight figures (trajectory, altitude with flight-mode
  bands, latitude/longitude/altitude panels, roll/pitch/yaw).

pymavlink, pyulog and pymap3d are optional (``pip install "stablecues[mav]"``); they are imported
only when a function needs them.
"""

from .ekf import EkfConfig, EkfReport, SolutionComparison, compare_solutions, run_ekf
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
    "SolutionComparison",
    "TruncatedLogWarning",
    "compare_solutions",
    "detect_format",
    "mode_spans",
    "read_log",
    "run_ekf",
]
