"""Flight-log readers: ArduPilot dataflash, PX4 ULog and plain GNSS tracks into :class:`FlightLog`.

:func:`read_log` recognises the format from the file's first bytes, not from its name:

* ArduPilot dataflash binary (``.bin``, records start with ``0xA3 0x95``) and its text form
  (``.log``, lines starting with ``FMT,``), through :mod:`pymavlink`'s ``DFReader``;
* PX4 ULog (``.ulg``, magic ``ULog``), through :mod:`pyulog`;
* a CSV GNSS track (a header naming latitude / longitude columns and a time column), for
  recordings that only kept the receiver's positions.

The first instance of every sensor is used (IMU 0, GPS 0, BARO 0, MAG 0, EKF core 0), which is
what the autopilots fly on by default. A file that ends inside a record is read up to the last
whole record and a warning says so; a file of none of these formats raises
:class:`~stablecues.errors.DatasetError`.
"""

from __future__ import annotations

import contextlib
import io
import logging
import re
import struct
import warnings
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import DatasetError, MissingDependencyError, StableCuesError, reason
from ..fileio import captured_stderr
from ..geometry.rotations import euler_zyx_to_quat, quat_to_euler_zyx, wxyz_to_xyzw
from . import geo
from .flightlog import (
    AttitudeSeries,
    BaroSeries,
    FlightLog,
    GnssFixes,
    ImuSeries,
    MagSeries,
    ModeChange,
    NavSolution,
)
from .tables import find_column, numbers, read_csv_table, time_column_seconds

logger = logging.getLogger(__name__)

__all__ = ["TruncatedLogWarning", "read_log", "detect_format"]

_DF_MAGIC = b"\xa3\x95"
_ULOG_MAGIC = b"ULog\x01\x12\x35"
_GPS_EPOCH_UNIX = 315964800.0  # 1980-01-06T00:00:00Z
# (first UNIX second in force, GPS - UTC seconds)
_LEAP_SECONDS = ((1341100800.0, 16), (1435708800.0, 17), (1483228800.0, 18))

# PX4 vehicle_status.nav_state names (msg/VehicleStatus.msg).
PX4_NAV_STATES = {
    0: "MANUAL", 1: "ALTCTL", 2: "POSCTL", 3: "AUTO_MISSION", 4: "AUTO_LOITER", 5: "AUTO_RTL",
    6: "AUTO_RCRECOVER", 7: "AUTO_RTGS", 8: "AUTO_LANDENGFAIL", 9: "AUTO_LANDGPSFAIL", 10: "ACRO",
    11: "UNUSED", 12: "DESCEND", 13: "TERMINATION", 14: "OFFBOARD", 15: "STAB", 16: "RATTITUDE",
    17: "AUTO_TAKEOFF", 18: "AUTO_LAND", 19: "AUTO_FOLLOW_TARGET", 20: "AUTO_PRECLAND", 21: "ORBIT",
    22: "AUTO_VTOL_TAKEOFF", 23: "EXTERNAL1", 24: "EXTERNAL2", 25: "EXTERNAL3", 26: "EXTERNAL4",
    27: "EXTERNAL5", 28: "EXTERNAL6", 29: "EXTERNAL7", 30: "EXTERNAL8",
}  # fmt: skip


class TruncatedLogWarning(UserWarning):
    """The log file ends inside a record; everything before it was read."""


def detect_format(path: str | Path) -> str:
    """The format of a flight-log file from its first bytes.

    Returns:
        "dataflash", "dataflash_text", "ulog" or "gnss_csv".

    Raises:
        DatasetError: missing file, or none of these formats.
    """
    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"{p}: flight log not found")
    with p.open("rb") as fh:
        head = fh.read(4096)
    if head.startswith(_ULOG_MAGIC):
        return "ulog"
    if head.startswith(_DF_MAGIC) and len(head) >= 3:
        return "dataflash"
    text = head.decode("utf-8", errors="replace").lstrip("\ufeff")
    if text.startswith("FMT,") or text.startswith("FMT, "):
        return "dataflash_text"
    first = text.splitlines()[0].lower() if text else ""
    cols = {c.strip().strip("#").strip() for c in re.split(r"[,;\t]", first)}
    if cols & _LAT_NAMES and cols & _LON_NAMES:
        return "gnss_csv"
    shown = head[:8].hex(" ") if head else "an empty file"
    raise DatasetError(
        f"{p}: not a flight log: expected an ArduPilot dataflash log (starts a3 95), a PX4 ULog "
        f"(starts 'ULog') or a CSV GNSS track with lat/lon columns, found {shown}"
    )


