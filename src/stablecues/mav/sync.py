"""Camera frames on a flight log's clock: a pose per frame, TUM files, loop ground truth.

A recording is a folder of images plus their capture times, paired with a flight log:

* capture times from a CSV (``--times``; a time column and, optionally, an image-name column and
  geotags ``lat``/``lon``/``alt``), from ``times.txt`` (one time per image), from an EuRoC
  ``data.csv`` beside the image folder, or from image names that are timestamps;
* stereo folders ``left/`` + ``right/`` (also ``images/`` + ``right/``, ``image_0/`` + ``image_1/``,
  ``cam0/data`` + ``cam1/data``) are recognised; a plain image folder is the left camera;
* the frames' clock is mapped to the log's (seconds since log start): UNIX times through the
  log's GNSS time, boot times through the autopilot's boot clock, plus a clock offset that is
  given, or estimated from the frames' geotags against the GNSS track;
* a pose per frame is interpolated from a navigation solution (this package's EKF, the
  autopilot's own, or the GNSS track alone) and written in TUM format
  (``t x y z qx qy qz qw``, camera-to-world, ENU metres about the first GNSS fix);
* loop ground truth from those poses uses :func:`stablecues.groundtruth.loops_from_poses`
  (the project's convention: (N, N) bool, ``gt[i, j]`` for query ``i`` and earlier frame ``j``).
"""

from __future__ import annotations

import logging
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from ..errors import DatasetError, InputError, check_array
from . import geo
from .flightlog import FlightLog, NavSolution
from .tables import find_column, numbers, read_csv_table, time_column_seconds

logger = logging.getLogger(__name__)

Clock = Literal["auto", "utc", "boot", "log"]
PoseSource = Literal["auto", "ekf", "onboard", "gnss"]
Mount = Literal["body", "forward", "nadir"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff")

# Camera axes (optical: x right, y down, z forward) as columns in the body frame (FRD).
MOUNTS: dict[str, np.ndarray] = {
    "body": np.eye(3),
    "forward": np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
    "nadir": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}

_STEREO_LAYOUTS = (
    ("left", "right"),
    ("images", "right"),
    ("image_0", "image_1"),
    ("cam0/data", "cam1/data"),
    ("mav0/cam0/data", "mav0/cam1/data"),
)
_NAME_COLUMNS = ("image", "filename", "file", "name", "image_name", "frame", "path", "img")
_TIME_COLUMNS = (
    "utc_usec", "time_utc_usec", "utc", "timestamp [ns]", "timestamp_ns", "timestamp_us", "timestamp",
    "time", "t", "stamp", "time_s", "capture_time",
)  # fmt: skip


@dataclass(frozen=True, eq=False)
class FrameSet:
    """Camera frames of a recording, in capture order.

    Attributes:
        paths: left (or only) image files; may not exist when only a times CSV was given.
        right: right image files, same order, or None.
        times: (N,) float64 capture times in seconds, in the frames' own clock.
        is_utc: True when ``times`` are UNIX (UTC) seconds.
        geotags: (N, 3) float64 latitude, longitude, altitude per frame, or None (altitude NaN
            when the CSV has none).
        source: where the times came from, for messages.
    """

    paths: tuple[Path, ...]
    right: tuple[Path, ...] | None
    times: np.ndarray
    is_utc: bool
    geotags: np.ndarray | None
    source: str

    def __len__(self) -> int:
        return len(self.paths)


def _natural_key(name: str) -> list[object]:
    return [int(s) if s.isdigit() else s.lower() for s in re.split(r"(\d+)", name)]


def _list_images(folder: Path) -> list[Path]:
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files, key=lambda p: _natural_key(p.name))


def _image_dirs(root: Path) -> tuple[Path, Path | None]:
    for left, right in _STEREO_LAYOUTS:
        if (root / left).is_dir():
            r = root / right
            return root / left, (r if r.is_dir() else None)
    return root, None


