"""Trajectory and timestamp files: TUM, KITTI, EuRoC and ``times.txt``, read and written here only.

Poses are (M, 4, 4) float64 homogeneous transforms; which frame maps to which is the file's
convention (camera-to-world for TUM and KITTI, body-to-world for EuRoC's ground truth).
Quaternions follow :mod:`stablecues.geometry.rotations`: (x, y, z, w).

=========== =========================================== ===========================
format      one line                                    reader / writer
=========== =========================================== ===========================
TUM         ``t x y z qx qy qz qw``                     :func:`read_tum` / :func:`write_tum`
KITTI       ``r11 r12 r13 tx ... r33 tz`` (3x4 rows)    :func:`read_kitti` / :func:`write_kitti`
EuRoC       ``ns, px, py, pz, qw, qx, qy, qz[, ...]``   :func:`read_euroc` / :func:`write_euroc`
times.txt   ``t`` (seconds)                             :func:`read_times` / :func:`write_times`
=========== =========================================== ===========================

Blank lines and lines starting with ``#`` or ``%`` are skipped; numbers may be separated by
spaces or commas. Every reader raises :class:`~stablecues.errors.DatasetError` naming the file
and the line on a malformed file.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from .errors import DatasetError, InputError, check_array
from .fileio import read_text
from .geometry.rotations import matrix_to_quat, quat_to_matrix, wxyz_to_xyzw, xyzw_to_wxyz

__all__ = [
    "associate",
    "nearest",
    "ns_to_seconds",
    "poses_from_tum_rows",
    "read_euroc",
    "read_kitti",
    "read_number_rows",
    "read_poses",
    "read_times",
    "read_tum",
    "write_euroc",
    "write_kitti",
    "write_times",
    "write_tum",
]


def read_number_rows(path: str | Path, columns: int | tuple[int, ...], what: str) -> np.ndarray:
    """Read whitespace- or comma-separated numbers, skipping blank and ``#`` / ``%`` lines.

    Args:
        path: the text file.
        columns: the number of numbers each line must have (or the allowed numbers); every
            line must have as many as the first.
        what: what the file is, for messages ("TUM trajectory").

    Returns:
        (M, C) float64 array.

    Raises:
        DatasetError: missing file, a file over :data:`stablecues.limits.MAX_TEXT_BYTES` or
            holding binary data, a non-numeric value, or a line of the wrong length.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: {what} file not found")
    allowed = (columns,) if isinstance(columns, int) else columns
    rows: list[list[float]] = []
    width: int | None = None
    # universal newlines, as reading the file line by line does
    for lineno, line in enumerate(io.StringIO(read_text(path, what), newline=None), 1):
        text = line.strip()
        if not text or text.startswith(("#", "%")):
            continue
        parts = text.replace(",", " ").split()
        if len(parts) not in allowed or (width is not None and len(parts) != width):
            want = " or ".join(str(c) for c in allowed) if width is None else str(width)
            raise DatasetError(
                f"{path}: {what} needs {want} numbers per line, line {lineno} has {len(parts)}"
            )
        width = len(parts)
        try:
            rows.append([float(p) for p in parts])
        except ValueError:
            raise DatasetError(f"{path}: {what} line {lineno} is not numeric: {text[:60]!r}") from None
    if not rows:
        return np.zeros((0, allowed[0]), dtype=np.float64)
    return np.asarray(rows, dtype=np.float64)