def read_log(path: str | Path) -> FlightLog:
    """Read a flight log into a :class:`FlightLog`.

    Args:
        path: ArduPilot ``.bin`` / ``.log``, PX4 ``.ulg``, or a CSV GNSS track.

    Returns:
        The log's series, modes, onboard EKF output and bookkeeping. Reading problems that
        still leave usable data are listed in ``FlightLog.warnings`` and emitted as Python
        warnings (:class:`TruncatedLogWarning` for a file cut inside a record).

    Raises:
        DatasetError: missing file, not a flight log, or a log with no timestamped record.
        ImportError: pymavlink / pyulog missing (``pip install "stablecues[mav]"``).
    """
    p = Path(path)
    fmt = detect_format(p)
    if fmt in ("dataflash", "dataflash_text"):
        log = _read_dataflash(p, text=fmt == "dataflash_text")
    elif fmt == "ulog":
        log = _read_ulog(p)
    else:
        log = _read_gnss_csv(p)
    for w in log.warnings:
        category: type[Warning] = TruncatedLogWarning if "ends inside a record" in w else UserWarning
        warnings.warn(f"{p.name}: {w}", category, stacklevel=2)
    return log


# ---------------------------------------------------------------------------------------------
# ArduPilot dataflash


def _import(module: str) -> Any:
    try:
        if module == "DFReader":
            from pymavlink import DFReader

            return DFReader
        if module == "mavutil":
            from pymavlink import mavutil

            return mavutil
        if module == "pyulog":
            import pyulog

            return pyulog
    except ImportError as exc:  # pragma: no cover - depends on the environment
        package = "pyulog" if module == "pyulog" else "pymavlink"
        raise MissingDependencyError(f"reading flight logs needs {package}: {geo.MAV_EXTRA_HINT}") from exc
    raise ValueError(module)


_WANTED = {"GPS", "GPA", "IMU", "BARO", "MAG", "ATT", "XKF1", "XKQ", "NKF1", "NKQ1", "NKQ", "EKF1"}
_WANTED |= {"ORGN", "MODE", "MSG", "PARM"}


_Rows = list[tuple[float | None, Any]]


@dataclass
class _DataflashScan:
    """What one pass over a dataflash log keeps: counts, wanted records, parameters, clocks."""

    counts: Counter[str] = field(default_factory=Counter)
    rows: dict[str, _Rows] = field(default_factory=lambda: {k: [] for k in _WANTED})
    params: dict[str, float] = field(default_factory=dict)
    vehicle: str = ""
    first_boot: float | None = None
    last_boot: float | None = None
    mav_type: Any = None
    trailing: int = 0
    offset: int = 0
    data_len: int = 0
    noise: list[str] = field(default_factory=list)
    unseen: int = 0

    def add(self, name: str, boot: float | None, m: Any) -> None:
        """Book one record of a wanted type."""
        if name == "PARM":
            self.params[str(m.Name)] = float(m.Value)
        elif name == "MSG":
            msg = str(m.Message)
            if not self.vehicle and re.match(r"(Ardu\w+|APM:\w+|Rover|Blimp|AntennaTracker)", msg):
                self.vehicle = msg
        else:
            self.rows[name].append((boot, m))


def _boot_time(m: Any, name: str, boot: float | None) -> float | None:
    """The record's boot-clock time in seconds, or ``boot`` (the last one seen) when it has none."""
    names = m._fieldnames
    if "TimeUS" in names:
        return float(m.TimeUS * 1e-6)
    if name == "GPS" and "T" in names:  # ArduCopter 3.x: TimeMS is the GPS time of week
        return float(m.T * 1e-3)
    if "TimeMS" in names and name != "GPS":
        return float(m.TimeMS * 1e-3)
    return boot


def _open_dataflash(path: Path, text: bool) -> Any:
    dfreader = _import("DFReader")
    try:
        return (
            dfreader.DFReader_text(str(path), zero_time_base=False)
            if text
            else dfreader.DFReader_binary(str(path), zero_time_base=False)
        )
    except Exception as exc:
        raise DatasetError(f"{path}: not a readable dataflash log ({type(exc).__name__}: {exc})") from None


def _read_records(reader: Any, scan: _DataflashScan, err: io.StringIO) -> None:
    """Every record of ``reader`` into ``scan``; a reader error ends the pass (noted in ``err``)."""
    boot: float | None = None
    while True:
        try:
            m = reader.recv_msg()
        except Exception as exc:  # pymavlink raises assorted errors on corrupt data
            err.write(f"stopped reading: {type(exc).__name__}: {exc}\n")
            break
        if m is None:
            break
        name = m.get_type()
        scan.counts[name] += 1
        boot = _boot_time(m, name, boot)
        if boot is not None:
            scan.first_boot = boot if scan.first_boot is None else scan.first_boot
            scan.last_boot = boot if scan.last_boot is None else max(scan.last_boot, boot)
        if name in _WANTED:
            scan.add(name, boot, m)


def _scan_dataflash(path: Path, text: bool) -> _DataflashScan:
    """One pass over the log with pymavlink, its console output captured as ``noise``."""
    scan = _DataflashScan()
    out, err = io.StringIO(), io.StringIO()
    # pymavlink prints from Python and from its compiled indexer (file descriptor 2): keep both
    with captured_stderr() as printed, contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        reader = _open_dataflash(path, text)
        _read_records(reader, scan, err)
        scan.mav_type = reader.mav_type
        scan.data_len = int(getattr(reader, "data_len", 0))
        scan.offset = int(getattr(reader, "offset", 0))
        scan.trailing = max(0, scan.data_len - scan.offset) if not text else 0
        with contextlib.suppress(Exception):
            reader.close()
        with contextlib.suppress(Exception):
            reader.filehandle.close()
    scan.noise = [ln for ln in (out.getvalue() + err.getvalue()).splitlines() if ln.strip()]
    scan.noise += printed.lines
    scan.unseen = printed.count - len(printed.lines)
    return scan


