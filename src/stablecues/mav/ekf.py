"""Error-state EKF fusing IMU, GNSS, barometer and magnetometer into position, velocity, attitude.

The filter (Sola, "Quaternion kinematics for the error-state Kalman filter", 2017, sections 5-7)
keeps a nominal state

    p (3, ENU m), v (3, ENU m/s), q (body FRD -> ENU quaternion, (x, y, z, w)),
    b_a (3, m/s^2 accelerometer bias), b_g (3, rad/s gyro bias), b_baro (1, m barometer offset)

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
* **IMU gaps** longer than ``max_imu_gap_s`` are not integrated: attitude restarts from
  accelerometer and compass, and position re-anchors on the next GNSS fix.

:class:`NavigationFilter` holds the state and has one method per step (predict, an update per
sensor, re-anchor, attitude restart); it walks the log's events (:class:`Event`: IMU, GNSS,
barometer, compass) in time order. :func:`run_ekf` runs it over a whole log.

Initialisation: at the first GNSS fix of at least ``min_fix`` (3 = 3D), position = that fix
(the ENU origin), velocity = its GNSS velocity, roll/pitch from the mean accelerometer and yaw
from the tilt-compensated magnetometer over ``init_window_s`` seconds around it.

Noise settings, and where each value comes from: see :class:`EkfConfig`. One configuration is used
for every flight; nothing is tuned to a particular log.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from ..errors import InputError
from ..geometry.rotations import (
    euler_zyx_to_quat,
    quat_from_rotvec,
    quat_multiply,
    quat_normalize,
    quat_to_euler_zyx,
    quat_to_matrix,
)
from . import geo
from .flightlog import BaroSeries, FlightLog, GnssFixes, MagSeries, NavSolution

logger = logging.getLogger(__name__)

GRAVITY = 9.80665  # m/s^2, standard gravity
_G_VEC = np.array([0.0, 0.0, -GRAVITY])

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


def _ned_euler(r_enu: np.ndarray) -> tuple[float, float, float]:
    """Roll, pitch, yaw (NED, radians) of a body->ENU rotation matrix."""
    r = geo.R_ENU_NED.T @ r_enu  # body -> NED
    roll = float(np.arctan2(r[2, 1], r[2, 2]))
    pitch = float(-np.arcsin(np.clip(r[2, 0], -1.0, 1.0)))
    yaw = float(np.arctan2(r[1, 0], r[0, 0]))
    return roll, pitch, yaw


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


class Event(IntEnum):
    """The kinds of event on the filter's time line; events at one time run in this order."""

    IMU = 0
    GNSS = 1
    BARO = 2
    MAG = 3


