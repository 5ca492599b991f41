"""Synthetic flight data shared by the mav tests (no shared data needed).

* :func:`make_log`: a hand-written ArduPilot dataflash log (binary);
* :func:`simulate`: a simulated flight (IMU, GNSS, barometer, compass) with its true solution;
* :func:`track_log`: a CSV GNSS track with boot and UTC clocks;
* :func:`fake_images`: placeholder image files.

Quaternions are (x, y, z, w), as everywhere in stablecues.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from stablecues.geometry.rotations import euler_zyx_to_quat, quat_to_matrix
from stablecues.mav import (
    AttitudeSeries,
    BaroSeries,
    FlightLog,
    GnssFixes,
    ImuSeries,
    MagSeries,
    NavSolution,
    geo,
)

# ---------------------------------------------------------------------------------------------
# ArduPilot dataflash

DF_HEAD = b"\xa3\x95"
# name -> (type id, struct format after the header, dataflash format, columns)
FORMATS = {
    "MSG": (140, "<Q64s", "QZ", "TimeUS,Message"),
    "PARM": (141, "<Q16sf", "QNf", "TimeUS,Name,Value"),
    "GPS": (142, "<QBIHBhiiffff", "QBIHBcLLffff", "TimeUS,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ"),
    "IMU": (143, "<QBffffff", "QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ"),
    "BARO": (144, "<QBff", "QBff", "TimeUS,I,Alt,Press"),
    "MAG": (145, "<QBhhh", "QBhhh", "TimeUS,I,MagX,MagY,MagZ"),
    "ATT": (146, "<Qfff", "Qfff", "TimeUS,Roll,Pitch,Yaw"),
    "MODE": (147, "<QBBB", "QMBB", "TimeUS,Mode,ModeNum,Rsn"),
    "XKF1": (148, "<QBfffffffff", "QBfffffffff", "TimeUS,C,Roll,Pitch,Yaw,VN,VE,VD,PN,PE,PD"),
    "ORGN": (149, "<QBiif", "QBLLf", "TimeUS,Type,Lat,Lng,Alt"),
    "XKQ": (150, "<QBffff", "QBffff", "TimeUS,C,Q1,Q2,Q3,Q4"),
}
FMT_STRUCT = struct.Struct("<BB4s16s64s")


def _fmt_record(name: str) -> bytes:
    tid, fmt, df, cols = FORMATS[name]
    length = 3 + struct.calcsize(fmt)
    return DF_HEAD + bytes([128]) + FMT_STRUCT.pack(tid, length, name.encode(), df.encode(), cols.encode())


def _record(name: str, *values: object) -> bytes:
    tid, fmt, _, _ = FORMATS[name]
    vals = [v.encode() if isinstance(v, str) else v for v in values]
    if name == "MSG":
        vals[1] = vals[1].ljust(64, b"\0")  # type: ignore[union-attr]
    return DF_HEAD + bytes([tid]) + struct.pack(fmt, *vals)


def make_log(seconds: float = 10.0, *, xkq_wxyz: tuple[float, float, float, float] | None = None) -> bytes:
    """A copter hovering 1 s, then flying north at 2 m/s; LOITER, BRAKE at 4 s, RTL at 7 s.

    Args:
        seconds: log length.
        xkq_wxyz: when given, an EKF3 attitude quaternion record (XKQ, logged scalar first as
            ArduPilot does) with this value beside every XKF1 record (whose Euler angles say 0).
    """
    out = bytearray()
    # FMT of FMT itself, as ArduPilot writes it
    out += (
        DF_HEAD
        + bytes([128])
        + FMT_STRUCT.pack(128, 89, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns")
    )
    for name in FORMATS:
        if name != "XKQ" or xkq_wxyz is not None:
            out += _fmt_record(name)
    t0 = 50_000_000  # 50 s after boot
    out += _record("MSG", t0, "ArduCopter V4.3.6 (abcdef12)")
    out += _record("PARM", t0, "COMPASS_DEC", 0.0)
    out += _record("ORGN", t0, 0, int(52.0 * 1e7), int(-4.0 * 1e7), 100.0)
    out += _record("MODE", t0, 5, 5, 1)
    lat0, lon0 = 52.0, -4.0
    for k in range(int(seconds * 50)):
        t = t0 + k * 20_000
        ts = k * 0.02
        out += _record("IMU", t, 0, 0.0, 0.0, 0.0, 0.0, 0.0, -9.80665)
        out += _record("IMU", t, 1, 0.0, 0.0, 0.0, 0.0, 0.0, -9.7)  # second IMU: ignored
        if k % 5 == 0:
            out += _record("BARO", t, 0, 0.5, 101000.0)
            out += _record("MAG", t, 0, 200, 0, 400)
            out += _record("ATT", t, 0.0, 0.0, 0.0)
            north = max(0.0, ts - 1.0) * 2.0
            speed = 2.0 if ts > 1.0 else 0.0
            out += _record("XKF1", t, 0, 0.0, 0.0, 0.0, speed, 0.0, 0.0, north, 0.0, 0.0)
            if xkq_wxyz is not None:
                out += _record("XKQ", t, 0, *xkq_wxyz)
        if k % 10 == 0:
            north = max(0.0, ts - 1.0) * 2.0
            lat = lat0 + north / 6_371_000.0 * 180.0 / np.pi
            gms = 300_000_000 + k * 20
            speed = 2.0 if ts > 1.0 else 0.0
            out += _record(
                "GPS", t, 3, gms, 2269, 15, 80, int(round(lat * 1e7)), int(lon0 * 1e7), 100.0, speed, 0.0, 0.0
            )
        if k == 200:
            out += _record("MODE", t, 17, 17, 1)
        if k == 350:
            out += _record("MODE", t, 6, 6, 1)
    return bytes(out)


# ---------------------------------------------------------------------------------------------
# A simulated flight for the EKF

SIM_ORIGIN = (47.0, 8.0, 400.0)
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
    return geo.R_ENU_NED @ quat_to_matrix(euler_zyx_to_quat(rpy[:, 0], rpy[:, 1], rpy[:, 2]))


def simulate(
    *, duration: float = 40.0, imu_hz: float = 50.0, lag: float = 0.0, seed: int = 0
) -> tuple[FlightLog, NavSolution]:
    """A 12 m circle at 3 m/s with IMU biases and sensor noise, and its true solution."""
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
    llh = geo.enu_to_geodetic(pg_noisy, SIM_ORIGIN)
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
    rpy_m = _truth(tm)[3]
    r_m_ned = quat_to_matrix(euler_zyx_to_quat(rpy_m[:, 0], rpy_m[:, 1], rpy_m[:, 2]))
    mag_b = np.einsum("nji,j->ni", r_m_ned, earth_ned) + rng.normal(0, 0.003, (len(tm), 3))
    log = FlightLog(
        path=Path("simulated"), kind="sim", vehicle="sim", duration=duration, boot_time_offset=0.0,
        utc_offset=float("nan"), counts={}, params={}, gnss=gnss, baro=baro, imu=imu,
        mag=MagSeries(tm, mag_b), attitude=AttitudeSeries.empty(), onboard=None, ground_truth=None,
        mode_changes=(),
    )  # fmt: skip
    ptrue, vtrue, _, rpy_t = _truth(ti)
    q_true = geo.ned_to_enu_quat(euler_zyx_to_quat(rpy_t[:, 0], rpy_t[:, 1], rpy_t[:, 2]))
    truth = NavSolution("truth", SIM_ORIGIN, ti, ptrue, vtrue, q_true)
    return log, truth


# ---------------------------------------------------------------------------------------------
# CSV GNSS track and image files

TRACK_ORIGIN = (50.0, 10.0, 100.0)


def track_log(tmp_path: Path, *, speed: float = 5.0) -> Path:
    """A CSV GNSS track flying east at ``speed`` m/s for 60 s, 10 Hz, boot clock plus UTC."""
    t = np.arange(0.0, 60.0, 0.1)
    enu = np.column_stack([speed * t, np.zeros_like(t), 20.0 + 0 * t])
    llh = geo.enu_to_geodetic(enu, TRACK_ORIGIN)
    boot0, utc0 = 100.0, 1.7e9
    rows = ["timestamp,utc_usec,lat,lon,alt_msl"]
    for k in range(len(t)):
        stamps = f"{int((boot0 + t[k]) * 1e6)},{int((utc0 + t[k]) * 1e6)}"
        rows.append(f"{stamps},{llh[k, 0]:.9f},{llh[k, 1]:.9f},{llh[k, 2]:.3f}")
    path = tmp_path / "track.csv"
    path.write_text("\n".join(rows) + "\n")
    return path


def fake_images(folder: Path, names: list[str]) -> None:
    """Files with image names (not decodable: the mav code never decodes them)."""
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        (folder / n).write_bytes(b"\x89PNG fake")