def _dataflash_warnings(scan: _DataflashScan) -> list[str]:
    """One line per reading problem: a truncated file, skipped bytes, the reader's messages."""
    warn_list: list[str] = []
    if scan.trailing > 0:
        warn_list.append(
            f"log ends inside a record: the last {scan.trailing} bytes were ignored "
            f"(read up to offset {scan.offset} of {scan.data_len})"
        )
    if scan.noise:
        bad = sum("bad header" in ln for ln in scan.noise)
        rest = [ln for ln in scan.noise if "bad header" not in ln]
        if bad:
            warn_list.append(f"skipped {bad} bytes of unrecognised data")
        warn_list += rest[:5]
        if len(rest) > 5 or scan.unseen:
            warn_list.append(f"... and {max(len(rest) - 5, 0) + scan.unseen} more reader messages")
    return warn_list


def _df_times(items: _Rows, t0: float) -> np.ndarray:
    """Seconds since log start of records (a record before the first timestamp is at 0)."""
    return np.array([(b if b is not None else t0) - t0 for b, _ in items], dtype=np.float64)


def _df_first(items: _Rows, field: str = "I") -> _Rows:
    """The records of instance 0 (or without an instance field)."""
    return [(b, m) for b, m in items if getattr(m, field, 0) in (0, None) or field not in m._fieldnames]


def _df_sensors(rows: dict[str, _Rows], t0: float) -> tuple[ImuSeries, BaroSeries, MagSeries, AttitudeSeries]:
    """IMU, barometer, compass (first instances) and the autopilot's attitude."""
    imu_rows = _df_first(rows["IMU"])
    imu = (
        ImuSeries(
            _df_times(imu_rows, t0),
            np.array([[m.GyrX, m.GyrY, m.GyrZ] for _, m in imu_rows], dtype=np.float64),
            np.array([[m.AccX, m.AccY, m.AccZ] for _, m in imu_rows], dtype=np.float64),
        )
        if imu_rows
        else ImuSeries.empty()
    )
    baro_rows = _df_first(rows["BARO"])
    baro = (
        BaroSeries(
            _df_times(baro_rows, t0),
            np.array([m.Alt for _, m in baro_rows], dtype=np.float64),
            np.array([getattr(m, "Press", np.nan) for _, m in baro_rows], dtype=np.float64),
        )
        if baro_rows
        else BaroSeries.empty()
    )
    mag_rows = _df_first(rows["MAG"])
    mag = (
        MagSeries(
            _df_times(mag_rows, t0),
            np.array([[m.MagX, m.MagY, m.MagZ] for _, m in mag_rows], dtype=np.float64) * 1e-3,
        )
        if mag_rows
        else MagSeries.empty()
    )
    att_rows = rows["ATT"]
    attitude = AttitudeSeries.empty()
    if att_rows:
        rpy = np.radians(np.array([[m.Roll, m.Pitch, m.Yaw] for _, m in att_rows], dtype=np.float64))
        attitude = AttitudeSeries(
            _df_times(att_rows, t0), np.column_stack([rpy[:, :2], geo.wrap_angle(rpy[:, 2])])
        )
    return imu, baro, mag, attitude


def _df_modes(rows: _Rows, t0: float, mav_type: Any) -> tuple[ModeChange, ...]:
    """Flight-mode records, named by pymavlink's mode table of the vehicle type."""
    mapping = _import("mavutil").mode_mapping_bynumber(mav_type) or {}
    changes: list[ModeChange] = []
    for b, m in rows:
        t = (b if b is not None else t0) - t0
        raw = m.ModeNum if "ModeNum" in m._fieldnames else m.Mode
        if isinstance(raw, str) and not raw.strip().lstrip("-").isdigit():
            changes.append(ModeChange(t, raw.strip().upper(), -1))  # very old logs name the mode
            continue
        number = int(raw)
        changes.append(ModeChange(t, str(mapping.get(number, f"MODE_{number}")), number))
    return tuple(changes)


# what pymavlink raises when a record's field does not hold what its format says (it converts
# fields when they are read), and what converting such a field raises here
_RECORD_ERRORS = (ValueError, TypeError, AttributeError, OverflowError, KeyError, IndexError, struct.error)


def _read_dataflash(path: Path, *, text: bool) -> FlightLog:
    try:
        return _decode_dataflash(path, text)
    except StableCuesError:
        raise
    except _RECORD_ERRORS as exc:
        raise DatasetError(
            f"{path}: a record holds a value its format does not allow ({reason(exc)})"
        ) from None


