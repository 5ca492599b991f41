"""The EKF: a simulated flight with known truth, its steps one by one, and the real uob flights
against ArduPilot's EKF3 (those skip when ../shared/data is absent)."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path

pytest.importorskip("pymap3d")

from flight_synth import simulate  # noqa: E402

from stablecues.errors import InputError  # noqa: E402
from stablecues.geometry.rotations import euler_zyx_to_quat, quat_to_matrix  # noqa: E402
from stablecues.mav import (  # noqa: E402
    EkfConfig,
    FlightLog,
    ImuSeries,
    compare_solutions,
    read_log,
    run_ekf,
)
from stablecues.mav.ekf import Event, NavigationFilter, imu_noise_from_log, mag_heading  # noqa: E402


def test_ekf_recovers_a_simulated_flight() -> None:
    log, truth = simulate()
    solution, report = run_ekf(log, EkfConfig(gnss_lag_s=0.0, declination_deg=0.0))
    assert solution.origin == pytest.approx(
        tuple(np.array([log.gnss.lat[0], log.gnss.lon[0], log.gnss.alt[0]])), abs=1e-12
    )
    cmp = compare_solutions(solution, truth, remove_offset=False, t_min=5.0)
    assert cmp.h_rmse_m < 0.2
    assert cmp.v_rmse_m < 0.2
    assert cmp.roll_rmse_deg < 1.0 and cmp.pitch_rmse_deg < 1.0
    assert cmp.yaw_rmse_deg < 3.0
    assert report.rejected == {"gnss_pos": 0, "gnss_vel": 0, "baro": 0, "mag": 0}
    # velocity too
    at = solution.interpolate(truth.t[truth.t > 5])
    assert np.sqrt(np.mean(np.sum((at.velocity - truth.velocity[truth.t > 5]) ** 2, axis=1))) < 0.15


def test_ekf_compensates_a_known_gnss_lag() -> None:
    log, truth = simulate(lag=0.3, seed=1)
    right, _ = run_ekf(log, EkfConfig(gnss_lag_s=0.3, declination_deg=0.0))
    wrong, _ = run_ekf(log, EkfConfig(gnss_lag_s=0.0, declination_deg=0.0))
    err_right = compare_solutions(right, truth, remove_offset=False, t_min=5.0).h_rmse_m
    err_wrong = compare_solutions(wrong, truth, remove_offset=False, t_min=5.0).h_rmse_m
    assert err_right < 0.2
    assert err_wrong > 2 * err_right  # 3 m/s x 0.3 s is a metre of along-track error


def test_ekf_inputs_are_checked() -> None:
    log, _ = simulate(duration=5.0)
    no_imu = FlightLog(**{**log.__dict__, "imu": ImuSeries.empty()})
    with pytest.raises(InputError, match="IMU"):
        run_ekf(no_imu)
    no_fix = FlightLog(**{**log.__dict__, "gnss": log.gnss.subset(np.zeros(len(log.gnss), bool))})
    with pytest.raises(InputError, match="GNSS"):
        run_ekf(no_fix)


def test_mag_heading_hand_cases() -> None:
    # level, nose north: field (north, 0, down) -> heading 0; nose east: the field is on the body's left
    assert mag_heading(np.array([0.2, 0.0, 0.4]), 0.0, 0.0, 0.0) == pytest.approx(0.0)
    assert mag_heading(np.array([0.0, -0.2, 0.4]), 0.0, 0.0, 0.0) == pytest.approx(np.pi / 2)
    assert mag_heading(np.array([0.2, 0.0, 0.4]), 0.0, 0.0, np.radians(5)) == pytest.approx(np.radians(5))
    # tilt compensation: pitched 20 degrees nose up, nose north
    r = quat_to_matrix(euler_zyx_to_quat(0.0, np.radians(20), 0.0))
    body = r.T @ np.array([0.2, 0.0, 0.4])
    assert mag_heading(body, 0.0, np.radians(20), 0.0) == pytest.approx(0.0, abs=1e-9)


def test_imu_noise_from_log_measures_white_noise() -> None:
    rng = np.random.default_rng(3)
    t = np.arange(0, 100, 0.01)
    acc = rng.normal(0, 1.2, (len(t), 3)) + [0, 0, -9.8]
    gyro = rng.normal(0, 0.05, (len(t), 3))
    sa, sg = imu_noise_from_log(t, gyro, acc)
    assert sa == pytest.approx(1.2, rel=0.05) and sg == pytest.approx(0.05, rel=0.05)
    # quiet sensors are floored at EKF3's defaults
    assert imu_noise_from_log(t, gyro * 0, acc * 0) == (0.35, 0.015)


def test_run_ekf_is_the_filter_run_over_the_log() -> None:
    log, _ = simulate(duration=8.0, seed=2)
    cfg = EkfConfig(gnss_lag_s=0.0, declination_deg=0.0)
    a, rep_a = run_ekf(log, cfg)
    f = NavigationFilter(log, cfg)
    b, rep_b = f.run()
    for name in ("t", "position", "velocity", "quaternion", "position_std"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert rep_a == rep_b and rep_a.accepted["gnss_pos"] == 40 and rep_a.start_time == 0.0
    # quaternions are body -> ENU (x, y, z, w), unit, w >= 0
    np.testing.assert_allclose(np.linalg.norm(a.quaternion, axis=1), 1.0, atol=1e-12)
    assert np.all(a.quaternion[:, 3] >= 0)


def test_events_run_in_kind_order_at_equal_times() -> None:
    assert [e.name for e in sorted(Event)] == ["IMU", "GNSS", "BARO", "MAG"]
    log, _ = simulate(duration=3.0)
    t, kinds, index = NavigationFilter(log).inputs.timeline(EkfConfig())
    assert np.all(np.diff(t) >= 0)
    same = np.flatnonzero(np.diff(t) == 0)
    assert np.all(kinds[same] <= kinds[same + 1])
    counts = {Event(k).name: int(np.sum(kinds == k)) for k in np.unique(kinds)}
    # IMU 50 Hz, GNSS 5 Hz, barometer and compass 10 Hz (under max_aiding_rate_hz = 20)
    assert counts == {"IMU": 150, "GNSS": 15, "BARO": 30, "MAG": 30}
    assert index[kinds == Event.GNSS].tolist() == list(range(15))


def test_filter_steps_predict_update_reanchor() -> None:
    log, _ = simulate(duration=6.0, seed=4)
    f = NavigationFilter(log, EkfConfig(gnss_lag_s=0.0, declination_deg=0.0))
    p0, v0, P0 = f.p, f.v, f.P.copy()
    f.predict(0.0)  # no time: nothing moves
    assert f.p is p0 and np.array_equal(f.P, P0)
    f.predict(0.1)
    np.testing.assert_allclose(f.p, p0 + v0 * 0.1, atol=0.02)  # about the GNSS velocity
    assert f.p is not p0 and np.all(np.diag(f.P) >= np.diag(P0) - 1e-12)  # uncertainty grows
    # a GNSS fix right here is accepted; one 50 m away is gated out
    f.update_gnss(1, 0.2)
    assert f.accepted["gnss_pos"] == 1 and f.rejected["gnss_pos"] == 0
    pos = f.inputs.gnss_pos
    f.inputs.gnss_pos[2] = pos[2] + [50.0, 0.0, 0.0]
    f.update_gnss(2, 0.4)
    assert f.rejected["gnss_pos"] == 1 and f.resets == 0
    # rejected for longer than gnss_reset_s: re-anchored on the fix, position covariance reset
    f.update_gnss(2, 0.4 + f.config.gnss_reset_s + 0.1)
    assert f.resets == 1
    np.testing.assert_array_equal(f.p, pos[2])
    assert f.P[0, 0] == pytest.approx(max(0.3, f.config.gnss_pos_noise) ** 2)
    assert np.all(f.P[0:6, 6:] == 0.0) and np.all(f.P[6:, 0:6] == 0.0)
    f.reanchor(7.0, np.array([1.0, 2.0, 3.0]), None, 2.0, 4.0)
    assert f.resets == 2 and f.last_gnss_ok == 7.0 and f.P[2, 2] == 16.0
    np.testing.assert_array_equal(f.p, [1.0, 2.0, 3.0])
    # barometer and compass updates move the state and count
    f.update_baro(10)
    f.update_mag(10)
    assert f.accepted["baro"] == 1 and f.accepted["mag"] == 1


def test_imu_gap_restarts_attitude_and_reanchors() -> None:
    log, truth = simulate(duration=30.0, seed=3)
    imu = log.imu
    keep = (imu.t < 12.0) | (imu.t > 15.0)  # a 3 s IMU dropout while GNSS goes on
    gap_log = dataclasses.replace(log, imu=ImuSeries(imu.t[keep], imu.gyro[keep], imu.accel[keep]))
    solution, report = run_ekf(gap_log, EkfConfig(gnss_lag_s=0.0, declination_deg=0.0))
    assert report.resets == 1  # re-anchored once, on the first fix after the IMU came back
    assert not np.any((solution.t > 12.0) & (solution.t < 15.0))  # nothing integrated in the gap
    after = compare_solutions(solution, truth, remove_offset=False, t_min=18.0)
    assert after.h_rmse_m < 0.3 and after.yaw_rmse_deg < 5.0


def test_long_gnss_outage_of_bad_fixes_resets() -> None:
    log, truth = simulate(duration=40.0, seed=5)
    g = log.gnss
    bad = (g.t > 20.0) & (g.t < 30.0)
    lat = np.where(bad, g.lat + 5e-4, g.lat)  # ~55 m north for 10 s
    jump_log = dataclasses.replace(log, gnss=dataclasses.replace(g, lat=lat))
    solution, report = run_ekf(jump_log, EkfConfig(gnss_lag_s=0.0, declination_deg=0.0))
    assert report.rejected["gnss_pos"] > 20 and report.resets >= 1
    ok = compare_solutions(solution, truth, remove_offset=False, t_min=35.0)
    assert ok.h_rmse_m < 0.5  # back on the good fixes after the jump


def _read(path: Path) -> FlightLog:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_log(path)


@pytest.mark.parametrize("name", ["2023-07-06_10-12-18.bin", "2023-07-06_10-18-44.bin"])
def test_ekf_matches_onboard_ekf3_on_uob_flights(name: str) -> None:
    pytest.importorskip("pymavlink")
    log = _read(shared_path("mav", "uob_ardupilot_copter_2023", name))
    solution, report = run_ekf(log)  # one configuration, the defaults, for both flights
    assert log.onboard is not None
    cmp = compare_solutions(solution, log.onboard)
    # acceptance: within 0.5 m horizontal and 0.3 m vertical RMS after removing a constant offset
    assert cmp.h_rmse_m < 0.5
    assert cmp.v_rmse_m < 0.3
    assert cmp.n > 900  # the whole flight is compared (XKF1 at 10 Hz)
    assert np.linalg.norm(cmp.offset_enu) < 0.5  # same origin conventions: no big hidden offset
    assert cmp.roll_rmse_deg < 5 and cmp.pitch_rmse_deg < 5
    assert np.isfinite(solution.position).all() and np.isfinite(solution.quaternion).all()
    assert report.gnss_lag_s == pytest.approx(0.12)  # GPS_DELAY_MS = 0 in these logs: driver default
    assert report.declination_deg == pytest.approx(np.degrees(log.params["COMPASS_DEC"]))
    assert sum(report.rejected.values()) == 0 and report.resets == 0