def read_frames(
    frames_dir: str | Path | None,
    times_csv: str | Path | None = None,
    *,
    time_column: str | None = None,
) -> FrameSet:
    """Find a recording's images and their capture times.

    Args:
        frames_dir: the image folder (or a recording folder with a stereo layout); None to take
            the frames from ``times_csv`` alone (its name column, relative to the CSV's folder).
        times_csv: CSV of capture times. Without it: ``times.txt`` (seconds, one per image),
            an EuRoC ``data.csv`` next to the image folder, or numeric image names.
        time_column: the CSV's time column; default: the first of utc_usec, time_utc_usec, utc,
            timestamp [ns], timestamp_ns, timestamp_us, timestamp, time, t, stamp, time_s.

    Returns:
        The frames sorted by capture time.

    Raises:
        DatasetError: no images, no capture times, or times that do not match the images.
    """
    root = Path(frames_dir) if frames_dir is not None else None
    left_dir: Path | None = None
    right_dir: Path | None = None
    images: list[Path] = []
    if root is not None:
        if not root.is_dir():
            raise DatasetError(f"{root}: frames folder not found")
        left_dir, right_dir = _image_dirs(root)
        images = _list_images(left_dir)
        if not images:
            raise DatasetError(f"{left_dir}: expected image files ({', '.join(IMAGE_SUFFIXES)}), found none")

    geotags: np.ndarray | None = None
    if times_csv is not None:
        csv_path = Path(times_csv)
        paths, times, is_utc, geotags = _times_from_csv(csv_path, images, time_column)
        source = str(csv_path)
    elif root is not None and left_dir is not None:
        paths, times, is_utc, source = _times_without_csv(root, left_dir, images)
    else:
        raise DatasetError("frames need an image folder, a times CSV, or both")

    order = np.argsort(times, kind="stable")
    paths = [paths[k] for k in order]
    times = times[order]
    if geotags is not None:
        geotags = geotags[order]
    right: tuple[Path, ...] | None = None
    if right_dir is not None:
        by_stem = {p.stem: p for p in _list_images(right_dir)}
        missing = [p.name for p in paths if p.stem not in by_stem]
        if missing:
            raise DatasetError(f"{right_dir}: expected a right image for {missing[0]}, found none")
        right = tuple(by_stem[p.stem] for p in paths)
    return FrameSet(tuple(paths), right, times, is_utc, geotags, source)


def _times_from_csv(
    path: Path, images: list[Path], time_column: str | None
) -> tuple[list[Path], np.ndarray, bool, np.ndarray | None]:
    header, body = read_csv_table(path, "frame times CSV")
    lower = [h.lower() for h in header]
    if time_column is not None:
        if time_column.lower() not in lower:
            raise DatasetError(f"{path}: no column {time_column!r}; the header has {header}")
        itime: int | None = lower.index(time_column.lower())
    else:
        itime = find_column(header, _TIME_COLUMNS)
    if itime is None:
        raise DatasetError(f"{path}: expected a time column ({', '.join(_TIME_COLUMNS)}), found {header}")
    if not body:
        raise DatasetError(f"{path}: frame times CSV has a header but no rows")
    times, is_utc = time_column_seconds(path, header[itime], [r[itime] for r in body])
    iname = find_column(header, _NAME_COLUMNS)
    ilat = find_column(header, ("lat", "latitude", "latitude_deg"))
    ilon = find_column(header, ("lon", "lng", "longitude", "longitude_deg"))
    ialt = find_column(header, ("alt_msl", "alt", "altitude", "altitude_msl_m", "height"))
    tags: np.ndarray | None = None
    if ilat is not None and ilon is not None:
        lat = numbers(path, header[ilat], [r[ilat] for r in body])
        lon = numbers(path, header[ilon], [r[ilon] for r in body])
        alt = (
            numbers(path, header[ialt], [r[ialt] for r in body])
            if ialt is not None
            else np.full(len(body), np.nan)
        )
        tags = np.column_stack([lat, lon, alt])

    if images:
        if iname is not None:
            by_name = {Path(r[iname]).name: k for k, r in enumerate(body)}
            by_stem = {Path(r[iname]).stem: k for k, r in enumerate(body)}
            rows = []
            for img in images:
                k = by_name.get(img.name, by_stem.get(img.stem))
                if k is None:
                    raise DatasetError(f"{path}: no row for image {img.name} (column {header[iname]!r})")
                rows.append(k)
            idx = np.array(rows, dtype=np.int64)
            return images, times[idx], is_utc, (tags[idx] if tags is not None else None)
        if len(body) != len(images):
            raise DatasetError(
                f"{path}: {len(body)} time rows for {len(images)} images, no image-name column"
            )
        return images, times, is_utc, tags
    if iname is None:
        raise DatasetError(
            f"{path}: without a frames folder the CSV needs an image-name column ({_NAME_COLUMNS})"
        )
    paths = [path.parent / r[iname] for r in body]
    return paths, times, is_utc, tags