def _poses(rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    poses = np.tile(np.eye(4), (rotations.shape[0], 1, 1))
    poses[:, :3, :3] = rotations
    poses[:, :3, 3] = translations
    return poses


def _check_poses(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    check_array("poses", poses, shape=(None, 4, 4))
    return poses


def _write_lines(path: str | Path, lines: list[str], comments: tuple[str, ...]) -> None:
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("".join(f"# {c}\n" for c in comments) + "".join(line + "\n" for line in lines))


# ----------------------------------------------------------------------------------------------
# TUM


def poses_from_tum_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TUM rows ``t x y z qx qy qz qw`` -> ((M,) times, (M, 4, 4) float64 poses).

    Raises:
        InputError: a zero quaternion (no rotation).
    """
    if rows.shape[0] == 0:
        return np.zeros(0), np.zeros((0, 4, 4))
    return rows[:, 0].copy(), _poses(quat_to_matrix(rows[:, 4:8]), rows[:, 1:4])


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file (``t x y z qx qy qz qw`` per line).

    Returns:
        (M,) float64 times in seconds and (M, 4, 4) float64 poses.

    Raises:
        DatasetError: missing file, a malformed line or a zero quaternion.
    """
    rows = read_number_rows(path, 8, "TUM trajectory (t x y z qx qy qz qw)")
    try:
        return poses_from_tum_rows(rows)
    except InputError as exc:
        raise DatasetError(f"{path}: TUM trajectory: {exc}") from None


def write_tum(
    path: str | Path, times: np.ndarray, poses: np.ndarray, *, comments: tuple[str, ...] = ()
) -> int:
    """Write a TUM trajectory, one line per pose whose time and pose are finite.

    Args:
        path: output file (folders are created).
        times: (M,) float64 seconds.
        poses: (M, 4, 4) float64 poses.
        comments: lines written first, each prefixed with ``# ``.

    Returns:
        The number of poses written.
    """
    poses = _check_poses(poses)
    times = np.asarray(times, dtype=np.float64)
    check_array("times", times, shape=(poses.shape[0],))
    ok = np.isfinite(times) & np.isfinite(poses).all(axis=(1, 2))
    quats = np.full((poses.shape[0], 4), np.nan)
    if ok.any():
        quats[ok] = matrix_to_quat(poses[ok, :3, :3])
    lines = []
    for k in np.flatnonzero(ok):
        px, py, pz = poses[k, :3, 3]
        x, y, z, w = quats[k]
        lines.append(f"{times[k]:.6f} {px:.4f} {py:.4f} {pz:.4f} {x:.7f} {y:.7f} {z:.7f} {w:.7f}")
    _write_lines(path, lines, comments)
    return int(ok.sum())


# ----------------------------------------------------------------------------------------------
# KITTI


def read_kitti(path: str | Path) -> np.ndarray:
    """Read a KITTI pose file: (M, 4, 4) float64 camera-to-world poses (12 numbers a line).

    Raises:
        DatasetError: missing file or a line without 12 numbers.
    """
    rows = read_number_rows(path, 12, "KITTI poses (3x4 row-major)")
    poses = np.tile(np.eye(4), (rows.shape[0], 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    return poses


def write_kitti(path: str | Path, poses: np.ndarray) -> None:
    """Write (M, 4, 4) poses as a KITTI pose file (the top 3x4 of each, row-major)."""
    poses = _check_poses(poses)
    _write_lines(path, [" ".join(f"{v:.9e}" for v in p[:3].ravel()) for p in poses], ())


def read_poses(path: str | Path) -> tuple[np.ndarray | None, np.ndarray]:
    """Read a TUM (8 numbers a line) or KITTI (12 numbers a line) pose file, whichever it is.

    Returns:
        ((M,) float64 seconds, or None for KITTI poses, which carry no times; (M, 4, 4) float64
        poses).

    Raises:
        DatasetError: as :func:`read_tum` and :func:`read_kitti`, or lines of another length.
    """
    rows = read_number_rows(path, (8, 12), "poses (TUM: t x y z qx qy qz qw, or KITTI: 3x4 row-major)")
    if rows.shape[1] == 12 and rows.shape[0]:
        poses = np.tile(np.eye(4), (rows.shape[0], 1, 1))
        poses[:, :3, :] = rows.reshape(-1, 3, 4)
        return None, poses
    try:
        return poses_from_tum_rows(rows)
    except InputError as exc:
        raise DatasetError(f"{path}: TUM trajectory: {exc}") from None


# ----------------------------------------------------------------------------------------------
# EuRoC


def ns_to_seconds(ns: np.ndarray) -> np.ndarray:
    """Integer nanoseconds -> float64 seconds, exact to the nanosecond near today's epochs."""
    ns = np.asarray(ns, dtype=np.int64)
    return (ns // 1_000_000_000).astype(np.float64) + (ns % 1_000_000_000).astype(np.float64) * 1e-9


def read_euroc(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read EuRoC ground truth (``state_groundtruth_estimate0/data.csv`` or ``vicon0/data.csv``).

    Returns:
        (M,) float64 seconds and (M, 4, 4) float64 body-to-world poses.

    Raises:
        DatasetError: missing file, lines with other than 8 or 17 numbers, a zero quaternion.
    """
    rows = read_number_rows(path, (8, 17), "EuRoC ground truth (ns, p xyz, q wxyz, ...)")
    times = ns_to_seconds(rows[:, 0].astype(np.int64))
    if rows.shape[0] == 0:
        return times, np.zeros((0, 4, 4))
    try:
        rotations = quat_to_matrix(wxyz_to_xyzw(rows[:, 4:8]))
    except InputError as exc:
        raise DatasetError(f"{path}: EuRoC ground truth: {exc}") from None
    return times, _poses(rotations, rows[:, 1:4])


def write_euroc(path: str | Path, times: np.ndarray, poses: np.ndarray) -> None:
    """Write EuRoC-style ground truth: ``#timestamp [ns], p_x, p_y, p_z, q_w, q_x, q_y, q_z``."""
    poses = _check_poses(poses)
    times = np.asarray(times, dtype=np.float64)
    check_array("times", times, shape=(poses.shape[0],))
    q = xyzw_to_wxyz(matrix_to_quat(poses[:, :3, :3])) if poses.shape[0] else np.zeros((0, 4))
    lines = [
        f"{round(t * 1e9)}," + ",".join(f"{v:.9f}" for v in (*p[:3, 3], *qk))
        for t, p, qk in zip(times, poses, q, strict=True)
    ]
    _write_lines(path, ["#timestamp [ns], p_x [m], p_y [m], p_z [m], q_w, q_x, q_y, q_z", *lines], ())


# ----------------------------------------------------------------------------------------------
# times.txt


def read_times(path: str | Path, what: str = "times (one timestamp per line)") -> np.ndarray:
    """Read ``times.txt``: (M,) float64 seconds, one per line.

    Raises:
        DatasetError: missing file or a line that is not one number.
    """
    return read_number_rows(path, 1, what)[:, 0]


def write_times(path: str | Path, times: np.ndarray) -> None:
    """Write (M,) seconds as ``times.txt``, one per line with microsecond precision."""
    _write_lines(path, [f"{t:.6f}" for t in np.asarray(times, dtype=np.float64)], ())


# ----------------------------------------------------------------------------------------------
# associating time stamps


def associate(query_times: np.ndarray, ref_times: np.ndarray, max_difference: float) -> np.ndarray:
    """Match each query time with the nearest reference time, one-to-one, as TUM's associate.py.

    Pairs are taken greedily in order of increasing time difference; each reference is used
    at most once and pairs further apart than ``max_difference`` are dropped.

    Args:
        query_times: (N,) float64 seconds.
        ref_times: (M,) float64 seconds.
        max_difference: largest accepted difference, seconds.

    Returns:
        (N,) int64 index into ``ref_times`` for each query, -1 where none.
    """
    q = np.asarray(query_times, dtype=np.float64)
    r = np.asarray(ref_times, dtype=np.float64)
    out = np.full(q.shape[0], -1, dtype=np.int64)
    if q.size == 0 or r.size == 0:
        return out
    order = np.argsort(r, kind="stable")
    rs = r[order]
    # candidate pairs: for each query, the references within max_difference (sorted window)
    lo = np.searchsorted(rs, q - max_difference, side="left")
    hi = np.searchsorted(rs, q + max_difference, side="right")
    pairs: list[tuple[float, int, int]] = []
    for qi in range(q.size):
        for k in range(lo[qi], hi[qi]):
            pairs.append((abs(rs[k] - q[qi]), qi, int(order[k])))
    pairs.sort()
    used = np.zeros(r.size, dtype=bool)
    for _, qi, ri in pairs:
        if out[qi] < 0 and not used[ri]:
            out[qi] = ri
            used[ri] = True
    return out


def nearest(query_times: np.ndarray, ref_times: np.ndarray, max_difference: float) -> np.ndarray:
    """Index of the nearest reference time for each query (references may repeat); -1 if too far.

    Args:
        query_times: (N,) float64 seconds.
        ref_times: (M,) float64 seconds, any order.
        max_difference: largest accepted difference, seconds.

    Returns:
        (N,) int64 indices into ``ref_times``.
    """
    q = np.asarray(query_times, dtype=np.float64)
    r = np.asarray(ref_times, dtype=np.float64)
    out = np.full(q.shape[0], -1, dtype=np.int64)
    if q.size == 0 or r.size == 0:
        return out
    order = np.argsort(r, kind="stable")
    rs = r[order]
    pos = np.clip(np.searchsorted(rs, q), 1, rs.size - 1) if rs.size > 1 else np.zeros(q.size, int)
    left = np.maximum(pos - 1, 0)
    pick = np.where(np.abs(rs[left] - q) <= np.abs(rs[pos] - q), left, pos)
    ok = np.abs(rs[pick] - q) <= max_difference
    out[ok] = order[pick[ok]]
    return out
