"""Error-state EKF fusing IMU, GNSS, barometer and magnetometer into position, velocity, attitude.

The filter (Sola, "Quaternion kinematics for the error-state Kalman filter", 2017, sections 5-7)
keeps a nominal state

    p (3, ENU m), v (3, ENU m/s), q (body FRD -> ENU quaternion), b_a (3, m/s^2 accelerometer bias),
    b_g (3, rad/s gyro bias), b_baro (1, m barometer offset)

and a 16-dimensional error state ``[dp, dv, dtheta, db_a, db_g, db_baro]`` with the attitude
error ``dtheta`` in the body frame (``q_true = q * Exp(dtheta)``).

* **Prediction** at every IMU sample, at the IMU's own logged rate (zero-order hold between
  samples): ``v += (R (a_m - b_a) + g) dt``, ``q = q * Exp((w_m - b_g) dt)``.
* **GNSS position and velocity** (geodetic -> ENU about the first fix, through pymap3d) with the
  receiver's reported 1-sigma accuracies, floored by the noise settings. GNSS measurements are
  stamped ``lag`` seconds before their log time; the log is processed offline, so they are simply
  applied at that earlier time in time order (no delayed-state buffer is needed).
* **Barometric altitude** ``z = p_up + b_baro`` (the barometer's zero and slow drift are a state).
* **Magnetic heading**: tilt-compensated with the current roll/pitch, plus the declination.
* Every update passes an innovation gate (``gate_sigma`` standard deviations per component, as
  EKF3's ``*_I_GATE``); GNSS is re-anchored when it has been rejected for ``gnss_reset_s``.

Initialisation: at the first GNSS fix of at least ``min_fix`` (3 = 3D), position = that fix
(the ENU origin), velocity = its GNSS velocity, roll/pitch from the mean accelerometer and yaw
from the tilt-compensated magnetometer over ``init_window_s`` seconds around it.

Noise settings, and where each value comes from: see :class:`EkfConfig`. One configuration is used
for every flight; nothing is tuned to a particular log.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from . import geo
from .flightlog import FlightLog, NavSolution

logger = logging.getLogger(__name__)

GRAVITY = 9.80665  # m/s^2, standard gravity

_N = 16
_P, _V, _TH, _BA, _BG, _BB = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15), 15


@dataclass(frozen=True)
class EkfConfig:
    """Settings of :func:`run_ekf`. Defaults are ArduPilot EKF3's own defaults where EKF3 has the
    same quantity (its parameter named in brackets; these are also the values logged by the
    ArduCopter 4.3 flights in ``uob_ardupilot_copter_2023``), otherwise stated below.

    Attributes:
        accel_noise: accelerometer noise, m/s^2. None: measured from the log (see
            :func:`imu_noise_from_log`), never below EKF3's EK3_ACC_P_NSE = 0.35.
        gyro_noise: gyro noise, rad/s. None: measured from the log, never below EKF3's
            EK3_GYRO_P_NSE = 0.015.
        accel_bias_noise: accelerometer bias random walk, m/s^3 [EK3_ABIAS_P_NSE = 0.003].
        gyro_bias_noise: gyro bias random walk, rad/s^2 [EK3_GBIAS_P_NSE = 0.001].
        baro_bias_noise: barometer offset random walk, m/sqrt(s). EKF3 has no such state; 0.05 lets
            the offset move a few decimetres per minute (weather, temperature, prop wash).
        gnss_pos_noise: floor on the GNSS horizontal position sigma, m [EK3_POSNE_M_NSE = 0.5].
        gnss_alt_noise: floor on the GNSS height sigma, m; EKF3 uses 1.5 x EK3_POSNE_M_NSE = 0.75.
        gnss_vel_noise: floor on the GNSS horizontal velocity sigma, m/s [EK3_VELNE_M_NSE = 0.3].
        gnss_vvel_noise: floor on the GNSS vertical velocity sigma, m/s [EK3_VELD_M_NSE = 0.5].
        gnss_accel_scale: GNSS noise added per m/s^2 of horizontal acceleration (EKF3's
            gpsNEVelVarAccScale = 0.05: receivers lag and overshoot under acceleration).
        baro_noise: barometer sigma, m [EK3_ALT_M_NSE = 2.0].
        yaw_noise: magnetic heading sigma, rad [EK3_YAW_M_NSE = 0.5].
        gate_sigma: innovation gate in standard deviations [EK3_POS_I_GATE = 500 -> 5 sigma].
        gnss_lag_s: GNSS measurement delay, s. None: the log's GPS_DELAY_MS / GPS1_DELAY_MS /
            EKF2_GPS_DELAY when set (> 0), else 0.12 s, ArduPilot's default for u-blox M8/F9
            receivers (AP_GPS_UBLOX::get_lag).
        declination_deg: magnetic declination, degrees east. None: the log's COMPASS_DEC
            (radians), else 0.
        min_fix: smallest GNSS fix type used (3 = 3D).
        init_window_s: seconds of accelerometer / magnetometer averaged for the initial attitude.
        gnss_reset_s: re-anchor position/velocity on GNSS after it was rejected this long, s.
        max_imu_gap_s: a longer gap between IMU samples (logging paused, e.g. while disarmed) is
            not integrated: the state waits and position/velocity are re-anchored on the next
            GNSS fix.
        predict_rate_hz: IMUs logged faster than this are averaged in blocks of consecutive
            samples (a delta-velocity / delta-angle per block) so that prediction runs at about
            this rate; the noise is scaled so that the filter's uncertainty does not depend on it.
        max_aiding_rate_hz: barometer and compass samples closer than 1 / this are skipped (EKF3
            fuses them at 10-20 Hz; PX4 logs may hold them at the IMU rate).
        use_gnss_velocity, use_gnss_altitude, use_baro, use_mag: switch a measurement off.
    """

    accel_noise: float | None = None
    gyro_noise: float | None = None
    accel_bias_noise: float = 0.003
    gyro_bias_noise: float = 0.001
    baro_bias_noise: float = 0.05
    gnss_pos_noise: float = 0.5
    gnss_alt_noise: float = 0.75
    gnss_vel_noise: float = 0.3
    gnss_vvel_noise: float = 0.5
    gnss_accel_scale: float = 0.05
    baro_noise: float = 2.0
    yaw_noise: float = 0.5
    gate_sigma: float = 5.0
    gnss_lag_s: float | None = None
    declination_deg: float | None = None
    min_fix: int = 3
    init_window_s: float = 1.0
    gnss_reset_s: float = 5.0
    max_imu_gap_s: float = 1.0
    predict_rate_hz: float = 100.0
    max_aiding_rate_hz: float = 20.0
    use_gnss_velocity: bool = True
    use_gnss_altitude: bool = True
    use_baro: bool = True
    use_mag: bool = True


@dataclass(frozen=True)
class EkfReport:
    """Book-keeping of one :func:`run_ekf` run.

    Attributes:
        gnss_lag_s, declination_deg: the values used.
        accel_noise, gyro_noise: the IMU noise used (m/s^2, rad/s).
        accepted, rejected: updates applied / refused by the gate, per measurement kind.
        resets: GNSS re-anchorings.
        start_time: log time (s) of the initialisation.
    """

    gnss_lag_s: float
    declination_deg: float
    accel_noise: float
    gyro_noise: float
    accepted: dict[str, int]
    rejected: dict[str, int]
    resets: int
    start_time: float


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _rotvec_matrix(v: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrix of a rotation vector (3,)."""
    angle = float(np.linalg.norm(v))
    k = _skew(v)
    if angle < 1e-9:
        return np.eye(3) + k
    return np.eye(3) + np.sin(angle) / angle * k + (1.0 - np.cos(angle)) / angle**2 * (k @ k)


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def _qexp(v: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(v))
    if angle < 1e-12:
        return np.array([1.0, 0.5 * v[0], 0.5 * v[1], 0.5 * v[2]])
    s = np.sin(0.5 * angle) / angle
    return np.array([np.cos(0.5 * angle), s * v[0], s * v[1], s * v[2]])