def _decode_dataflash(path: Path, text: bool) -> FlightLog:
    scan = _scan_dataflash(path, text)
    if scan.first_boot is None or scan.last_boot is None:
        raise DatasetError(f"{path}: not a usable dataflash log: no record with a timestamp was found")
    warn_list = _dataflash_warnings(scan)
    t0 = scan.first_boot
    rows = scan.rows
    gnss, utc_offset = _df_gnss(_df_first(rows["GPS"]), _df_first(rows["GPA"]), t0)
    imu, baro, mag, attitude = _df_sensors(rows, t0)
    onboard, origin_note = _df_onboard(rows, t0, gnss)
    if origin_note:
        warn_list.append(origin_note)
    return FlightLog(
        path=path,
        kind="ardupilot",
        vehicle=scan.vehicle,
        duration=float(scan.last_boot - t0),
        boot_time_offset=float(t0),
        utc_offset=utc_offset,
        counts=dict(scan.counts),
        params=scan.params,
        gnss=gnss,
        baro=baro,
        imu=imu,
        mag=mag,
        attitude=attitude,
        onboard=onboard,
        ground_truth=None,
        mode_changes=_df_modes(rows["MODE"], t0, scan.mav_type),
        truncated=scan.trailing > 0,
        warnings=tuple(warn_list),
    )


def _gps_to_unix(week: np.ndarray, tow_s: np.ndarray) -> np.ndarray:
    gps = _GPS_EPOCH_UNIX + week * 604800.0 + tow_s
    leap = np.zeros_like(gps)
    for start, seconds in _LEAP_SECONDS:
        leap = np.where(gps >= start + seconds, seconds, leap)
    return gps - leap


def _df_gnss(
    gps_rows: list[tuple[float | None, Any]], gpa_rows: list[tuple[float | None, Any]], t0: float
) -> tuple[GnssFixes, float]:
    if not gps_rows:
        return GnssFixes.empty(), float("nan")
    acc = {round(b, 6): m for b, m in gpa_rows if b is not None}
    t, lat, lon, alt, fix, nsat, vel, h_acc, v_acc, s_acc, week, tow = ([] for _ in range(12))
    for b, m in gps_rows:
        bt = b if b is not None else t0
        t.append(bt - t0)
        lat.append(m.Lat)
        lon.append(m.Lng)
        alt.append(m.Alt)
        fix.append(m.Status)
        nsat.append(getattr(m, "NSats", -1))
        spd, crs = float(m.Spd), np.radians(float(m.GCrs))
        vz = float(getattr(m, "VZ", np.nan))
        a = acc.get(round(bt, 6))
        if a is not None and "VV" in a._fieldnames and not a.VV:
            vz = np.nan
        vel.append((spd * np.cos(crs), spd * np.sin(crs), vz))
        h_acc.append(getattr(a, "HAcc", np.nan) if a is not None else np.nan)
        v_acc.append(getattr(a, "VAcc", np.nan) if a is not None else np.nan)
        s_acc.append(getattr(a, "SAcc", np.nan) if a is not None else np.nan)
        if "GWk" in m._fieldnames:
            week.append(m.GWk)
            tow.append(m.GMS * 1e-3)
        elif "Week" in m._fieldnames:
            week.append(m.Week)
            tow.append(m.TimeMS * 1e-3)
        else:
            week.append(0)
            tow.append(np.nan)
    fixes = GnssFixes(
        t=np.array(t, dtype=np.float64),
        lat=np.array(lat, dtype=np.float64),
        lon=np.array(lon, dtype=np.float64),
        alt=np.array(alt, dtype=np.float64),
        fix=np.array(fix, dtype=np.int16),
        n_sats=np.array(nsat, dtype=np.int16),
        vel_ned=np.array(vel, dtype=np.float64).reshape(-1, 3),
        h_acc=np.array(h_acc, dtype=np.float64),
        v_acc=np.array(v_acc, dtype=np.float64),
        s_acc=np.array(s_acc, dtype=np.float64),
    )
    w = np.array(week, dtype=np.float64)
    s = np.array(tow, dtype=np.float64)
    ok = (w > 0) & np.isfinite(s) & (fixes.fix >= 3)
    utc_offset = float(np.median(_gps_to_unix(w[ok], s[ok]) - fixes.t[ok])) if np.any(ok) else float("nan")
    return fixes, utc_offset