def _times_without_csv(
    root: Path, left_dir: Path, images: list[Path]
) -> tuple[list[Path], np.ndarray, bool, str]:
    for cand in (root / "times.txt", left_dir / "times.txt", left_dir.parent / "times.txt"):
        if cand.is_file():
            vals = [
                ln.split()[0] for ln in cand.read_text().splitlines() if ln.strip() and not ln.startswith("#")
            ]
            if len(vals) != len(images):
                raise DatasetError(f"{cand}: {len(vals)} times for {len(images)} images")
            t, is_utc = time_column_seconds(cand, "time_s", vals)
            return images, t, is_utc, str(cand)
    euroc = left_dir.parent / "data.csv"
    if left_dir.name == "data" and euroc.is_file():
        header, body = read_csv_table(euroc, "EuRoC camera list")
        by_name = {r[1]: r[0] for r in body if len(r) >= 2}
        missing = [p.name for p in images if p.name not in by_name]
        if missing:
            raise DatasetError(f"{euroc}: no row for image {missing[0]}")
        t, is_utc = time_column_seconds(
            euroc, header[0] or "timestamp [ns]", [by_name[p.name] for p in images]
        )
        return images, t, is_utc, str(euroc)
    stems = [p.stem for p in images]
    if all(re.fullmatch(r"\d+(\.\d+)?", s) for s in stems):
        t, is_utc = time_column_seconds(left_dir, "name", stems)
        return images, t, is_utc, f"{left_dir} (image names)"
    raise DatasetError(
        f"{root}: no capture times: expected a times CSV, times.txt, EuRoC data.csv or numeric names"
    )


def frame_log_times(
    frames: FrameSet, log: FlightLog, *, clock: Clock = "auto", offset: float = 0.0
) -> np.ndarray:
    """The frames' capture times on the log's clock (seconds since log start).

    Args:
        frames: the frames.
        log: the flight log.
        clock: what the frame times are: "utc" (UNIX seconds, mapped through the log's GNSS
            time), "boot" (the autopilot's boot clock), "log" (already seconds since log start),
            or "auto" (UNIX when they look like it, else boot).
        offset: seconds added after the mapping (a known camera clock error).

    Returns:
        (N,) float64.

    Raises:
        DatasetError: UTC frame times but a log without GNSS time, or a boot-clock mapping
            for a log that has none.
    """
    if clock == "auto":
        clock = "utc" if frames.is_utc else "boot"
    if clock == "utc":
        if not np.isfinite(log.utc_offset):
            raise DatasetError(f"{log.path}: frame times are UTC but the log has no GNSS time to map them")
        base = frames.times - log.utc_offset
    elif clock == "boot":
        if not np.isfinite(log.boot_time_offset):
            raise DatasetError(f"{log.path}: frame times are on the boot clock but the log has no boot clock")
        base = frames.times - log.boot_time_offset
    elif clock == "log":
        base = frames.times.copy()
    else:
        raise InputError(f"clock: expected auto, utc, boot or log, got {clock!r}")
    return np.asarray(base + float(offset), dtype=np.float64)