def _ned_euler(r_enu: np.ndarray) -> tuple[float, float, float]:
    """Roll, pitch, yaw (NED, radians) of a body->ENU rotation matrix."""
    r = geo.R_ENU_NED.T @ r_enu  # body -> NED
    roll = float(np.arctan2(r[2, 1], r[2, 2]))
    pitch = float(-np.arcsin(np.clip(r[2, 0], -1.0, 1.0)))
    yaw = float(np.arctan2(r[1, 0], r[0, 0]))
    return roll, pitch, yaw


def _r_enu_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    q_ned = geo.euler_to_quat(np.array(roll), np.array(pitch), np.array(yaw))
    return geo.R_ENU_NED @ _quat_matrix(np.asarray(q_ned, dtype=np.float64).reshape(4))


def mag_heading(field_body: np.ndarray, roll: float, pitch: float, declination: float) -> float:
    """True heading (NED yaw, radians) from a body-frame magnetic field and the body's tilt.

    Args:
        field_body: (3,) magnetic field in the body frame (FRD), any unit.
        roll, pitch: radians.
        declination: magnetic declination, radians east.
    """
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    mx, my, mz = field_body
    # field rotated into the level (yaw-only) frame: Ry(pitch) Rx(roll) m
    hx = cp * mx + sp * sr * my + sp * cr * mz
    hy = cr * my - sr * mz
    return float(geo.wrap_angle(np.arctan2(-hy, hx) + declination))


