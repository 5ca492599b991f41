"""Where poses come from: the EKF, the autopilot's solution or the GNSS track (no shared data)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymap3d")

from flight_synth import make_log, track_log  # noqa: E402

from stablecues.errors import InputError  # noqa: E402
from stablecues.mav import FlightLog, read_log  # noqa: E402
from stablecues.mav.solutions import gnss_solution, log_solution, resample_solution  # noqa: E402


def test_log_solution_sources(tmp_path: Path) -> None:
    log: FlightLog = read_log(track_log(tmp_path))
    assert log_solution(log).name == "gnss"  # no IMU: auto falls back to the track
    with pytest.raises(InputError, match="onboard"):
        log_solution(log, "onboard")
    with pytest.raises(InputError, match="IMU"):
        log_solution(log, "ekf")
    with pytest.raises(InputError):
        resample_solution(gnss_solution(log), 0.0)
    every = resample_solution(gnss_solution(log), 2.0)
    assert len(every) == 120 and np.isfinite(every.position).all()  # 0 to 59.5 s


def test_gnss_solution_takes_the_autopilot_attitude(tmp_path: Path) -> None:
    pytest.importorskip("pymavlink")
    path = tmp_path / "synth.bin"
    path.write_bytes(make_log())
    log = read_log(path)
    g = gnss_solution(log)
    assert g.has_attitude  # ATT says level, facing north: FRD -> ENU is 180 deg about (1, 1, 0)
    np.testing.assert_allclose(
        np.abs(g.quaternion), [[np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0]] * len(g), atol=1e-6
    )
    np.testing.assert_allclose(g.rpy, 0.0, atol=1e-6)
    assert log_solution(log).name == "stablecues-ekf" and log_solution(log, "onboard").name == "XKF1[0]"