def gnss_solution(log: FlightLog, *, min_fix: int = 3) -> NavSolution:
    """The GNSS track as a navigation solution (ENU about the first fix).

    Attitude comes from the log's own attitude estimate when it has one (NaN otherwise);
    velocity from the receiver (NaN when not reported).

    Raises:
        InputError: no fix of at least ``min_fix``.
    """
    g = log.gnss
    ok = (g.fix >= min_fix) & np.isfinite(g.lat) & np.isfinite(g.lon) & np.isfinite(g.alt)
    if not np.any(ok):
        raise InputError(f"{log.path}: no GNSS fix of type >= {min_fix}")
    g = g.subset(ok)
    order = np.argsort(g.t, kind="stable")
    g = g.subset(order)
    origin = (float(g.lat[0]), float(g.lon[0]), float(g.alt[0]))
    pos = geo.geodetic_to_enu(g.lat, g.lon, g.alt, origin)
    quat = np.full((len(g), 4), np.nan)
    att = log.attitude
    if len(att) >= 2:
        inside = (g.t >= att.t[0]) & (g.t <= att.t[-1])
        q_ned = geo.euler_to_quat(att.rpy[:, 0], att.rpy[:, 1], att.rpy[:, 2])
        quat[inside] = geo.ned_to_enu_quat(geo.quat_slerp(att.t, q_ned, g.t[inside]))
    return NavSolution("gnss", origin, g.t, pos, g.vel_ned @ geo.R_ENU_NED.T, quat, np.full_like(pos, np.nan))


def log_solution(
    log: FlightLog, source: PoseSource = "auto", ekf_config: object | None = None
) -> NavSolution:
    """The navigation solution poses are taken from.

    Args:
        log: the flight log.
        source: "ekf" (:func:`stablecues.mav.ekf.run_ekf`), "onboard" (the autopilot's EKF),
            "gnss" (:func:`gnss_solution`), or "auto": ekf when the log has IMU and GNSS, else
            onboard when present, else gnss.
        ekf_config: an :class:`~stablecues.mav.ekf.EkfConfig` for the "ekf" source.

    Raises:
        InputError: the chosen source is not available in this log.
    """
    from .ekf import EkfConfig, run_ekf

    if source == "auto":
        has_fix = bool(np.any(log.gnss.fix >= 3))
        source = (
            "ekf" if len(log.imu) >= 2 and has_fix else ("onboard" if log.onboard is not None else "gnss")
        )
    if source == "ekf":
        cfg = ekf_config if isinstance(ekf_config, EkfConfig) else None
        solution, _ = run_ekf(log, cfg)
        return solution
    if source == "onboard":
        if log.onboard is None:
            raise InputError(f"{log.path}: the log has no onboard navigation solution")
        return log.onboard
    if source == "gnss":
        return gnss_solution(log)
    raise InputError(f"source: expected auto, ekf, onboard or gnss, got {source!r}")


def estimate_clock_offset(
    log_times: np.ndarray,
    geotags: np.ndarray,
    track: NavSolution,
    *,
    search_s: float = 30.0,
    step_s: float = 0.05,
) -> tuple[float, float]:
    """Clock offset that best places geotagged frames on a track.

    Searches ``offset`` in ``[-search_s, search_s]`` minimising the RMS horizontal distance between
    each frame's geotag and the track at ``log_times + offset`` (grid of ``step_s``, then a
    parabolic refinement). Frames whose shifted time leaves the track are ignored for that offset.

    Args:
        log_times: (N,) frame times on the log's clock, s.
        geotags: (N, 3) latitude, longitude, altitude (altitude unused).
        track: the solution to match against (GNSS track or EKF).

    Returns:
        (offset in seconds to add to ``log_times``, RMS horizontal residual in metres).

    Raises:
        InputError: fewer than 2 finite geotags, or no offset with enough overlap.
    """
    log_times = np.asarray(log_times, dtype=np.float64)
    geotags = np.asarray(geotags, dtype=np.float64)
    check_array("geotags", geotags, shape=(len(log_times), 3))
    ok = np.isfinite(geotags[:, :2]).all(axis=1) & np.isfinite(log_times)
    if ok.sum() < 2:
        raise InputError("estimating a clock offset needs at least 2 geotagged frames")
    tag_enu = geo.geodetic_to_enu(geotags[ok, 0], geotags[ok, 1], np.zeros(int(ok.sum())), track.origin)[
        :, :2
    ]
    ft = log_times[ok]
    need = max(2, int(0.5 * ok.sum()))

    def cost(off: float) -> float:
        tt = ft + off
        inside = (tt >= track.t[0]) & (tt <= track.t[-1])
        if inside.sum() < need:
            return np.inf
        e = np.interp(tt[inside], track.t, track.position[:, 0]) - tag_enu[inside, 0]
        n = np.interp(tt[inside], track.t, track.position[:, 1]) - tag_enu[inside, 1]
        return float(np.mean(e * e + n * n))

    grid = np.arange(-search_s, search_s + 0.5 * step_s, step_s)
    costs = np.array([cost(float(o)) for o in grid])
    if not np.any(np.isfinite(costs)):
        raise InputError("no clock offset within the search range overlaps frames and track")
    k = int(np.nanargmin(costs))
    best = float(grid[k])
    if 0 < k < len(grid) - 1 and np.all(np.isfinite(costs[k - 1 : k + 2])):
        c0, c1, c2 = costs[k - 1], costs[k], costs[k + 1]
        denom = c0 - 2 * c1 + c2
        if denom > 0:
            best += 0.5 * step_s * (c0 - c2) / denom
    return best, float(np.sqrt(cost(best)))