def _df_onboard(rows: dict[str, _Rows], t0: float, gnss: GnssFixes) -> tuple[NavSolution | None, str]:
    """The autopilot's EKF output (EKF3 XKF1 core 0, else EKF2 NKF1, else the 2014 EKF1)."""
    found = [
        (n, qn) for n, qn in (("XKF1", "XKQ"), ("NKF1", "NKQ1"), ("EKF1", "")) if _df_first(rows[n], "C")
    ]
    if not found:
        return None, ""
    name, qname = found[0]
    items = _df_first(rows[name], "C")
    t = _df_times(items, t0)
    ned = np.array([[m.PN, m.PE, m.PD] for _, m in items], dtype=np.float64)
    vel_ned = np.array([[m.VN, m.VE, m.VD] for _, m in items], dtype=np.float64)
    rpy = np.radians(np.array([[m.Roll, m.Pitch, m.Yaw] for _, m in items], dtype=np.float64))
    q_ned = euler_zyx_to_quat(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    if qname:
        qitems = _df_first(rows[qname] or rows.get("NKQ", []), "C")
        qmap = {round(b, 6): m for b, m in qitems if b is not None}
        for k, (b, _) in enumerate(items):
            qm = qmap.get(round(b if b is not None else t0, 6))
            if qm is not None:
                q_ned[k] = (qm.Q2, qm.Q3, qm.Q4, qm.Q1)  # logged scalar first (Q1 = w)
    q_enu = geo.ned_to_enu_quat(q_ned)
    pos = ned @ geo.R_ENU_NED.T
    vel = vel_ned @ geo.R_ENU_NED.T
    origins = [m for _, m in rows["ORGN"] if getattr(m, "Type", 0) == 0]
    note = ""
    if origins:
        origin = (float(origins[0].Lat), float(origins[0].Lng), float(origins[0].Alt))
        estimated = False
    else:
        origin, ok = _fit_origin(t, pos, gnss)
        estimated = True
        if not ok:
            return None, f"{name}: no EKF origin (ORGN) and no GNSS fix to place it; onboard solution dropped"
        note = f"{name}: the log has no EKF origin (ORGN); it was fitted to the GNSS track"
    return (
        NavSolution(
            name=f"{name}[0]" if name != "EKF1" else name,
            origin=origin,
            t=t,
            position=pos,
            velocity=vel,
            quaternion=q_enu,
            position_std=np.full_like(pos, np.nan),
            origin_estimated=estimated,
        ),
        note,
    )


def _fit_origin(
    t: np.ndarray, pos_enu: np.ndarray, gnss: GnssFixes
) -> tuple[tuple[float, float, float], bool]:
    """An ENU origin that makes ``pos_enu`` agree with the GNSS track on average (median)."""
    good = gnss.subset(gnss.fix >= 3)
    if len(good) == 0 or len(t) == 0:
        return (float("nan"), float("nan"), float("nan")), False
    ref = (float(good.lat[0]), float(good.lon[0]), float(good.alt[0]))
    g_enu = geo.geodetic_to_enu(good.lat, good.lon, good.alt, ref)
    inside = (good.t >= t[0]) & (good.t <= t[-1])
    if not np.any(inside):
        return (float("nan"), float("nan"), float("nan")), False
    e_at = np.column_stack([np.interp(good.t[inside], t, pos_enu[:, k]) for k in range(3)])
    offset = np.median(g_enu[inside] - e_at, axis=0)
    llh = geo.enu_to_geodetic(offset[None, :], ref)[0]
    return (float(llh[0]), float(llh[1]), float(llh[2])), True


# ---------------------------------------------------------------------------------------------
# PX4 ULog


def _ulog_trailing_bytes(path: Path) -> int:
    """Bytes after the last whole ULog message (0 for a complete file)."""
    data = path.read_bytes()
    off = 16
    n = len(data)
    unpack = struct.Struct("<H").unpack_from
    while off + 3 <= n:
        (size,) = unpack(data, off)
        end = off + 3 + size
        if end > n:
            return n - off
        off = end
    return n - off


_Topics = dict[str, dict[str, np.ndarray]]
_Seconds = Callable[[dict[str, np.ndarray]], np.ndarray]


def _ulog_vec(data: dict[str, np.ndarray], base: str, n: int = 3) -> np.ndarray:
    """(N, n) float64 of the array fields ``base[0]`` ... ``base[n-1]``."""
    return np.column_stack([data[f"{base}[{k}]"].astype(np.float64) for k in range(n)])


def _ulog_quat(data: dict[str, np.ndarray]) -> np.ndarray:
    """(N, 4) quaternions (x, y, z, w) of a topic's ``q`` field (PX4 logs it scalar first)."""
    return wxyz_to_xyzw(_ulog_vec(data, "q", 4))


def _open_ulog(path: Path) -> Any:
    pyulog = _import("pyulog")
    try:
        return pyulog.ULog(str(path))
    except Exception as exc:
        raise DatasetError(f"{path}: not a readable ULog ({type(exc).__name__}: {exc})") from None


def _ulog_warnings(path: Path, ulog: Any) -> tuple[list[str], bool]:
    """Reading problems, one line each, and whether the file ends inside a message."""
    warn_list: list[str] = []
    trailing = _ulog_trailing_bytes(path)
    if trailing > 0:
        warn_list.append(f"log ends inside a record: the last {trailing} bytes were ignored")
    if getattr(ulog, "file_corruption", False):
        warn_list.append("pyulog found corrupt data in the file; corrupt messages were skipped")
    return warn_list, trailing > 0


def _ulog_topics(ulog: Any) -> tuple[_Topics, Counter[str]]:
    """The first instance of every topic, and the number of samples per topic (all instances)."""
    topics: _Topics = {}
    counts: Counter[str] = Counter()
    for d in ulog.data_list:
        counts[d.name] += len(d.data["timestamp"])
        if d.multi_id == 0 and d.name not in topics:
            topics[d.name] = d.data
    return topics, counts


def _ulog_imu_mag(topics: _Topics, tsec: _Seconds) -> tuple[ImuSeries, MagSeries]:
    imu = ImuSeries.empty()
    if "sensor_combined" in topics:
        sc = topics["sensor_combined"]
        imu = ImuSeries(tsec(sc), _ulog_vec(sc, "gyro_rad"), _ulog_vec(sc, "accelerometer_m_s2"))
    mag = MagSeries.empty()
    if "vehicle_magnetometer" in topics:
        vm = topics["vehicle_magnetometer"]
        mag = MagSeries(tsec(vm), _ulog_vec(vm, "magnetometer_ga"))
    elif "sensor_combined" in topics and "magnetometer_ga[0]" in topics["sensor_combined"]:
        sc = topics["sensor_combined"]
        mag = MagSeries(tsec(sc), _ulog_vec(sc, "magnetometer_ga"))
    return imu, mag


def _ulog_solutions(topics: _Topics, tsec: _Seconds) -> tuple[NavSolution | None, NavSolution | None]:
    """The onboard estimate (``vehicle_local_position``) and the simulator's ground truth."""
    q_att = None
    if "vehicle_attitude" in topics:
        va = topics["vehicle_attitude"]
        q_att = (tsec(va), _ulog_quat(va))
    onboard = _ulog_local_position(
        topics.get("vehicle_local_position"), tsec, q_att, "vehicle_local_position"
    )
    truth = None
    if "vehicle_local_position_groundtruth" in topics:
        q_gt = None
        if "vehicle_attitude_groundtruth" in topics:
            vag = topics["vehicle_attitude_groundtruth"]
            q_gt = (tsec(vag), _ulog_quat(vag))
        truth = _ulog_local_position(
            topics["vehicle_local_position_groundtruth"], tsec, q_gt, "vehicle_local_position_groundtruth"
        )
    return onboard, truth


def _ulog_modes(topics: _Topics, tsec: _Seconds) -> tuple[ModeChange, ...]:
    """A mode change wherever ``vehicle_status.nav_state`` changes."""
    if "vehicle_status" not in topics:
        return ()
    vs = topics["vehicle_status"]
    nav = vs["nav_state"].astype(np.int64)
    tt = np.maximum(tsec(vs), 0.0)
    return tuple(
        ModeChange(float(tt[k]), PX4_NAV_STATES.get(int(nav[k]), f"NAV_{int(nav[k])}"), int(nav[k]))
        for k in range(len(nav))
        if k == 0 or nav[k] != nav[k - 1]
    )


def _ulog_info(ulog: Any) -> tuple[str, dict[str, float], list[str]]:
    """The vehicle's description, its parameters (last logged value of each) and the names of
    parameters left out because their value is not a number."""
    info = ulog.msg_info_dict
    vehicle = " ".join(str(info[k]) for k in ("sys_name", "ver_hw", "ver_sw_release") if k in info)
    params: dict[str, float] = {}
    changes = [(k, v) for k, v in ulog.initial_parameters.items()]
    changes += [(key, value) for _, key, value in ulog.changed_parameters]
    for key, value in changes:
        number = _param_number(value)
        if number is not None:
            params[str(key)] = number
    skipped = sorted({str(k) for k, v in changes if _param_number(v) is None})
    return vehicle, params, skipped


def _param_number(value: object) -> float | None:
    """A parameter's value as a number; None for one that is not (raw bytes, text)."""
    if isinstance(value, bool | np.bool_):
        return float(value)
    if isinstance(value, int | float | np.integer | np.floating):
        return float(value)
    return None


def _read_ulog(path: Path) -> FlightLog:
    try:
        return _decode_ulog(path)
    except StableCuesError:
        raise
    except _RECORD_ERRORS as exc:
        raise DatasetError(
            f"{path}: a ULog message holds a value its format does not allow ({reason(exc)})"
        ) from None


def _decode_ulog(path: Path) -> FlightLog:
    ulog = _open_ulog(path)
    warn_list, truncated = _ulog_warnings(path, ulog)
    topics, counts = _ulog_topics(ulog)
    if not topics:
        raise DatasetError(f"{path}: not a usable ULog: no logged data (only a header and definitions)")
    # pyulog's convention (and the MANIFEST's): the log starts at the header's timestamp; a few
    # topics carry samples stamped before it (negative times here).
    t0_us = int(ulog.start_timestamp)
    last = int(ulog.last_timestamp)

    def tsec(data: dict[str, np.ndarray]) -> np.ndarray:
        return (data["timestamp"].astype(np.int64) - t0_us) * 1e-6

    gnss, utc_offset = _ulog_gnss(topics, tsec)
    imu, mag = _ulog_imu_mag(topics, tsec)
    attitude = AttitudeSeries.empty()
    if "vehicle_attitude" in topics:
        va = topics["vehicle_attitude"]
        attitude = AttitudeSeries(tsec(va), geo.map_known(quat_to_euler_zyx, _ulog_quat(va), 3))
    onboard, truth = _ulog_solutions(topics, tsec)
    vehicle, params, skipped = _ulog_info(ulog)
    if skipped:
        names = ", ".join(skipped[:3])
        warn_list.append(f"{len(skipped)} parameters that are not numbers were left out ({names})")
    return FlightLog(
        path=path,
        kind="px4",
        vehicle=vehicle,
        duration=float((last - t0_us) * 1e-6),
        boot_time_offset=t0_us * 1e-6,
        utc_offset=utc_offset,
        counts=dict(counts),
        params=params,
        gnss=gnss,
        baro=_ulog_baro(topics, tsec),
        imu=imu,
        mag=mag,
        attitude=attitude,
        onboard=onboard,
        ground_truth=truth,
        mode_changes=_ulog_modes(topics, tsec),
        truncated=truncated,
        warnings=tuple(warn_list),
    )


def _ulog_gnss(
    topics: dict[str, dict[str, np.ndarray]], tsec: Callable[[dict[str, np.ndarray]], np.ndarray]
) -> tuple[GnssFixes, float]:
    name = next((n for n in ("vehicle_gps_position", "sensor_gps") if n in topics), None)
    if name is None:
        return GnssFixes.empty(), float("nan")
    g = topics[name]
    if "latitude_deg" in g:
        lat, lon, alt = (g["latitude_deg"].astype(np.float64), g["longitude_deg"].astype(np.float64),
                         g["altitude_msl_m"].astype(np.float64))  # fmt: skip
    else:
        lat, lon, alt = g["lat"] * 1e-7, g["lon"] * 1e-7, g["alt"] * 1e-3
    n = len(lat)
    vel = np.column_stack([g[k].astype(np.float64) for k in ("vel_n_m_s", "vel_e_m_s", "vel_d_m_s")])
    if "vel_ned_valid" in g:
        vel[g["vel_ned_valid"] == 0] = np.nan
    t = tsec(g)
    fixes = GnssFixes(
        t=t,
        lat=np.asarray(lat, dtype=np.float64),
        lon=np.asarray(lon, dtype=np.float64),
        alt=np.asarray(alt, dtype=np.float64),
        fix=g["fix_type"].astype(np.int16),
        n_sats=g["satellites_used"].astype(np.int16) if "satellites_used" in g else np.full(n, -1, np.int16),
        vel_ned=vel,
        h_acc=g["eph"].astype(np.float64) if "eph" in g else np.full(n, np.nan),
        v_acc=g["epv"].astype(np.float64) if "epv" in g else np.full(n, np.nan),
        s_acc=g["s_variance_m_s"].astype(np.float64) if "s_variance_m_s" in g else np.full(n, np.nan),
    )
    utc = g.get("time_utc_usec")
    ok = (utc is not None) and np.any(utc > 0)
    utc_offset = (
        float(np.median(utc[utc > 0] * 1e-6 - t[utc > 0])) if ok and utc is not None else float("nan")
    )
    return fixes, utc_offset


def _ulog_baro(
    topics: dict[str, dict[str, np.ndarray]], tsec: Callable[[dict[str, np.ndarray]], np.ndarray]
) -> BaroSeries:
    if "vehicle_air_data" in topics:
        a = topics["vehicle_air_data"]
        press = (
            a["baro_pressure_pa"].astype(np.float64)
            if "baro_pressure_pa" in a
            else np.full(len(a["timestamp"]), np.nan)
        )
        return BaroSeries(tsec(a), a["baro_alt_meter"].astype(np.float64), press)
    if "sensor_baro" in topics:
        b = topics["sensor_baro"]
        press = b["pressure"].astype(np.float64)
        if np.nanmedian(press) < 2000.0:  # older PX4 logged millibar
            press = press * 100.0
        alt = (
            b["altitude"].astype(np.float64)
            if "altitude" in b
            else 44330.0 * (1.0 - (press / 101325.0) ** (1 / 5.255))
        )
        return BaroSeries(tsec(b), alt, press)
    if "sensor_combined" in topics and "baro_alt_meter" in topics["sensor_combined"]:
        sc = topics["sensor_combined"]
        return BaroSeries(
            tsec(sc), sc["baro_alt_meter"].astype(np.float64), np.full(len(sc["timestamp"]), np.nan)
        )
    return BaroSeries.empty()


def _ulog_local_position(
    lp: dict[str, np.ndarray] | None,
    tsec: Callable[[dict[str, np.ndarray]], np.ndarray],
    q_att: tuple[np.ndarray, np.ndarray] | None,
    name: str,
) -> NavSolution | None:
    if lp is None or len(lp["timestamp"]) == 0:
        return None
    ref_ok = np.ones(len(lp["timestamp"]), dtype=bool)
    if "xy_global" in lp:
        ref_ok = lp["xy_global"].astype(bool)
    if not np.any(ref_ok):
        return None
    k = int(np.flatnonzero(ref_ok)[-1])
    origin = (float(lp["ref_lat"][k]), float(lp["ref_lon"][k]), float(lp["ref_alt"][k]))
    keep = ref_ok & (np.abs(lp["ref_lat"] - origin[0]) < 1e-9) & (np.abs(lp["ref_lon"] - origin[1]) < 1e-9)
    t = tsec(lp)[keep]
    ned = np.column_stack([lp[c][keep].astype(np.float64) for c in ("x", "y", "z")])
    vned = np.column_stack([lp[c][keep].astype(np.float64) for c in ("vx", "vy", "vz")])
    quat = np.full((len(t), 4), np.nan)
    if q_att is not None and len(q_att[0]) > 0:
        tq, q = q_att
        inside = (t >= tq[0]) & (t <= tq[-1])
        order = np.argsort(tq, kind="stable")
        quat[inside] = geo.ned_to_enu_quat(geo.slerp_known(tq[order], q[order], t[inside]))
    return NavSolution(
        name=name,
        origin=origin,
        t=t,
        position=ned @ geo.R_ENU_NED.T,
        velocity=vned @ geo.R_ENU_NED.T,
        quaternion=quat,
        position_std=np.full((len(t), 3), np.nan),
    )


# ---------------------------------------------------------------------------------------------
# CSV GNSS track

_LAT_NAMES = {"lat", "latitude", "latitude_deg", "lat_deg"}
_LON_NAMES = {"lon", "lng", "longitude", "longitude_deg", "lon_deg"}
_ALT_NAMES = ("alt_msl", "altitude_msl_m", "alt", "altitude", "height", "alt_m", "altitude_m")
_TIME_NAMES = ("timestamp", "time_us", "time_usec", "timestamp_us", "time", "t", "time_s", "stamp")
_UTC_NAMES = ("utc_usec", "time_utc_usec", "utc", "utc_time", "datetime", "gps_time")


def _read_gnss_csv(path: Path) -> FlightLog:
    header, body = read_csv_table(path, "GNSS track")
    ilat = find_column(header, tuple(sorted(_LAT_NAMES)))
    ilon = find_column(header, tuple(sorted(_LON_NAMES)))
    ialt = find_column(header, _ALT_NAMES)
    itime = find_column(header, _TIME_NAMES)
    iutc = find_column(header, _UTC_NAMES)
    if ilat is None or ilon is None:
        raise DatasetError(f"{path}: GNSS track needs latitude and longitude columns, found {header}")
    main = itime if itime is not None else iutc
    if main is None:
        raise DatasetError(
            f"{path}: GNSS track needs a time column ({', '.join(_TIME_NAMES + _UTC_NAMES)}), found {header}"
        )
    if not body:
        raise DatasetError(f"{path}: GNSS track has a header but no rows")

    def col(i: int) -> list[str]:
        return [r[i] for r in body]

    secs, is_epoch = time_column_seconds(path, header[main], col(main))
    utc_secs: np.ndarray | None = secs if is_epoch else None
    if utc_secs is None and iutc is not None:
        u, u_epoch = time_column_seconds(path, header[iutc], col(iutc))
        utc_secs = u if u_epoch else None
    if not np.isfinite(secs).any():
        raise DatasetError(f"{path}: GNSS track column {header[main]!r} holds no finite time")
    order = np.argsort(secs, kind="stable")
    t0 = float(np.nanmin(secs))
    t = secs[order] - t0
    lat = numbers(path, header[ilat], col(ilat))[order]
    lon = numbers(path, header[ilon], col(ilon))[order]
    alt = numbers(path, header[ialt], col(ialt))[order] if ialt is not None else np.zeros(len(t))
    n = len(t)
    ok = np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt) & np.isfinite(t)
    fixes = GnssFixes(
        t=t[ok], lat=lat[ok], lon=lon[ok], alt=alt[ok],
        fix=np.full(int(ok.sum()), 3, np.int16), n_sats=np.full(int(ok.sum()), -1, np.int16),
        vel_ned=np.full((int(ok.sum()), 3), np.nan), h_acc=np.full(int(ok.sum()), np.nan),
        v_acc=np.full(int(ok.sum()), np.nan), s_acc=np.full(int(ok.sum()), np.nan),
    )  # fmt: skip
    utc_offset = float("nan")
    boot_offset = t0
    if utc_secs is not None:
        diff = utc_secs[order] - t
        utc_offset = float(np.nanmedian(diff))
        if is_epoch:
            boot_offset = float("nan")
    warn_list = [] if ok.all() else [f"{int(n - ok.sum())} rows without a complete position were skipped"]
    return FlightLog(
        path=path,
        kind="gnss_csv",
        vehicle="",
        duration=float(np.nanmax(t)) if n else 0.0,
        boot_time_offset=boot_offset,
        utc_offset=utc_offset,
        counts={"GNSS": int(ok.sum())},
        params={},
        gnss=fixes,
        baro=BaroSeries.empty(),
        imu=ImuSeries.empty(),
        mag=MagSeries.empty(),
        attitude=AttitudeSeries.empty(),
        onboard=None,
        ground_truth=None,
        mode_changes=(),
        truncated=False,
        warnings=tuple(warn_list),
    )


def iter_logs(folder: str | Path) -> Iterable[Path]:
    """Flight-log files (.bin, .BIN, .log, .ulg) under ``folder``, sorted."""
    root = Path(folder)
    return sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in (".bin", ".ulg", ".log"))
