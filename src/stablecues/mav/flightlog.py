"""One time-indexed structure for a drone flight, whatever log format it came from.

Every series has its own time axis ``t``: (N,) float64 seconds since the first record of the
log (the log's start is 0). :class:`FlightLog` also keeps how that clock maps to the
autopilot's boot clock and, when the GNSS reported time, to UTC, so that camera frames
stamped in either clock can be placed on it (:mod:`stablecues.mav.clock`).

Units: degrees for latitude/longitude, metres, metres per second, radians, radians per second,
gauss for the magnetic field. Vectors in the body frame are Forward-Right-Down (FRD); vectors in
the world frame of a :class:`NavSolution` are East-North-Up (see :mod:`stablecues.mav.geo`).
Quaternions are (x, y, z, w), scalar last (:mod:`stablecues.geometry.rotations`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..geometry.rotations import matrix_to_quat, quat_slerp, quat_to_euler_zyx
from . import geo


def _empty(*shape: int) -> np.ndarray:
    return np.zeros((0, *shape), dtype=np.float64)


@dataclass(frozen=True, eq=False)
class GnssFixes:
    """GNSS receiver solutions.

    Attributes:
        t: (N,) float64 seconds since log start.
        lat, lon: (N,) float64 degrees (WGS84).
        alt: (N,) float64 metres above mean sea level.
        fix: (N,) int16 fix type: 0 no GPS, 1 no fix, 2 2D, 3 3D, 4 DGPS, 5 RTK float, 6 RTK fixed.
        n_sats: (N,) int16 satellites used, -1 when unknown.
        vel_ned: (N, 3) float64 north, east, down velocity in m/s, NaN when not reported.
        h_acc, v_acc: (N,) float64 reported 1-sigma horizontal / vertical accuracy in m, NaN if none.
        s_acc: (N,) float64 reported 1-sigma speed accuracy in m/s, NaN when not reported.
    """

    t: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    alt: np.ndarray
    fix: np.ndarray
    n_sats: np.ndarray
    vel_ned: np.ndarray
    h_acc: np.ndarray
    v_acc: np.ndarray
    s_acc: np.ndarray

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @classmethod
    def empty(cls) -> GnssFixes:
        return cls(
            _empty(), _empty(), _empty(), _empty(), np.zeros(0, np.int16), np.zeros(0, np.int16),
            _empty(3), _empty(), _empty(), _empty(),
        )  # fmt: skip

    def subset(self, keep: np.ndarray) -> GnssFixes:
        """The fixes selected by a boolean mask or index array."""
        return GnssFixes(**{f.name: getattr(self, f.name)[keep] for f in dataclasses.fields(self)})


@dataclass(frozen=True, eq=False)
class BaroSeries:
    """Barometric altitude.

    Attributes:
        t: (N,) float64 seconds since log start.
        alt: (N,) float64 barometric altitude in metres; its zero is the autopilot's own
            reference (ArduPilot: ground level at arming; PX4: standard atmosphere), so only
            its changes are meaningful.
        pressure: (N,) float64 static pressure in Pa, NaN when not logged.
    """

    t: np.ndarray
    alt: np.ndarray
    pressure: np.ndarray

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @classmethod
    def empty(cls) -> BaroSeries:
        return cls(_empty(), _empty(), _empty())


@dataclass(frozen=True, eq=False)
class ImuSeries:
    """Inertial samples in the body frame (FRD).

    Attributes:
        t: (N,) float64 seconds since log start.
        gyro: (N, 3) float64 angular rate, rad/s.
        accel: (N, 3) float64 specific force, m/s^2 (about (0, 0, -9.81) when level and still).
    """

    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @classmethod
    def empty(cls) -> ImuSeries:
        return cls(_empty(), _empty(3), _empty(3))


@dataclass(frozen=True, eq=False)
class MagSeries:
    """Magnetometer samples in the body frame (FRD), calibration applied by the autopilot.

    Attributes:
        t: (N,) float64 seconds since log start.
        field: (N, 3) float64 magnetic field in gauss.
    """

    t: np.ndarray
    field: np.ndarray

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @classmethod
    def empty(cls) -> MagSeries:
        return cls(_empty(), _empty(3))


@dataclass(frozen=True, eq=False)
class AttitudeSeries:
    """The autopilot's attitude estimate.

    Attributes:
        t: (N,) float64 seconds since log start.
        rpy: (N, 3) float64 roll, pitch, yaw in radians (aerospace ZYX, body FRD to NED).
    """

    t: np.ndarray
    rpy: np.ndarray

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @classmethod
    def empty(cls) -> AttitudeSeries:
        return cls(_empty(), _empty(3))


@dataclass(frozen=True, eq=False)
class NavSolution:
    """A navigation solution: position, velocity and attitude over time in local ENU.

    Used both for the autopilot's own EKF output and for :func:`stablecues.mav.ekf.run_ekf`.

    Attributes:
        name: where it comes from ("XKF1[0]", "vehicle_local_position", "stablecues-ekf", ...).
        origin: (lat deg, lon deg, alt m MSL) of the ENU origin.
        t: (N,) float64 seconds since log start.
        position: (N, 3) float64 east, north, up metres about ``origin``.
        velocity: (N, 3) float64 east, north, up m/s; NaN when unknown.
        quaternion: (N, 4) float64 body(FRD)->ENU unit quaternions (x, y, z, w), scalar last;
            NaN rows where the attitude is unknown.
        position_std: (N, 3) float64 1-sigma of ``position`` in m, NaN when unknown.
        origin_estimated: True when the log did not name the origin and it was fitted to GNSS.
    """

    name: str
    origin: tuple[float, float, float]
    t: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    quaternion: np.ndarray
    position_std: np.ndarray = field(default_factory=lambda: _empty(3))
    origin_estimated: bool = False

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def rpy(self) -> np.ndarray:
        """(N, 3) float64 roll, pitch, yaw in radians (body FRD relative to NED); NaN rows where
        the attitude is unknown."""
        if len(self) == 0:
            return _empty(3)
        return geo.map_known(quat_to_euler_zyx, geo.enu_to_ned_quat(self.quaternion), 3)

    @property
    def has_attitude(self) -> bool:
        return len(self) > 0 and bool(np.all(np.isfinite(self.quaternion)))

    def geodetic(self) -> np.ndarray:
        """(N, 3) float64 latitude deg, longitude deg, altitude m MSL of every position."""
        if len(self) == 0:
            return _empty(3)
        return geo.enu_to_geodetic(self.position, self.origin)

    def reframed(self, origin: tuple[float, float, float]) -> NavSolution:
        """The same solution expressed about another ENU origin.

        Positions are converted exactly through geodetic coordinates; velocities and attitude are
        rotated by the (small) change of the local vertical between the two origins.
        """
        origin = (float(origin[0]), float(origin[1]), float(origin[2]))
        if origin == tuple(self.origin) or len(self) == 0:
            return dataclasses.replace(self, origin=origin)
        llh = self.geodetic()
        pos = geo.geodetic_to_enu(llh[:, 0], llh[:, 1], llh[:, 2], origin)
        rot = _enu_rotation(self.origin, origin)
        vel = self.velocity @ rot.T
        quat = geo.rotate_known(matrix_to_quat(rot), self.quaternion)
        return dataclasses.replace(
            self,
            origin=origin,
            position=pos,
            velocity=vel,
            quaternion=quat,
        )

    def interpolate(self, times: np.ndarray, *, max_gap: float = 2.0) -> NavSolution:
        """The solution at ``times`` (s since log start): linear in position and velocity, slerp
        in attitude. Times outside the solution's span, or inside a gap between two samples longer
        than ``max_gap`` seconds (logging paused), give NaN rows.

        Args:
            times: (M,) float64 seconds since log start.
            max_gap: longest interval between samples that is interpolated across, seconds.
        """
        times = np.asarray(times, dtype=np.float64).reshape(-1)
        m = len(times)
        pos = np.full((m, 3), np.nan)
        vel = np.full((m, 3), np.nan)
        quat = np.full((m, 4), np.nan)
        std = np.full((m, 3), np.nan)
        if len(self) > 0:
            inside = (times >= self.t[0]) & (times <= self.t[-1])
            if len(self) > 1:
                seg = np.clip(np.searchsorted(self.t, times, side="right") - 1, 0, len(self) - 2)
                exact = np.isin(times, self.t)
                inside &= (self.t[seg + 1] - self.t[seg] <= max_gap) | exact
            ti = times[inside]
            for k in range(3):
                pos[inside, k] = np.interp(ti, self.t, self.position[:, k])
                vel[inside, k] = np.interp(ti, self.t, self.velocity[:, k])
                if len(self.position_std) == len(self):
                    std[inside, k] = np.interp(ti, self.t, self.position_std[:, k])
            if self.has_attitude:
                quat[inside] = quat_slerp(self.t, self.quaternion, ti)
        return NavSolution(self.name, self.origin, times, pos, vel, quat, std, self.origin_estimated)


def _enu_rotation(src: tuple[float, float, float], dst: tuple[float, float, float]) -> np.ndarray:
    """3x3 rotation taking ENU vectors at ``src`` to ENU vectors at ``dst``."""

    def ecef_from_enu(lat: float, lon: float) -> np.ndarray:
        la, lo = np.radians(lat), np.radians(lon)
        return np.array(
            [
                [-np.sin(lo), -np.sin(la) * np.cos(lo), np.cos(la) * np.cos(lo)],
                [np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la) * np.sin(lo)],
                [0.0, np.cos(la), np.sin(la)],
            ]
        )

    return ecef_from_enu(dst[0], dst[1]).T @ ecef_from_enu(src[0], src[1])


@dataclass(frozen=True)
class ModeChange:
    """A flight-mode record of the log.

    Attributes:
        t: seconds since log start (0 for records logged before the first timestamp).
        name: the mode's name as the autopilot calls it ("LOITER", "AUTO_RTL", ...).
        number: the autopilot's mode number (ArduPilot custom mode, PX4 nav_state).
    """

    t: float
    name: str
    number: int


@dataclass(frozen=True)
class ModeSpan:
    """A time interval flown in one flight mode: ``[start, end)`` seconds since log start."""

    name: str
    number: int
    start: float
    end: float


def mode_spans(changes: tuple[ModeChange, ...] | list[ModeChange], end: float) -> tuple[ModeSpan, ...]:
    """Merge mode records into spans: a record repeating the current mode continues its span.

    Args:
        changes: mode records in time order.
        end: end of the last span (the log's duration).

    Returns:
        Spans in time order; empty when there is no record.
    """
    spans: list[ModeSpan] = []
    for ch in changes:
        if spans and spans[-1].name == ch.name:
            continue
        if spans:
            spans[-1] = dataclasses.replace(spans[-1], end=max(ch.t, spans[-1].start))
        spans.append(ModeSpan(ch.name, ch.number, ch.t, end))
    if spans:
        spans[-1] = dataclasses.replace(spans[-1], end=max(end, spans[-1].start))
    return tuple(spans)


@dataclass(frozen=True, eq=False)
class FlightLog:
    """Everything :func:`stablecues.mav.logs.read_log` extracts from one flight log.

    Attributes:
        path: the log file.
        kind: "ardupilot" (dataflash .bin / .log), "px4" (ULog) or "gnss_csv".
        vehicle: firmware / vehicle description found in the log ("" when none).
        duration: seconds from the first to the last record.
        boot_time_offset: autopilot boot-clock seconds at log time 0 (boot = t + offset).
        utc_offset: UNIX seconds at log time 0 (UTC = t + offset) from the GNSS time, NaN if unknown.
        counts: number of records per message / topic name (all instances).
        params: autopilot parameters (last logged value of each).
        gnss, baro, imu, mag, attitude: sensor series of the first instance (may be empty).
        onboard: the autopilot's own navigation solution (EKF), or None.
        ground_truth: simulator ground truth when the log has it (PX4 SITL), or None.
        mode_changes: every flight-mode record in time order.
        truncated: the file ended inside a record (what came before it was read).
        warnings: what went wrong while reading, one line each.
    """

    path: Path
    kind: str
    vehicle: str
    duration: float
    boot_time_offset: float
    utc_offset: float
    counts: Mapping[str, int]
    params: Mapping[str, float]
    gnss: GnssFixes
    baro: BaroSeries
    imu: ImuSeries
    mag: MagSeries
    attitude: AttitudeSeries
    onboard: NavSolution | None
    ground_truth: NavSolution | None
    mode_changes: tuple[ModeChange, ...]
    truncated: bool = False
    warnings: tuple[str, ...] = ()

    def mode_spans(self) -> tuple[ModeSpan, ...]:
        """Flight-mode spans over the whole log (repeated records of one mode merged)."""
        return mode_spans(self.mode_changes, self.duration)

    def summary(self) -> str:
        """A few lines describing the log, for the CLI."""
        lines = [
            f"{self.path.name}: {self.kind} log, {self.vehicle or 'unknown vehicle'}, {self.duration:.1f} s",
            f"  GNSS {len(self.gnss)} fixes ({int(np.sum(self.gnss.fix >= 3))} 3D or better), "
            f"baro {len(self.baro)}, IMU {len(self.imu)}, mag {len(self.mag)}, attitude {len(self.attitude)}",
            f"  onboard EKF: {self.onboard.name if self.onboard is not None else 'none'}"
            + (f"; ground truth: {self.ground_truth.name}" if self.ground_truth is not None else ""),
        ]
        spans = self.mode_spans()
        if spans:
            lines.append("  modes: " + ", ".join(f"{s.name} {s.start:.1f}-{s.end:.1f} s" for s in spans))
        if self.truncated:
            lines.append("  truncated: read up to the last whole record")
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)