@dataclass(frozen=True, eq=False)
class FramePoses:
    """A pose per camera frame.

    Attributes:
        names: image file names.
        frame_times: (N,) float64 capture times in the frames' clock (s).
        log_times: (N,) float64 the same on the log's clock (s since log start), offset included.
        positions: (N, 3) float64 camera positions, ENU metres about ``origin``; NaN outside the
            solution's span.
        quaternions: (N, 4) float64 camera-to-world (w, x, y, z); NaN outside the span.
        valid: (N,) bool frames inside the solution's span.
        origin: (lat, lon, alt) of the ENU frame.
        source: the solution's name.
        offset: clock offset applied, s.
        has_attitude: False when the solution had no attitude (level, north-facing body assumed).
        mount: camera mounting ("body", "forward", "nadir").
    """

    names: tuple[str, ...]
    frame_times: np.ndarray
    log_times: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    valid: np.ndarray
    origin: tuple[float, float, float]
    source: str
    offset: float
    has_attitude: bool
    mount: str

    @property
    def yaws(self) -> np.ndarray:
        """(N,) heading of each camera pose: ZYX yaw of its rotation in the ENU frame, radians."""
        return yaw_of(self.quaternions)


def yaw_of(quaternions: np.ndarray) -> np.ndarray:
    """ZYX yaw (rotation about the world vertical) of (N, 4) (w, x, y, z) rotations, radians.

    A rotation of the vehicle about the vertical by ``a`` adds ``a`` to this yaw whatever the
    camera mounting, so yaw differences compare headings.
    """
    r = geo.quat_to_matrix(np.asarray(quaternions, dtype=np.float64))
    return np.arctan2(r[..., 1, 0], r[..., 0, 0])


def poses_for_frames(
    frames: FrameSet,
    log: FlightLog,
    solution: NavSolution,
    *,
    clock: Clock = "auto",
    offset: float | Literal["estimate"] = 0.0,
    mount: Mount = "body",
) -> FramePoses:
    """Interpolate a pose for every frame.

    Args:
        frames: the recording's frames.
        log: the flight log (for its clocks).
        solution: the navigation solution (see :func:`log_solution`).
        clock: the frames' clock (see :func:`frame_log_times`).
        offset: seconds added to the mapped frame times, or "estimate" to fit it from the
            frames' geotags against the log's GNSS track (:func:`estimate_clock_offset`).
        mount: camera mounting on the body: "body" (camera frame = body FRD), "forward"
            (optical frame looking forward), "nadir" (optical frame looking down, image top
            towards the nose).

    Raises:
        DatasetError / InputError: clock mapping impossible, unknown mount, or "estimate"
            without geotags.
    """
    if mount not in MOUNTS:
        raise InputError(f"mount: expected one of {sorted(MOUNTS)}, got {mount!r}")
    t_log = frame_log_times(frames, log, clock=clock, offset=0.0)
    if isinstance(offset, str):
        if offset != "estimate":
            raise InputError(f"offset: expected seconds or 'estimate', got {offset!r}")
        if frames.geotags is None:
            raise InputError("offset 'estimate' needs geotagged frames (lat/lon columns in the times CSV)")
        off, rms = estimate_clock_offset(t_log, frames.geotags, gnss_solution(log))
        logger.info("estimated clock offset %.3f s (geotag residual %.2f m RMS)", off, rms)
    else:
        off = float(offset)
    t_log = t_log + off
    at = solution.interpolate(t_log)
    valid = np.isfinite(at.position).all(axis=1)
    has_att = bool(solution.has_attitude)
    quat = at.quaternion.copy()
    if not has_att:
        level_north = geo.matrix_to_quat(geo.R_ENU_NED)
        quat[valid] = level_north
    q_mount = geo.matrix_to_quat(MOUNTS[mount])
    quat = np.where(
        valid[:, None],
        geo.quat_normalize(geo.quat_multiply(quat, np.broadcast_to(q_mount, quat.shape))),
        np.nan,
    )
    if not valid.all():
        logger.warning(
            "%d of %d frames fall outside the %s solution (%.1f-%.1f s); they get no pose",
            int((~valid).sum()),
            len(valid),
            solution.name,
            solution.t[0] if len(solution) else float("nan"),
            solution.t[-1] if len(solution) else float("nan"),
        )
    return FramePoses(
        names=tuple(p.name for p in frames.paths),
        frame_times=frames.times.copy(),
        log_times=t_log,
        positions=at.position,
        quaternions=quat,
        valid=valid,
        origin=solution.origin,
        source=solution.name,
        offset=off,
        has_attitude=has_att,
        mount=mount,
    )


