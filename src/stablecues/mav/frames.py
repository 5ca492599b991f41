"""A recording's camera frames and their capture times, in the frames' own clock.

A recording is a folder of images plus their capture times:

* capture times from a CSV (a time column and, optionally, an image-name column and geotags
  ``lat``/``lon``/``alt``), from ``times.txt`` (one time in seconds per image), from an EuRoC
  ``data.csv`` beside the image folder, or from image names that are timestamps;
* stereo folders ``left/`` + ``right/`` (also ``images/`` + ``right/``, ``image_0/`` + ``image_1/``,
  ``cam0/data`` + ``cam1/data``) are recognised; a plain image folder is the left camera.

Placing the frames on a flight log's clock is :mod:`stablecues.mav.clock`'s job.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..imageio import list_images, match_by_stem
from ..trajectory import read_times
from .tables import find_column, is_epoch_seconds, numbers, read_csv_table, time_column_seconds

__all__ = ["FrameSet", "read_frames"]

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
        DatasetError: no images, no capture times, or times that do not match the images
            (:class:`~stablecues.errors.ImageError`, a DatasetError, for missing images).
    """
    root = Path(frames_dir) if frames_dir is not None else None
    left_dir: Path | None = None
    right_dir: Path | None = None
    images: list[Path] = []
    if root is not None:
        if not root.is_dir():
            raise DatasetError(f"{root}: frames folder not found")
        left_dir, right_dir = _image_dirs(root)
        images = list_images(left_dir, "frames")

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
    right = tuple(match_by_stem(paths, right_dir, "right")) if right_dir is not None else None
    return FrameSet(tuple(paths), right, times, is_utc, geotags, source)


def _geotags(path: Path, header: list[str], body: list[list[str]]) -> np.ndarray | None:
    """(N, 3) latitude, longitude, altitude (NaN when absent) of a CSV with lat/lon columns."""
    ilat = find_column(header, ("lat", "latitude", "latitude_deg"))
    ilon = find_column(header, ("lon", "lng", "longitude", "longitude_deg"))
    ialt = find_column(header, ("alt_msl", "alt", "altitude", "altitude_msl_m", "height"))
    if ilat is None or ilon is None:
        return None
    lat = numbers(path, header[ilat], [r[ilat] for r in body])
    lon = numbers(path, header[ilon], [r[ilon] for r in body])
    alt = (
        numbers(path, header[ialt], [r[ialt] for r in body])
        if ialt is not None
        else np.full(len(body), np.nan)
    )
    return np.column_stack([lat, lon, alt])


def _time_index(path: Path, header: list[str], time_column: str | None) -> int:
    lower = [h.lower() for h in header]
    if time_column is not None:
        if time_column.lower() not in lower:
            raise DatasetError(f"{path}: no column {time_column!r}; the header has {header}")
        return lower.index(time_column.lower())
    itime = find_column(header, _TIME_COLUMNS)
    if itime is None:
        raise DatasetError(f"{path}: expected a time column ({', '.join(_TIME_COLUMNS)}), found {header}")
    return itime


def _times_from_csv(
    path: Path, images: list[Path], time_column: str | None
) -> tuple[list[Path], np.ndarray, bool, np.ndarray | None]:
    header, body = read_csv_table(path, "frame times CSV")
    itime = _time_index(path, header, time_column)
    if not body:
        raise DatasetError(f"{path}: frame times CSV has a header but no rows")
    times, is_utc = time_column_seconds(path, header[itime], [r[itime] for r in body])
    iname = find_column(header, _NAME_COLUMNS)
    tags = _geotags(path, header, body)
    if not images:
        if iname is None:
            raise DatasetError(
                f"{path}: without a frames folder the CSV needs an image-name column ({_NAME_COLUMNS})"
            )
        return [path.parent / r[iname] for r in body], times, is_utc, tags
    if iname is None:
        if len(body) != len(images):
            raise DatasetError(
                f"{path}: {len(body)} time rows for {len(images)} images, no image-name column"
            )
        return images, times, is_utc, tags
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


def _times_without_csv(
    root: Path, left_dir: Path, images: list[Path]
) -> tuple[list[Path], np.ndarray, bool, str]:
    for cand in (root / "times.txt", left_dir / "times.txt", left_dir.parent / "times.txt"):
        if cand.is_file():
            t = read_times(cand, "frame times (one time in seconds per image)")
            if len(t) != len(images):
                raise DatasetError(f"{cand}: {len(t)} times for {len(images)} images")
            return images, t, is_epoch_seconds(t), str(cand)
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
