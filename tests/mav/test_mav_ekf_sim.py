"""The EKF on a simulated flight with known truth (no shared data needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymap3d")

from scipy.spatial.transform import Rotation  # noqa: E402

from stablecues.errors import InputError  # noqa: E402
from stablecues.mav import (  # noqa: E402
    AttitudeSeries,
    BaroSeries,
    EkfConfig,
    FlightLog,
    GnssFixes,
    ImuSeries,
    MagSeries,
    NavSolution,
    compare_solutions,
    geo,
    run_ekf,
)
from stablecues.mav.ekf import imu_noise_from_log, mag_heading  # noqa: E402

ORIGIN = (47.0, 8.0, 400.0)
G = 9.80665
RADIUS, OMEGA = 12.0, 2 * np.pi / 25.0  # a 12 m circle in 25 s: 3 m/s


def _truth(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Position, velocity, acceleration (ENU) and body->NED Euler angles at times t."""
    ph = OMEGA * t
    pos = np.column_stack([RADIUS * np.cos(ph), RADIUS * np.sin(ph), 10 + 2 * np.sin(2 * np.pi * t / 20)])
    vel = np.column_stack(
        [
            -RADIUS * OMEGA * np.sin(ph),
            RADIUS * OMEGA * np.cos(ph),
            2 * (2 * np.pi / 20) * np.cos(2 * np.pi * t / 20),
        ]
    )
    acc = np.column_stack(
        [
            -RADIUS * OMEGA**2 * np.cos(ph),
            -RADIUS * OMEGA**2 * np.sin(ph),
            -2 * (2 * np.pi / 20) ** 2 * np.sin(2 * np.pi * t / 20),
        ]
    )
    heading_enu = ph + np.pi / 2  # facing along the velocity (counter-clockwise from east)
    yaw_ned = np.pi / 2 - heading_enu
    rpy = np.column_stack([0.08 * np.sin(0.7 * t), 0.05 * np.cos(0.4 * t), geo.wrap_angle(yaw_ned)])
    return pos, vel, acc, rpy


def _r_enu(rpy: np.ndarray) -> np.ndarray:
    q = geo.euler_to_quat(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    return geo.R_ENU_NED @ geo.quat_to_matrix(q)


def simulate(
    *, duration: float = 40.0, imu_hz: float = 50.0, lag: float = 0.0, seed: int = 0
) -> tuple[FlightLog, NavSolution]:
    rng = np.random.default_rng(seed)
    ti = np.arange(0.0, duration, 1.0 / imu_hz)
    _, _, acc, rpy = _truth(ti)
    r = _r_enu(rpy)
    f_body = np.einsum("nji,nj->ni", r, acc + np.array([0.0, 0.0, G]))
    h = 1e-4
    r_m = _r_enu(_truth(ti - h)[3])
    r_p = _r_enu(_truth(ti + h)[3])
    gyro = Rotation.from_matrix(np.einsum("nji,njk->nik", r_m, r_p)).as_rotvec() / (2 * h)
    accel_bias = np.array([0.08, -0.05, 0.1])
    gyro_bias = np.array([0.002, -0.001, 0.003])
    imu = ImuSeries(
        ti,
        gyro + gyro_bias + rng.normal(0, 0.003, gyro.shape),
        f_body + accel_bias + rng.normal(0, 0.05, f_body.shape),
    )

    tg = np.arange(0.0, duration, 0.2)
    pg, vg, _, _ = _truth(tg)
    pg_noisy = pg + rng.normal(0, [0.15, 0.15, 0.25], pg.shape)
    llh = geo.enu_to_geodetic(pg_noisy, ORIGIN)
    vel_ned = (vg + rng.normal(0, 0.05, vg.shape)) @ geo.R_ENU_NED.T
    n = len(tg)
    gnss = GnssFixes(
        t=tg + lag, lat=llh[:, 0], lon=llh[:, 1], alt=llh[:, 2], fix=np.full(n, 3, np.int16),
        n_sats=np.full(n, 12, np.int16), vel_ned=vel_ned, h_acc=np.full(n, 0.3), v_acc=np.full(n, 0.4),
        s_acc=np.full(n, 0.1),
    )  # fmt: skip
    tb = np.arange(0.0, duration, 0.1)
    baro = BaroSeries(tb, _truth(tb)[0][:, 2] + 3.0 + rng.normal(0, 0.3, len(tb)), np.full(len(tb), np.nan))
    tm = np.arange(0.0, duration, 0.1)
    earth_ned = np.array([0.2, 0.0, 0.45])  # gauss, no declination
    q_m = geo.euler_to_quat(*_truth(tm)[3].T)
    mag_b = np.einsum("nji,j->ni", geo.quat_to_matrix(q_m), earth_ned) + rng.normal(0, 0.003, (len(tm), 3))
    log = FlightLog(
        path=Path("simulated"), kind="sim", vehicle="sim", duration=duration, boot_time_offset=0.0,
        utc_offset=float("nan"), counts={}, params={}, gnss=gnss, baro=baro, imu=imu,
        mag=MagSeries(tm, mag_b), attitude=AttitudeSeries.empty(), onboard=None, ground_truth=None,
        mode_changes=(),
    )  # fmt: skip
    ptrue, vtrue, _, rpy_t = _truth(ti)
    q_true = geo.ned_to_enu_quat(geo.euler_to_quat(*rpy_t.T))
    truth = NavSolution("truth", ORIGIN, ti, ptrue, vtrue, q_true)
    return log, truth


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
    r = geo.quat_to_matrix(geo.euler_to_quat(np.array(0.0), np.array(np.radians(20)), np.array(0.0)))
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