def resample_solution(solution: NavSolution, rate_hz: float) -> NavSolution:
    """The solution at a regular rate over its span (for poses without camera frames).

    Raises:
        InputError: non-positive rate.
    """
    if not rate_hz > 0:
        raise InputError(f"rate_hz: expected > 0, got {rate_hz}")
    if len(solution) == 0:
        return solution
    t = np.arange(solution.t[0], solution.t[-1] + 1e-9, 1.0 / rate_hz)
    return solution.interpolate(t)


# ---------------------------------------------------------------------------------------------
# TUM files


def write_tum(
    path: str | Path,
    times: np.ndarray,
    positions: np.ndarray,
    quaternions: np.ndarray,
    *,
    comments: tuple[str, ...] = (),
) -> int:
    """Write a TUM trajectory ``t x y z qx qy qz qw`` (one line per finite pose).

    Args:
        path: output file.
        times: (N,) float64 seconds.
        positions: (N, 3) float64.
        quaternions: (N, 4) float64 (w, x, y, z); written as qx qy qz qw.
        comments: lines written first, each prefixed with ``# ``.

    Returns:
        The number of poses written (rows with a NaN are skipped).
    """
    times = np.asarray(times, dtype=np.float64)
    positions = np.asarray(positions, dtype=np.float64)
    quaternions = np.asarray(quaternions, dtype=np.float64)
    n = len(times)
    check_array("positions", positions, shape=(n, 3))
    check_array("quaternions", quaternions, shape=(n, 4))
    ok = np.isfinite(times) & np.isfinite(positions).all(axis=1) & np.isfinite(quaternions).all(axis=1)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    lines = [f"# {c}" for c in comments]
    for k in np.flatnonzero(ok):
        w, x, y, z = quaternions[k]
        px, py, pz = positions[k]
        lines.append(f"{times[k]:.6f} {px:.4f} {py:.4f} {pz:.4f} {x:.7f} {y:.7f} {z:.7f} {w:.7f}")
    out.write_text("\n".join(lines) + "\n")
    return int(ok.sum())


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a TUM trajectory file.

    Returns:
        times (N,) float64, positions (N, 3) float64, quaternions (N, 4) float64 (w, x, y, z).

    Raises:
        DatasetError: missing file or a line that is not 8 numbers.
    """
    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"{p}: TUM poses file not found")
    rows = []
    for k, line in enumerate(p.read_text().splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise DatasetError(
                f"{p}: TUM poses need 8 numbers per line (t x y z qx qy qz qw), line {k} has {len(parts)}"
            )
        try:
            rows.append([float(v) for v in parts])
        except ValueError:
            raise DatasetError(f"{p}: line {k}: expected numbers, found {s!r}") from None
    arr = np.array(rows, dtype=np.float64).reshape(-1, 8)
    quats = np.column_stack([arr[:, 7], arr[:, 4:7]])
    return arr[:, 0], arr[:, 1:4], quats


# ---------------------------------------------------------------------------------------------
# Loop ground truth and the image-folder dataset


def loops_from_trajectory(
    positions: np.ndarray,
    *,
    max_distance: float = 10.0,
    quaternions: np.ndarray | None = None,
    max_angle_deg: float | None = None,
    times: np.ndarray | None = None,
    min_gap_s: float = 0.0,
    min_gap_frames: int = 0,
) -> np.ndarray:
    """Loop ground truth from poses, in the project's convention.

    Wraps :func:`stablecues.groundtruth.loops_from_poses`, taking the headings from
    the pose quaternions (:func:`yaw_of`) when an angle threshold is given.

    Args:
        positions: (N, 3) float positions, metres.
        max_distance: metres.
        quaternions: (N, 4) (w, x, y, z) orientations; needed with ``max_angle_deg``.
        max_angle_deg: largest heading difference of a loop, degrees, or None.
        times: (N,) seconds, for ``min_gap_s``.
        min_gap_s: smallest time between the two frames of a loop.
        min_gap_frames: smallest index difference.

    Returns:
        (N, N) bool, ``gt[i, j]`` True when frame ``i`` revisits the earlier frame ``j``.

    Raises:
        InputError: inconsistent options or shapes.
    """
    from ..groundtruth import loops_from_poses

    yaws = None
    if max_angle_deg is not None:
        if quaternions is None:
            raise InputError("max_angle_deg needs the pose orientations (quaternions)")
        yaws = yaw_of(quaternions)
    return loops_from_poses(
        np.asarray(positions, dtype=np.float64),
        max_distance=max_distance,
        yaws=yaws,
        max_angle_deg=max_angle_deg,
        times=times,
        min_gap_s=min_gap_s,
        min_gap_frames=min_gap_frames,
    )


def write_image_folder(
    out_dir: str | Path,
    frames: FrameSet,
    poses: FramePoses,
    *,
    loops: np.ndarray | None = None,
    calibration: str | Path | None = None,
) -> Path:
    """Write the project's image-folder dataset for the frames that have a pose.

    Layout: ``images/`` (copies, named ``{index:06d}_{original name}`` so the natural name order is
    the capture order), ``right/`` when stereo, ``times.txt`` (frame times in seconds, the frames'
    clock), ``poses.txt`` (TUM, camera-to-world), ``loops.npy`` when ``loops`` is given
    (indexed like the written frames), and ``calib.yaml`` copied from ``calibration`` (an
    ORB-SLAM style settings file) when given.

    Returns:
        The dataset folder.

    Raises:
        InputError: ``loops`` not (M, M) bool for the M frames with a pose.
    """
    out = Path(out_dir)
    keep = np.flatnonzero(poses.valid)
    m = len(keep)
    if loops is not None:
        check_array("loops", loops, dtype=bool, shape=(m, m))
    (out / "images").mkdir(parents=True, exist_ok=True)
    if frames.right is not None:
        (out / "right").mkdir(parents=True, exist_ok=True)
    for new, k in enumerate(keep):
        name = f"{new:06d}_{frames.paths[k].name}"
        if not frames.paths[k].is_file():
            raise DatasetError(f"{frames.paths[k]}: image not found")
        shutil.copy2(frames.paths[k], out / "images" / name)
        if frames.right is not None:
            shutil.copy2(frames.right[k], out / "right" / name)
    (out / "times.txt").write_text("".join(f"{t:.6f}\n" for t in poses.frame_times[keep]))
    write_tum(out / "poses.txt", poses.frame_times[keep], poses.positions[keep], poses.quaternions[keep])
    if loops is not None:
        np.save(out / "loops.npy", loops)
    if calibration is not None:
        calib = Path(calibration)
        if not calib.is_file():
            raise DatasetError(f"{calib}: calibration file not found")
        shutil.copy2(calib, out / "calib.yaml")
    return out


def tum_comments(poses: FramePoses) -> tuple[str, ...]:
    """Header comment lines describing a poses file."""
    lat, lon, alt = poses.origin
    return (
        "stablecues mav poses: t x y z qx qy qz qw, camera-to-world",
        f"world: ENU metres about lat={lat:.8f} lon={lon:.8f} alt={alt:.3f} m; source: {poses.source}",
        f"camera mount: {poses.mount}; clock offset {poses.offset:.3f} s"
        + ("" if poses.has_attitude else "; no attitude in the source: level, north-facing body assumed"),
    )