@dataclass(frozen=True, eq=False)
class _FlightInputs:
    """A log's measurements as the filter uses them.

    Attributes:
        imu_t, imu_gyro, imu_acc: IMU samples sorted by time, block-averaged to about
            ``predict_rate_hz``: (N,), (N, 3) rad/s, (N, 3) m/s^2.
        dt_raw: median interval of the raw IMU samples, s.
        acc_sigma, gyro_sigma: IMU noise measured from the raw samples (m/s^2, rad/s).
        gnss: the usable fixes (fix type >= ``min_fix``, finite position).
        gnss_t: (M,) fix times minus the GNSS lag, s.
        gnss_pos, gnss_vel: (M, 3) ENU metres about ``origin`` and ENU m/s (NaN where unknown).
        baro: barometer samples, None when switched off.
        mag: compass samples.
        origin: the first usable fix (lat deg, lon deg, alt m).
        lag: GNSS lag, s.
        declination: magnetic declination, radians east.
        use_mag: whether the compass is used.
    """

    imu_t: np.ndarray
    imu_gyro: np.ndarray
    imu_acc: np.ndarray
    dt_raw: float
    acc_sigma: float
    gyro_sigma: float
    gnss: GnssFixes
    gnss_t: np.ndarray
    gnss_pos: np.ndarray
    gnss_vel: np.ndarray
    baro: BaroSeries | None
    mag: MagSeries
    origin: tuple[float, float, float]
    lag: float
    declination: float
    use_mag: bool

    @classmethod
    def from_log(cls, log: FlightLog, cfg: EkfConfig) -> _FlightInputs:
        """Select, sort and convert the log's measurements.

        Raises:
            InputError: no IMU samples or no GNSS fix of at least ``cfg.min_fix``.
        """
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
            raise InputError(
                f"{log.path}: the EKF needs a GNSS fix of type >= {cfg.min_fix}, the log has none"
            )
        gnss = log.gnss.subset(good)
        lag = _gnss_lag(log, cfg)
        origin = (float(gnss.lat[0]), float(gnss.lon[0]), float(gnss.alt[0]))
        order = np.argsort(imu.t, kind="stable")
        i_t, i_gyro, i_acc = imu.t[order], imu.gyro[order], imu.accel[order]
        # noise of the raw samples, then (for fast IMUs) block means at about predict_rate_hz
        acc_sigma, gyro_sigma = imu_noise_from_log(i_t, i_gyro, i_acc)
        dt_raw = float(np.median(np.diff(i_t)))
        i_t, i_gyro, i_acc = _block_means(i_t, i_gyro, i_acc, dt_raw, cfg.predict_rate_hz)
        return cls(
            imu_t=i_t,
            imu_gyro=i_gyro,
            imu_acc=i_acc,
            dt_raw=dt_raw,
            acc_sigma=acc_sigma,
            gyro_sigma=gyro_sigma,
            gnss=gnss,
            gnss_t=gnss.t - lag,
            gnss_pos=geo.geodetic_to_enu(gnss.lat, gnss.lon, gnss.alt, origin),
            gnss_vel=gnss.vel_ned @ geo.R_ENU_NED.T,  # NaN stays NaN
            baro=log.baro if cfg.use_baro else None,
            mag=log.mag,
            origin=origin,
            lag=lag,
            declination=_declination(log, cfg),
            use_mag=cfg.use_mag,
        )

    def level_attitude(self, w0: float, w1: float) -> tuple[np.ndarray, float]:
        """Attitude from the mean accelerometer (roll, pitch) and compass (yaw) in ``[w0, w1]``.

        Without a compass reading the heading comes from the GNSS course when the vehicle moves
        faster than 3 m/s, else it is 0 with a sigma of pi.

        Returns:
            The body->ENU quaternion (x, y, z, w) and the yaw sigma in radians.
        """
        i_t, i_acc, mag = self.imu_t, self.imu_acc, self.mag
        sel = (i_t >= w0) & (i_t <= w1)
        acc = (
            i_acc[sel].mean(axis=0)
            if np.any(sel)
            else i_acc[int(np.searchsorted(i_t, w0).clip(0, len(i_t) - 1))]
        )
        roll = float(np.arctan2(-acc[1], -acc[2]))
        pitch = float(np.arctan2(acc[0], np.hypot(acc[1], acc[2])))
        yaw, yaw_sigma = 0.0, float(np.pi)
        if len(mag) and self.use_mag:
            msel = (mag.t >= w0 - 1.0) & (mag.t <= w1 + 1.0)
            msel &= np.linalg.norm(mag.field, axis=1) > 0  # an all-zero field: no compass fitted
            if np.any(msel):
                yaw, yaw_sigma = mag_heading(mag.field[msel].mean(axis=0), roll, pitch, self.declination), 0.3
        if yaw_sigma >= np.pi:
            kk = min(int(np.searchsorted(self.gnss_t, w0)), len(self.gnss_t) - 1)
            vn = self.gnss.vel_ned[kk]
            if np.all(np.isfinite(vn[:2])) and np.hypot(vn[0], vn[1]) > 3.0:
                yaw, yaw_sigma = float(np.arctan2(vn[1], vn[0])), 0.3
        return geo.ned_to_enu_quat(euler_zyx_to_quat(roll, pitch, yaw)), yaw_sigma

    def timeline(self, cfg: EkfConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every event in time order: (times, :class:`Event` values as int8, measurement index).

        Barometer and compass samples are thinned to ``cfg.max_aiding_rate_hz``.
        """
        ev_t = [self.imu_t, self.gnss_t]
        ev_k = [np.full(len(self.imu_t), Event.IMU, np.int8), np.full(len(self.gnss_t), Event.GNSS, np.int8)]
        ev_i = [np.arange(len(self.imu_t)), np.arange(len(self.gnss_t))]
        for kind, series in ((Event.BARO, self.baro), (Event.MAG, self.mag if self.use_mag else None)):
            if series is not None and len(series):
                keep = _thin(series.t, cfg.max_aiding_rate_hz)
                ev_t.append(series.t[keep])
                ev_k.append(np.full(len(keep), kind, np.int8))
                ev_i.append(keep)
        all_t = np.concatenate(ev_t)
        all_k = np.concatenate(ev_k)
        all_i = np.concatenate(ev_i)
        order = np.lexsort((all_k, all_t))
        return all_t[order], all_k[order], all_i[order]


class NavigationFilter:
    """The error-state EKF of this module (see the module's description), one event at a time.

    :func:`run_ekf` is ``NavigationFilter(log, config).run()``. The steps are public for tests
    and for callers that drive the filter themselves: :meth:`predict` (IMU propagation), one
    update per sensor (:meth:`update_gnss`, :meth:`update_baro`, :meth:`update_mag`, each taking
    the index of the measurement in the log's prepared series), :meth:`reanchor` (position and
    velocity jump to a GNSS fix) and :meth:`restart_attitude` (after an IMU gap).

    State: ``p`` (3,) ENU m, ``v`` (3,) ENU m/s, ``q`` (4,) body->ENU quaternion (x, y, z, w),
    ``ba`` (3,) m/s^2, ``bg`` (3,) rad/s, ``bb`` barometer offset m, ``P`` (16, 16) covariance of
    the error state ``[dp, dv, dtheta, db_a, db_g, db_baro]``. ``p``, ``v`` and ``q`` are
    replaced, never changed in place, so recorded states stay as they were.
    """

    def __init__(self, log: FlightLog, config: EkfConfig | None = None) -> None:
        """Prepare the log's measurements and initialise the state at the first GNSS fix.

        Raises:
            InputError: no IMU samples or no GNSS fix of at least ``config.min_fix``.
        """
        self.config = cfg = config or EkfConfig()
        self.name = log.path.name
        self.inputs = inp = _FlightInputs.from_log(log, cfg)
        self.t_start = max(float(inp.gnss_t[0]), float(inp.imu_t[0]))
        self.q_acc = (cfg.accel_noise if cfg.accel_noise is not None else inp.acc_sigma) ** 2
        self.q_gyro = (cfg.gyro_noise if cfg.gyro_noise is not None else inp.gyro_sigma) ** 2
        self.accepted = {"gnss_pos": 0, "gnss_vel": 0, "baro": 0, "mag": 0}
        self.rejected = dict.fromkeys(self.accepted, 0)
        self.resets = 0
        self.t_now = self.t_imu = self.last_gnss_ok = self.t_start
        j_imu = max(int(np.searchsorted(inp.imu_t, self.t_start, side="right")) - 1, 0)
        self.a_m, self.w_m = inp.imu_acc[j_imu], inp.imu_gyro[j_imu]
        self.acc_h = 0.0  # horizontal acceleration magnitude, for the GNSS noise scaling
        self.need_anchor = False  # after an IMU gap, until the next GNSS fix
        self._init_state()
        # the state at every IMU sample: time, position, velocity, quaternion, position sigma
        self._out_t: list[float] = []
        self._out_p: list[np.ndarray] = []
        self._out_v: list[np.ndarray] = []
        self._out_q: list[np.ndarray] = []
        self._out_s: list[np.ndarray] = []

    def _init_state(self) -> None:
        """State and covariance at ``t_start`` from the nearest fix and the level attitude."""
        cfg, inp = self.config, self.inputs
        half = 0.5 * cfg.init_window_s
        self.q, yaw_sigma = inp.level_attitude(self.t_start - half, self.t_start + half)
        k0 = min(int(np.searchsorted(inp.gnss_t, self.t_start)), len(inp.gnss_t) - 1)
        self.p = inp.gnss_pos[k0].copy()
        self.v = np.nan_to_num(inp.gnss_vel[k0].copy())
        self.ba = np.zeros(3)
        self.bg = np.zeros(3)
        self.bb = 0.0
        if inp.baro is not None and len(inp.baro):
            self.bb = float(np.interp(self.t_start, inp.baro.t, inp.baro.alt)) - self.p[2]
        P = np.zeros((_N, _N))
        h0 = inp.gnss.h_acc[k0] if np.isfinite(inp.gnss.h_acc[k0]) else 0.0
        v0 = inp.gnss.v_acc[k0] if np.isfinite(inp.gnss.v_acc[k0]) else 0.0
        P[0, 0] = P[1, 1] = max(h0, cfg.gnss_pos_noise) ** 2
        P[2, 2] = max(v0, cfg.gnss_alt_noise) ** 2
        P[3:6, 3:6] = np.eye(3) * 0.5**2
        P[6, 6] = P[7, 7] = 0.05**2
        P[8, 8] = yaw_sigma**2  # body z ~ down, so this mostly covers heading
        P[9:12, 9:12] = np.eye(3) * 0.2**2
        P[12:15, 12:15] = np.eye(3) * 0.02**2
        P[15, 15] = 0.5**2
        self.P = P

    # -- the steps -----------------------------------------------------------------------------

    def predict(self, dt: float) -> None:
        """Propagate the state ``dt`` seconds with the held IMU sample (zero-order hold)."""
        if dt <= 0:
            return
        cfg = self.config
        r = quat_to_matrix(self.q)
        a = self.a_m - self.ba
        w = self.w_m - self.bg
        acc_w = r @ a + _G_VEC
        self.acc_h = float(np.hypot(acc_w[0], acc_w[1]))
        self.p = self.p + self.v * dt + 0.5 * acc_w * dt * dt
        self.v = self.v + acc_w * dt
        q = quat_multiply(self.q, quat_from_rotvec(w * dt))
        self.q = q / np.linalg.norm(q)
        F = np.eye(_N)
        F[0:3, 3:6] = np.eye(3) * dt
        F[3:6, 6:9] = -(r @ _skew(a)) * dt
        F[3:6, 9:12] = -r * dt
        F[6:9, 6:9] = _rotvec_matrix(w * dt).T
        F[6:9, 12:15] = -np.eye(3) * dt
        P = F @ self.P @ F.T
        d2 = dt * dt
        dn = self.inputs.dt_raw * dt  # white noise of per-sample sigma at the raw rate: sigma^2 dt_raw dt
        idx = np.arange(3)
        P[3 + idx, 3 + idx] += self.q_acc * dn
        P[6 + idx, 6 + idx] += self.q_gyro * dn
        P[9 + idx, 9 + idx] += cfg.accel_bias_noise**2 * d2
        P[12 + idx, 12 + idx] += cfg.gyro_bias_noise**2 * d2
        P[15, 15] += cfg.baro_bias_noise**2 * dt
        self.P = P

    def _correct(self, y: np.ndarray, H: np.ndarray, R: np.ndarray, kind: str) -> bool:
        """The gated Kalman update with innovation ``y``; False (and nothing changed) if gated."""
        PHt = self.P @ H.T
        S = H @ PHt + R
        if np.any(y * y > self.config.gate_sigma**2 * np.diag(S)):
            self.rejected[kind] += 1
            return False
        K = np.linalg.solve(S, PHt.T).T
        dx = K @ y
        IKH = np.eye(_N) - K @ H
        P = IKH @ self.P @ IKH.T + K @ R @ K.T
        self.P = 0.5 * (P + P.T)
        self.p = self.p + dx[_P]
        self.v = self.v + dx[_V]
        q = quat_multiply(self.q, quat_from_rotvec(dx[_TH]))
        self.q = q / np.linalg.norm(q)
        self.ba = self.ba + dx[_BA]
        self.bg = self.bg + dx[_BG]
        self.bb = self.bb + float(dx[_BB])
        self.accepted[kind] += 1
        return True

    def update_gnss(self, k: int, t: float) -> None:
        """Fuse GNSS fix ``k`` (position, then velocity); re-anchor on it when GNSS positions
        have been rejected for longer than ``gnss_reset_s``."""
        cfg, g = self.config, self.inputs.gnss
        extra = (cfg.gnss_accel_scale * self.acc_h) ** 2
        sh = max(g.h_acc[k] if np.isfinite(g.h_acc[k]) else 0.0, cfg.gnss_pos_noise)
        sv = max(g.v_acc[k] if np.isfinite(g.v_acc[k]) else 0.0, cfg.gnss_alt_noise)
        rows = [0, 1, 2] if cfg.use_gnss_altitude else [0, 1]
        H = np.zeros((len(rows), _N))
        for r_i, c in enumerate(rows):
            H[r_i, c] = 1.0
        R = np.diag([sh**2 + extra, sh**2 + extra, sv**2 + extra][: len(rows)])
        pos_ok = self._correct(self.inputs.gnss_pos[k, rows] - self.p[rows], H, R, "gnss_pos")
        if cfg.use_gnss_velocity:
            self._update_gnss_velocity(k, extra)
        if pos_ok:
            self.last_gnss_ok = t
        elif t - self.last_gnss_ok > cfg.gnss_reset_s:
            vel = self.inputs.gnss_vel[k]
            self.reanchor(t, self.inputs.gnss_pos[k], vel if np.all(np.isfinite(vel)) else None, sh, sv)

    def _update_gnss_velocity(self, k: int, extra: float) -> None:
        cfg = self.config
        gv = self.inputs.gnss_vel[k]
        vrows = [c for c in range(3) if np.isfinite(gv[c])]
        if not vrows:
            return
        s_acc = self.inputs.gnss.s_acc[k]
        ss = s_acc if np.isfinite(s_acc) else 0.0
        Hv = np.zeros((len(vrows), _N))
        sig = []
        for r_i, c in enumerate(vrows):
            Hv[r_i, 3 + c] = 1.0
            floor = cfg.gnss_vvel_noise if c == 2 else cfg.gnss_vel_noise
            sig.append(max(ss, floor) ** 2 + extra)
        self._correct(gv[vrows] - self.v[vrows], Hv, np.diag(sig), "gnss_vel")

    def update_baro(self, k: int) -> None:
        """Fuse barometer sample ``k``: ``alt = p_up + b_baro`` (skipped when not finite)."""
        baro = self.inputs.baro
        if baro is None:
            return
        H = np.zeros((1, _N))
        H[0, 2] = 1.0
        H[0, _BB] = 1.0
        y = np.array([baro.alt[k] - (self.p[2] + self.bb)])
        if np.isfinite(y[0]):
            self._correct(y, H, np.array([[self.config.baro_noise**2]]), "baro")

    def update_mag(self, k: int) -> None:
        """Fuse compass sample ``k`` as a tilt-compensated heading (skipped when the field is
        missing or zero, or the body is pitched near vertical)."""
        field = self.inputs.mag.field[k]
        if not np.all(np.isfinite(field)) or not np.any(field):
            return
        roll, pitch, yaw = _ned_euler(quat_to_matrix(self.q))
        if abs(np.cos(pitch)) < 0.2:
            return
        z = mag_heading(field, roll, pitch, self.inputs.declination)
        H = np.zeros((1, _N))
        H[0, 7] = np.sin(roll) / np.cos(pitch)
        H[0, 8] = np.cos(roll) / np.cos(pitch)
        y = np.array([float(geo.wrap_angle(z - yaw))])
        self._correct(y, H, np.array([[self.config.yaw_noise**2]]), "mag")

    def reanchor(
        self, t: float, position: np.ndarray, velocity: np.ndarray | None, sigma_h: float, sigma_v: float
    ) -> None:
        """Jump to a GNSS fix: position (and velocity, unless None) are set, their covariance is
        reset (horizontal / vertical position sigmas, 0.5 m/s velocity) and decorrelated."""
        self.p = np.array(position, dtype=np.float64)
        if velocity is not None:
            self.v = np.array(velocity, dtype=np.float64)
        P = self.P
        P[0:6, :] = 0.0
        P[:, 0:6] = 0.0
        P[0, 0] = P[1, 1] = sigma_h**2
        P[2, 2] = sigma_v**2
        P[3:6, 3:6] = np.eye(3) * 0.5**2
        self.resets += 1
        self.last_gnss_ok = t

    def restart_attitude(self, t: float) -> None:
        """Attitude from accelerometer and compass again (after an IMU gap), its covariance reset."""
        self.q, yaw_sigma = self.inputs.level_attitude(t, t + self.config.init_window_s)
        P = self.P
        P[6:9, :] = 0.0
        P[:, 6:9] = 0.0
        P[6, 6] = P[7, 7] = 0.05**2
        P[8, 8] = yaw_sigma**2

    def process(self, t: float, kind: Event, k: int) -> None:
        """One event of the time line: predict up to ``t``, then the measurement's step."""
        cfg, inp = self.config, self.inputs
        if t - self.t_imu > cfg.max_imu_gap_s:
            # the IMU has been silent (a logging gap, e.g. disarmed, or an IMU dropout while the
            # other sensors go on): never integrate a held IMU sample across it. When the IMU is
            # back the vehicle may have been moved or set upright, so attitude restarts from
            # accelerometer and compass, and position re-anchors on the next GNSS fix.
            if kind is Event.IMU:
                self.need_anchor = True
                self.restart_attitude(t)
        else:
            self.predict(t - self.t_now)
        self.t_now = t
        if kind is Event.IMU:
            self.t_imu = t
        if self.need_anchor and kind is Event.GNSS:
            vel = np.nan_to_num(inp.gnss_vel[k])
            self.reanchor(t, inp.gnss_pos[k], vel, cfg.gnss_pos_noise, cfg.gnss_alt_noise)
            self.need_anchor = False
        elif kind is Event.IMU:
            self.a_m, self.w_m = inp.imu_acc[k], inp.imu_gyro[k]
            self._record(t)
        elif kind is Event.GNSS:
            self.update_gnss(k, t)
        elif kind is Event.BARO:
            self.update_baro(k)
        else:
            self.update_mag(k)

    def _record(self, t: float) -> None:
        self._out_t.append(t)
        self._out_p.append(self.p)
        self._out_v.append(self.v)
        self._out_q.append(self.q)
        self._out_s.append(np.sqrt(np.diag(self.P)[0:3]))

    # -- the whole log -------------------------------------------------------------------------

    def run(self) -> tuple[NavSolution, EkfReport]:
        """Process every event from ``t_start`` on; the solution at every IMU sample and a report."""
        all_t, all_k, all_i = self.inputs.timeline(self.config)
        begin = int(np.searchsorted(all_t, self.t_start, side="left"))
        for e in range(begin, len(all_t)):
            self.process(float(all_t[e]), Event(int(all_k[e])), int(all_i[e]))
        solution = self.solution()
        logger.info(
            "EKF on %s: %d IMU steps, accepted %s, rejected %s",
            self.name,
            len(solution),
            self.accepted,
            self.rejected,
        )
        return solution, self.report()

    def solution(self) -> NavSolution:
        """The states recorded so far (one per IMU sample), as a navigation solution."""
        q = np.array(self._out_q, dtype=np.float64).reshape(-1, 4)
        return NavSolution(
            name="stablecues-ekf",
            origin=self.inputs.origin,
            t=np.array(self._out_t, dtype=np.float64),
            position=np.array(self._out_p, dtype=np.float64).reshape(-1, 3),
            velocity=np.array(self._out_v, dtype=np.float64).reshape(-1, 3),
            quaternion=geo.map_known(quat_normalize, q, 4),
            position_std=np.array(self._out_s, dtype=np.float64).reshape(-1, 3),
        )

    def report(self) -> EkfReport:
        """The settings used and the update counts so far."""
        return EkfReport(
            gnss_lag_s=self.inputs.lag,
            declination_deg=float(np.degrees(self.inputs.declination)),
            accel_noise=float(np.sqrt(self.q_acc)),
            gyro_noise=float(np.sqrt(self.q_gyro)),
            accepted=dict(self.accepted),
            rejected=dict(self.rejected),
            resets=self.resets,
            start_time=self.t_start,
        )


def run_ekf(log: FlightLog, config: EkfConfig | None = None) -> tuple[NavSolution, EkfReport]:
    """Fuse a flight log's IMU, GNSS, barometer and magnetometer into a navigation solution.

    Args:
        log: a flight log with IMU and GNSS (barometer and magnetometer are optional).
        config: filter settings; :class:`EkfConfig` defaults when None.

    Returns:
        The solution at every IMU sample from the initialisation on (ENU about the first
        usable GNSS fix, quaternions (x, y, z, w); ``name`` "stablecues-ekf"), and an
        :class:`EkfReport`.

    Raises:
        InputError: the log has no IMU samples or no GNSS fix of at least ``config.min_fix``.
    """
    return NavigationFilter(log, config).run()


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
        r_rpy = geo.map_known(quat_to_euler_zyx, geo.enu_to_ned_quat(ref.quaternion[keep]), 3)
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