EK3_ACC_P_NSE = 0.35  # m/s^2, ArduPilot EKF3 default accelerometer noise
EK3_GYRO_P_NSE = 0.015  # rad/s, ArduPilot EKF3 default gyro noise


def _thin(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices of samples at least 1 / rate_hz apart (the first one kept), for sorted ``t``."""
    if not rate_hz > 0 or len(t) == 0:
        return np.arange(len(t))
    slot = np.floor((t - t[0]) * rate_hz).astype(np.int64)
    return np.flatnonzero(np.r_[True, np.diff(slot) > 0])


def _block_means(
    t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, dt_raw: float, rate_hz: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average consecutive IMU samples in blocks of ``round(1 / (rate_hz dt_raw))``; each block is
    stamped with its first sample's time (the zero-order hold then covers the block's span)."""
    if not rate_hz > 0 or not dt_raw > 0:
        return t, gyro, accel
    m = int(round(1.0 / (rate_hz * dt_raw)))
    if m <= 1:
        return t, gyro, accel
    starts = np.arange(0, len(t), m)
    counts = np.diff(np.append(starts, len(t)))[:, None]
    return (
        t[starts],
        np.add.reduceat(gyro, starts, axis=0) / counts,
        np.add.reduceat(accel, starts, axis=0) / counts,
    )


def imu_noise_from_log(t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> tuple[float, float]:
    """Accelerometer and gyro noise of logged IMU samples, measured from the samples themselves.

    Autopilots log IMU snapshots at a fraction of the rate their own filters integrate
    (ArduCopter: 25 Hz per IMU in the uob logs, 50 Hz in 2014, against 400 Hz or more inside
    EKF3), so between two logged samples the airframe's vibration and the unlogged motion act as
    noise on a zero-order-hold prediction. Its size is the standard deviation of the
    sample-to-sample differences divided by sqrt(2) (white noise doubles its variance in a
    difference), averaged in variance over the three axes. Used when :class:`EkfConfig` leaves
    the noise at None; the result is never below EKF3's defaults.

    Args:
        t: (N,) sample times, s (used to drop differences across gaps longer than 0.5 s).
        gyro: (N, 3) rad/s.
        accel: (N, 3) m/s^2.

    Returns:
        (accelerometer sigma m/s^2, gyro sigma rad/s).
    """
    if len(t) < 3:
        return EK3_ACC_P_NSE, EK3_GYRO_P_NSE
    ok = np.diff(t) < 0.5
    da = np.diff(accel, axis=0)[ok]
    dg = np.diff(gyro, axis=0)[ok]
    if len(da) < 2:
        return EK3_ACC_P_NSE, EK3_GYRO_P_NSE
    sa = float(np.sqrt(np.mean(np.var(da, axis=0)) / 2.0))
    sg = float(np.sqrt(np.mean(np.var(dg, axis=0)) / 2.0))
    return max(sa, EK3_ACC_P_NSE), max(sg, EK3_GYRO_P_NSE)


def _gnss_lag(log: FlightLog, config: EkfConfig) -> float:
    if config.gnss_lag_s is not None:
        return float(config.gnss_lag_s)
    for key in ("GPS1_DELAY_MS", "GPS_DELAY_MS", "EKF2_GPS_DELAY"):
        value = log.params.get(key)
        if value is not None and value > 0:
            return float(value) * 1e-3
    return 0.12


def _declination(log: FlightLog, config: EkfConfig) -> float:
    if config.declination_deg is not None:
        return float(np.radians(config.declination_deg))
    value = log.params.get("COMPASS_DEC")
    return float(value) if value is not None and np.isfinite(value) else 0.0


def run_ekf(log: FlightLog, config: EkfConfig | None = None) -> tuple[NavSolution, EkfReport]:
    """Fuse a flight log's IMU, GNSS, barometer and magnetometer into a navigation solution.

    Args:
        log: a flight log with IMU and GNSS (barometer and magnetometer are optional).
        config: filter settings; :class:`EkfConfig` defaults when None.

    Returns:
        The solution at every IMU sample from the initialisation on (ENU about the first
        usable GNSS fix; ``name`` "stablecues-ekf"), and an :class:`EkfReport`.

    Raises:
        InputError: the log has no IMU samples or no GNSS fix of at least ``config.min_fix``.
    """
    cfg = config or EkfConfig()
    imu = log.imu
    good = np.flatnonzero(
        (log.gnss.fix >= cfg.min_fix)
        & np.isfinite(log.gnss.lat)
        & np.isfinite(log.gnss.lon)
        & np.isfinite(log.gnss.alt)
    )
    if len(imu) < 2:
        raise InputError(f"{log.path}: the EKF needs IMU samples, the log has {len(imu)}")
    if len(good) == 0:
        raise InputError(f"{log.path}: the EKF needs a GNSS fix of type >= {cfg.min_fix}, the log has none")
    gnss = log.gnss.subset(good)
    lag = _gnss_lag(log, cfg)
    decl = _declination(log, cfg)
    origin = (float(gnss.lat[0]), float(gnss.lon[0]), float(gnss.alt[0]))
    g_pos = geo.geodetic_to_enu(gnss.lat, gnss.lon, gnss.alt, origin)
    g_vel = gnss.vel_ned @ geo.R_ENU_NED.T  # NaN stays NaN
    g_t = gnss.t - lag

    imu_order = np.argsort(imu.t, kind="stable")
    i_t, i_gyro, i_acc = imu.t[imu_order], imu.gyro[imu_order], imu.accel[imu_order]
    # noise of the raw samples, then (for fast IMUs) block means at about predict_rate_hz
    acc_sigma, gyro_sigma = imu_noise_from_log(i_t, i_gyro, i_acc)
    dt_raw = float(np.median(np.diff(i_t)))
    i_t, i_gyro, i_acc = _block_means(i_t, i_gyro, i_acc, dt_raw, cfg.predict_rate_hz)
    t_start = max(float(g_t[0]), float(i_t[0]))

    mag = log.mag

    def level_attitude(w0: float, w1: float) -> tuple[np.ndarray, float]:
        """Attitude from the mean accelerometer (roll, pitch) and magnetometer (yaw) in [w0, w1];
        returns the quaternion and the yaw sigma (pi when no heading source)."""
        sel = (i_t >= w0) & (i_t <= w1)
        acc = (
            i_acc[sel].mean(axis=0)
            if np.any(sel)
            else i_acc[int(np.searchsorted(i_t, w0).clip(0, len(i_t) - 1))]
        )
        roll = float(np.arctan2(-acc[1], -acc[2]))
        pitch = float(np.arctan2(acc[0], np.hypot(acc[1], acc[2])))
        yaw, yaw_sigma = 0.0, float(np.pi)
        if len(mag) and cfg.use_mag:
            msel = (mag.t >= w0 - 1.0) & (mag.t <= w1 + 1.0)
            msel &= np.linalg.norm(mag.field, axis=1) > 0  # an all-zero field: no compass fitted
            if np.any(msel):
                yaw, yaw_sigma = mag_heading(mag.field[msel].mean(axis=0), roll, pitch, decl), 0.3
        if yaw_sigma >= np.pi:
            kk = min(int(np.searchsorted(g_t, w0)), len(g_t) - 1)
            vn = gnss.vel_ned[kk]
            if np.all(np.isfinite(vn[:2])) and np.hypot(vn[0], vn[1]) > 3.0:
                yaw, yaw_sigma = float(np.arctan2(vn[1], vn[0])), 0.3
        return geo.matrix_to_quat(_r_enu_from_euler(roll, pitch, yaw)), yaw_sigma

    q, yaw_sigma = level_attitude(t_start - 0.5 * cfg.init_window_s, t_start + 0.5 * cfg.init_window_s)
    k0 = min(int(np.searchsorted(g_t, t_start)), len(g_t) - 1)

    p = g_pos[k0].copy()
    v = np.nan_to_num(g_vel[k0].copy())
    ba = np.zeros(3)
    bg = np.zeros(3)
    bb = 0.0
    baro = log.baro if cfg.use_baro else None
    if baro is not None and len(baro):
        bb = float(np.interp(t_start, baro.t, baro.alt)) - p[2]

    P = np.zeros((_N, _N))
    h0 = gnss.h_acc[k0] if np.isfinite(gnss.h_acc[k0]) else 0.0
    v0 = gnss.v_acc[k0] if np.isfinite(gnss.v_acc[k0]) else 0.0
    P[0, 0] = P[1, 1] = max(h0, cfg.gnss_pos_noise) ** 2
    P[2, 2] = max(v0, cfg.gnss_alt_noise) ** 2
    P[3:6, 3:6] = np.eye(3) * 0.5**2
    P[6, 6] = P[7, 7] = 0.05**2
    P[8, 8] = yaw_sigma**2  # body z ~ down, so this mostly covers heading
    P[9:12, 9:12] = np.eye(3) * 0.2**2
    P[12:15, 12:15] = np.eye(3) * 0.02**2
    P[15, 15] = 0.5**2

    # --- events: IMU samples (kind 0), GNSS (1), baro (2), mag (3), in time order
    ev_t = [i_t, g_t]
    ev_k = [np.zeros(len(i_t), np.int8), np.ones(len(g_t), np.int8)]
    ev_i = [np.arange(len(i_t)), np.arange(len(g_t))]
    if baro is not None and len(baro):
        keep = _thin(baro.t, cfg.max_aiding_rate_hz)
        ev_t.append(baro.t[keep])
        ev_k.append(np.full(len(keep), 2, np.int8))
        ev_i.append(keep)
    if cfg.use_mag and len(mag):
        keep = _thin(mag.t, cfg.max_aiding_rate_hz)
        ev_t.append(mag.t[keep])
        ev_k.append(np.full(len(keep), 3, np.int8))
        ev_i.append(keep)
    all_t = np.concatenate(ev_t)
    all_k = np.concatenate(ev_k)
    all_i = np.concatenate(ev_i)
    order = np.lexsort((all_k, all_t))
    all_t, all_k, all_i = all_t[order], all_k[order], all_i[order]
    begin = int(np.searchsorted(all_t, t_start, side="left"))

    accepted = {"gnss_pos": 0, "gnss_vel": 0, "baro": 0, "mag": 0}
    rejected = dict.fromkeys(accepted, 0)
    resets = 0
    gate2 = cfg.gate_sigma**2
    g_vec = np.array([0.0, 0.0, -GRAVITY])
    eye16 = np.eye(_N)
    q_acc = (cfg.accel_noise if cfg.accel_noise is not None else acc_sigma) ** 2
    q_gyro = (cfg.gyro_noise if cfg.gyro_noise is not None else gyro_sigma) ** 2
    q_ab = cfg.accel_bias_noise**2
    q_gb = cfg.gyro_bias_noise**2
    q_bb = cfg.baro_bias_noise**2

    t_now = t_start
    t_imu = t_start
    j_imu = max(int(np.searchsorted(i_t, t_start, side="right")) - 1, 0)
    a_m, w_m = i_acc[j_imu], i_gyro[j_imu]
    last_gnss_ok = t_start
    acc_h = 0.0  # horizontal acceleration magnitude, for the GNSS noise scaling

    out_t: list[float] = []
    out_p: list[np.ndarray] = []
    out_v: list[np.ndarray] = []
    out_q: list[np.ndarray] = []
    out_s: list[np.ndarray] = []

    def predict(dt: float) -> None:
        nonlocal p, v, q, P, acc_h
        if dt <= 0:
            return
        r = _quat_matrix(q)
        a = a_m - ba
        w = w_m - bg
        acc_w = r @ a + g_vec
        acc_h = float(np.hypot(acc_w[0], acc_w[1]))
        p = p + v * dt + 0.5 * acc_w * dt * dt
        v = v + acc_w * dt
        q = _qmul(q, _qexp(w * dt))
        q = q / np.linalg.norm(q)
        F = eye16.copy()
        F[0:3, 3:6] = np.eye(3) * dt
        F[3:6, 6:9] = -(r @ _skew(a)) * dt
        F[3:6, 9:12] = -r * dt
        F[6:9, 6:9] = _rotvec_matrix(w * dt).T
        F[6:9, 12:15] = -np.eye(3) * dt
        P = F @ P @ F.T
        d2 = dt * dt
        dn = dt_raw * dt  # white noise of per-sample sigma at the raw rate: variance sigma^2 dt_raw dt
        idx = np.arange(3)
        P[3 + idx, 3 + idx] += q_acc * dn
        P[6 + idx, 6 + idx] += q_gyro * dn
        P[9 + idx, 9 + idx] += q_ab * d2
        P[12 + idx, 12 + idx] += q_gb * d2
        P[15, 15] += q_bb * dt

    def update(y: np.ndarray, H: np.ndarray, R: np.ndarray, kind: str) -> bool:
        nonlocal p, v, q, ba, bg, bb, P
        PHt = P @ H.T
        S = H @ PHt + R
        if np.any(y * y > gate2 * np.diag(S)):
            rejected[kind] += 1
            return False
        K = np.linalg.solve(S, PHt.T).T
        dx = K @ y
        IKH = eye16 - K @ H
        P = IKH @ P @ IKH.T + K @ R @ K.T
        P = 0.5 * (P + P.T)
        p = p + dx[_P]
        v = v + dx[_V]
        q = _qmul(q, _qexp(dx[_TH]))
        q = q / np.linalg.norm(q)
        ba = ba + dx[_BA]
        bg = bg + dx[_BG]
        bb = bb + float(dx[_BB])
        accepted[kind] += 1
        return True

    need_anchor = False
    for e in range(begin, len(all_t)):
        te = float(all_t[e])
        kind = int(all_k[e])
        i = int(all_i[e])
        if te - t_imu > cfg.max_imu_gap_s:
            # the IMU has been silent (a logging gap, e.g. disarmed, or an IMU dropout while the
            # other sensors go on): never integrate a held IMU sample across it. When the IMU is
            # back the vehicle may have been moved or set upright, so attitude restarts from
            # accelerometer and compass, and position re-anchors on the next GNSS fix.
            if kind == 0:
                need_anchor = True
                q, yaw_sigma = level_attitude(te, te + cfg.init_window_s)
                P[6:9, :] = 0.0
                P[:, 6:9] = 0.0
                P[6, 6] = P[7, 7] = 0.05**2
                P[8, 8] = yaw_sigma**2
        else:
            predict(te - t_now)
        t_now = te
        if kind == 0:
            t_imu = te
        if need_anchor and kind == 1:
            p = g_pos[i].copy()
            v = np.nan_to_num(g_vel[i].copy())
            P[0:6, :] = 0.0
            P[:, 0:6] = 0.0
            P[0, 0] = P[1, 1] = cfg.gnss_pos_noise**2
            P[2, 2] = cfg.gnss_alt_noise**2
            P[3:6, 3:6] = np.eye(3) * 0.5**2
            resets += 1
            last_gnss_ok = te
            need_anchor = False
            continue
        if kind == 0:
            a_m, w_m = i_acc[i], i_gyro[i]
            out_t.append(te)
            out_p.append(p)
            out_v.append(v)
            out_q.append(q)
            out_s.append(np.sqrt(np.diag(P)[0:3]))
        elif kind == 1:
            extra = (cfg.gnss_accel_scale * acc_h) ** 2
            sh = max(gnss.h_acc[i] if np.isfinite(gnss.h_acc[i]) else 0.0, cfg.gnss_pos_noise)
            sv = max(gnss.v_acc[i] if np.isfinite(gnss.v_acc[i]) else 0.0, cfg.gnss_alt_noise)
            rows = [0, 1, 2] if cfg.use_gnss_altitude else [0, 1]
            H = np.zeros((len(rows), _N))
            for r_i, c in enumerate(rows):
                H[r_i, c] = 1.0
            R = np.diag([sh**2 + extra, sh**2 + extra, sv**2 + extra][: len(rows)])
            y = g_pos[i, rows] - p[rows]
            pos_ok = update(y, H, R, "gnss_pos")
            if cfg.use_gnss_velocity:
                gv = g_vel[i]
                vrows = [c for c in range(3) if np.isfinite(gv[c])]
                if vrows:
                    ss = gnss.s_acc[i] if np.isfinite(gnss.s_acc[i]) else 0.0
                    Hv = np.zeros((len(vrows), _N))
                    sig = []
                    for r_i, c in enumerate(vrows):
                        Hv[r_i, 3 + c] = 1.0
                        floor = cfg.gnss_vvel_noise if c == 2 else cfg.gnss_vel_noise
                        sig.append(max(ss, floor) ** 2 + extra)
                    update(gv[vrows] - v[vrows], Hv, np.diag(sig), "gnss_vel")
            if pos_ok:
                last_gnss_ok = te
            elif te - last_gnss_ok > cfg.gnss_reset_s:
                # re-anchor on GNSS: position (and velocity when reported) jump to the fix
                p = g_pos[i].copy()
                if np.all(np.isfinite(g_vel[i])):
                    v = g_vel[i].copy()
                P[0:6, :] = 0.0
                P[:, 0:6] = 0.0
                P[0, 0] = P[1, 1] = sh**2
                P[2, 2] = sv**2
                P[3:6, 3:6] = np.eye(3) * 0.5**2
                resets += 1
                last_gnss_ok = te
        elif kind == 2 and baro is not None:
            H = np.zeros((1, _N))
            H[0, 2] = 1.0
            H[0, _BB] = 1.0
            y = np.array([baro.alt[i] - (p[2] + bb)])
            if np.isfinite(y[0]):
                update(y, H, np.array([[cfg.baro_noise**2]]), "baro")
        elif kind == 3:
            field = mag.field[i]
            if not np.all(np.isfinite(field)) or not np.any(field):
                continue
            r = _quat_matrix(q)
            roll, pitch, yaw = _ned_euler(r)
            if abs(np.cos(pitch)) < 0.2:
                continue
            z = mag_heading(field, roll, pitch, decl)
            H = np.zeros((1, _N))
            H[0, 7] = np.sin(roll) / np.cos(pitch)
            H[0, 8] = np.cos(roll) / np.cos(pitch)
            y = np.array([float(geo.wrap_angle(z - yaw))])
            update(y, H, np.array([[cfg.yaw_noise**2]]), "mag")

    t_arr = np.array(out_t, dtype=np.float64)
    quat = np.array(out_q, dtype=np.float64).reshape(-1, 4)
    solution = NavSolution(
        name="stablecues-ekf",
        origin=origin,
        t=t_arr,
        position=np.array(out_p, dtype=np.float64).reshape(-1, 3),
        velocity=np.array(out_v, dtype=np.float64).reshape(-1, 3),
        quaternion=geo.quat_normalize(quat) if len(quat) else quat,
        position_std=np.array(out_s, dtype=np.float64).reshape(-1, 3),
    )
    report = EkfReport(
        gnss_lag_s=lag,
        declination_deg=float(np.degrees(decl)),
        accel_noise=float(np.sqrt(q_acc)),
        gyro_noise=float(np.sqrt(q_gyro)),
        accepted=accepted,
        rejected=rejected,
        resets=resets,
        start_time=t_start,
    )
    logger.info(
        "EKF on %s: %d IMU steps, accepted %s, rejected %s", log.path.name, len(t_arr), accepted, rejected
    )
    return solution, report


@dataclass(frozen=True)
class SolutionComparison:
    """How far one navigation solution is from a reference.

    Attributes:
        estimate, reference: the two solutions' names.
        n: number of reference samples compared.
        h_rmse_m, v_rmse_m: horizontal / vertical RMS position difference in metres, after
            removing ``offset_enu`` when the comparison removes a constant offset.
        offset_enu: (3,) mean difference estimate - reference, metres (east, north, up).
        roll_rmse_deg, pitch_rmse_deg, yaw_rmse_deg: attitude RMS differences (NaN when either
            solution has no attitude).
    """

    estimate: str
    reference: str
    n: int
    h_rmse_m: float
    v_rmse_m: float
    offset_enu: tuple[float, float, float]
    roll_rmse_deg: float
    pitch_rmse_deg: float
    yaw_rmse_deg: float


def compare_solutions(
    estimate: NavSolution,
    reference: NavSolution,
    *,
    remove_offset: bool = True,
    t_min: float | None = None,
) -> SolutionComparison:
    """Position and attitude differences of ``estimate`` against ``reference`` at the reference's
    sample times inside the estimate's span (and after ``t_min`` when given).

    The reference is first expressed about the estimate's ENU origin, so solutions with
    different origins compare exactly. With ``remove_offset`` the mean position difference is
    removed first (different origins / antenna positions / datum).

    Raises:
        InputError: the two solutions do not overlap in time.
    """
    ref = reference.reframed(estimate.origin)
    keep = np.isfinite(ref.position).all(axis=1)
    if len(estimate):
        keep &= (ref.t >= estimate.t[0]) & (ref.t <= estimate.t[-1])
    if t_min is not None:
        keep &= ref.t >= t_min
    if not np.any(keep) or len(estimate) == 0:
        raise InputError(f"{estimate.name} and {reference.name} do not overlap in time")
    est = estimate.interpolate(ref.t[keep])
    # the estimate may have gaps inside the reference's span (interpolation gives NaN there)
    fin = np.isfinite(est.position).all(axis=1)
    if not fin.any():
        raise InputError(f"{estimate.name} and {reference.name} have no common valid samples")
    if not fin.all():
        keep[np.flatnonzero(keep)[~fin]] = False
        est = estimate.interpolate(ref.t[keep])
    diff = est.position - ref.position[keep]
    offset = diff.mean(axis=0) if remove_offset else np.zeros(3)
    d = diff - offset
    h = float(np.sqrt(np.mean(d[:, 0] ** 2 + d[:, 1] ** 2)))
    vv = float(np.sqrt(np.mean(d[:, 2] ** 2)))
    att = [float("nan")] * 3
    if estimate.has_attitude and np.all(np.isfinite(ref.quaternion[keep])):
        e_rpy = est.rpy
        r_rpy = geo.quat_to_euler(geo.enu_to_ned_quat(ref.quaternion[keep]))
        dd = geo.wrap_angle(e_rpy - r_rpy)
        att = [float(np.degrees(np.sqrt(np.mean(dd[:, k] ** 2)))) for k in range(3)]
    return SolutionComparison(
        estimate=estimate.name,
        reference=reference.name,
        n=int(keep.sum()),
        h_rmse_m=h,
        v_rmse_m=vv,
        offset_enu=(float(offset[0]), float(offset[1]), float(offset[2])),
        roll_rmse_deg=att[0],
        pitch_rmse_deg=att[1],
        yaw_rmse_deg=att[2],
    )
