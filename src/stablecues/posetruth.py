"""Loop ground truth from camera poses: which frames of a sequence revisit an earlier place.

A pair of frames (i, j), j < i, is a loop when all of these hold (:class:`LoopRule`):

* their positions are at most ``max_distance`` apart (the trajectory's unit, metres for TUM,
  EuRoC and KITTI);
* their orientations differ by at most ``max_angle_deg``: the angle of the relative rotation,
  so a place seen facing the other way is no loop (None: any orientation);
* they are at least ``min_gap_s`` seconds (when the frames' times are known; 20 by default) and
  ``min_gap_frames`` frames apart, so that a camera standing still or moving slowly does not
  close loops with itself.

The poses come from a dataset whose frames carry them (TUM's ``groundtruth.txt``, KITTI's poses,
a folder's ``poses.txt``, EuRoC's ground truth), from a trajectory file matched to the frames by
time (TUM ``t x y z qx qy qz qw``, EuRoC ``data.csv``; the nearest pose within ``max_dt``), or
from a trajectory file alone, whose rows are then the frames. A frame without a pose closes no
loop, and the count of such frames is kept with the result.

``stablecues gt poses`` writes such a matrix; ``stablecues eval --gt-poses`` scores a run on one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DatasetError, InputError
from .groundtruth import GroundTruth, loops_from_poses, sha256_file
from .limits import check_loop_frames

__all__ = ["LoopRule", "PoseSource", "frame_poses", "pose_ground_truth"]

DEFAULT_MIN_GAP_S = 20.0
DEFAULT_MAX_DT = 0.02


@dataclass(frozen=True)
class LoopRule:
    """When two frames are a loop (see the module docstring).

    Attributes:
        max_distance: largest distance between the two positions.
        max_angle_deg: largest angle of the relative rotation, degrees; None: any.
        min_gap_s: smallest time between the two frames, seconds; None: 20 s when the frames'
            times are known, else 0.
        min_gap_frames: smallest index difference.
    """

    max_distance: float
    max_angle_deg: float | None = 30.0
    min_gap_s: float | None = None
    min_gap_frames: int = 0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.max_distance) and self.max_distance >= 0):
            raise InputError(f"max distance: expected a finite number >= 0, got {self.max_distance}")
        if self.max_angle_deg is not None and not 0 <= self.max_angle_deg <= 180:
            raise InputError(f"max angle: expected 0..180 degrees, got {self.max_angle_deg}")
        if self.min_gap_s is not None and not (np.isfinite(self.min_gap_s) and self.min_gap_s >= 0):
            raise InputError(f"min gap: expected a finite number of seconds >= 0, got {self.min_gap_s}")
        if self.min_gap_frames < 0:
            raise InputError(f"min gap: expected frames >= 0, got {self.min_gap_frames}")

    def gap_s(self, timed: bool) -> float:
        """The time gap in force: the one given, else 20 s for timed frames, else 0."""
        if self.min_gap_s is not None:
            return self.min_gap_s
        return DEFAULT_MIN_GAP_S if timed else 0.0

    def describe(self, timed: bool) -> str:
        """The rule in one line, as the commands print it."""
        angle = ("any orientation" if self.max_angle_deg is None
                 else f"orientations within {self.max_angle_deg:g} deg")
        gaps = []
        if timed and self.gap_s(timed) > 0:
            gaps.append(f"{self.gap_s(timed):g} s")
        if self.min_gap_frames > 0 or not gaps:
            gaps.append(f"{max(self.min_gap_frames, 1)} frames")
        return (f"positions within {self.max_distance:g} (m), {angle}, at least "
                f"{' and '.join(gaps)} apart")


@dataclass(frozen=True)
class PoseSource:
    """The poses of a sequence's frames and where they came from.

    Attributes:
        poses: (N, 4, 4) float64, NaN rows for frames without a pose.
        times: (N,) float64 seconds (NaN where unknown), or None.
        source: the file (or dataset) the poses were read from.
        file: the pose file itself when there is one (its hash goes with the ground truth).
    """

    poses: np.ndarray
    times: np.ndarray | None
    source: str
    file: Path | None


def read_trajectory(path: Path) -> tuple[np.ndarray | None, np.ndarray]:
    """A TUM or KITTI pose file (:func:`stablecues.trajectory.read_poses`), or EuRoC's
    ``data.csv`` (by its ``.csv`` suffix): (times or None, (M, 4, 4) poses)."""
    from .trajectory import read_euroc, read_poses

    if not path.is_file():
        raise DatasetError(f"{path}: trajectory file not found")
    if path.suffix.lower() == ".csv":
        return read_euroc(path)
    return read_poses(path)


def frame_poses(
    source: str | Path,
    *,
    frame_times: np.ndarray | None = None,
    n_frames: int | None = None,
    trajectory: str | Path | None = None,
    max_dt: float = DEFAULT_MAX_DT,
    every: int = 1,
    dataset_format: str = "auto",
) -> PoseSource:
    """The poses of a sequence's frames.

    Args:
        source: a dataset (folder or ROS bag; its frames' own poses, or ``trajectory``'s matched
            to its frames' times) or a trajectory file (its rows are the frames, or, with
            ``frame_times``, matched to them).
        frame_times: (N,) seconds of the frames when ``source`` is a trajectory file (a run's
            timestamps), or None.
        n_frames: the frames a KITTI pose file (no times) must have one pose each for, or None.
        trajectory: a trajectory file for the frames of the dataset ``source``.
        max_dt: largest time between a frame and the pose it takes, seconds.
        every: keep every ``every``-th frame of a trajectory file read alone (its rows at the
            file's rate: 100 Hz for TUM's mocap).
        dataset_format: the dataset's format ("auto": detected).

    Raises:
        DatasetError: unreadable files, a dataset without poses, or a KITTI file of another
            length than the frames.
        InputError: bad settings.
    """
    if not (np.isfinite(max_dt) and max_dt >= 0):
        raise InputError(f"max dt: expected a finite number of seconds >= 0, got {max_dt}")
    if every < 1:
        raise InputError(f"every: expected >= 1, got {every}")
    src = Path(source)
    if src.is_dir() or src.suffix.lower() in (".bag", ".db3", ".mcap"):
        from .datasets import open_dataset

        ds = open_dataset(src, format=dataset_format)
        times = ds.times
        if trajectory is not None:
            return _matched(Path(trajectory), times, max_dt, f"{trajectory} at the frames of {src}")
        poses = ds.poses
        if poses is None:
            raise DatasetError(f"{src}: its frames carry no poses (a {ds.format} dataset without its "
                               "ground-truth trajectory): give one with --poses FILE")
        pose_file = _pose_file_of(ds)
        return PoseSource(poses, times, str(src), pose_file)
    if trajectory is not None:
        raise InputError(f"{src}: a trajectory file given as the source takes no second trajectory")
    if frame_times is not None:
        return _matched(src, np.asarray(frame_times, np.float64), max_dt, str(src), n_frames)
    times_or_none, poses = read_trajectory(src)
    if every > 1:
        poses = poses[::every]
        times_or_none = None if times_or_none is None else times_or_none[::every]
    return PoseSource(poses, times_or_none, str(src), src)


def _matched(path: Path, frame_times: np.ndarray, max_dt: float, what: str,
             n_frames: int | None = None) -> PoseSource:
    """A trajectory's poses at the frames' times (nearest within ``max_dt``; NaN where none)."""
    from .trajectory import nearest

    ptimes, poses = read_trajectory(path)
    n = frame_times.shape[0] if n_frames is None else n_frames
    if ptimes is None:  # KITTI: one pose per frame, in order
        if poses.shape[0] != n:
            raise DatasetError(f"{path}: {poses.shape[0]} poses without times, but {n} frames: a KITTI "
                               "pose file needs one line per frame")
        return PoseSource(poses, frame_times, what, path)
    if not np.isfinite(frame_times).any():
        raise DatasetError(f"{what}: the frames have no timestamps to match the trajectory's times to")
    idx = nearest(frame_times, ptimes, max_dt)
    out = np.full((frame_times.shape[0], 4, 4), np.nan)
    out[idx >= 0] = poses[idx[idx >= 0]]
    return PoseSource(out, frame_times, what, path)


def _pose_file_of(ds: Any) -> Path | None:
    """The trajectory file a dataset's poses came from, when it names one."""
    value = getattr(ds, "poses_path", None)
    return value if isinstance(value, Path) else None


def pose_ground_truth(source: PoseSource, rule: LoopRule) -> GroundTruth:
    """The loop matrix of ``source``'s frames under ``rule``, as a :class:`GroundTruth` whose
    ``path`` and ``sha256`` are the pose file's and whose notes hold the rule.

    Raises:
        DatasetError: more frames than a loop matrix may have (:mod:`stablecues.limits`).
    """
    poses = source.poses
    n = poses.shape[0]
    check_loop_frames(n, source.source)
    timed = source.times is not None and bool(np.isfinite(source.times).any())
    if not timed and rule.min_gap_frames <= 1 and rule.min_gap_s is None:
        raise InputError(f"{source.source}: the frames have no times, so no 20 s gap keeps a camera from "
                         "closing loops with its own last frames: give --min-gap-frames N (or --min-gap-s "
                         "with timed frames)")
    times = source.times if timed else None
    rotations = poses[:, :3, :3] if rule.max_angle_deg is not None else None
    matrix = loops_from_poses(
        poses[:, :3, 3], max_distance=rule.max_distance, rotations=rotations,
        max_angle_deg=rule.max_angle_deg, times=times, min_gap_s=rule.gap_s(timed),
        min_gap_frames=rule.min_gap_frames,
    )
    missing = int((~np.isfinite(poses[:, :3, 3]).all(axis=1)).sum())
    untimed = 0 if times is None else int((~np.isfinite(times)).sum())  # they close no loop either
    notes = {"from_poses": {"frames_without_time": untimed,
        "source": source.source, "rule": rule.describe(timed), "max_distance": rule.max_distance,
        "max_angle_deg": rule.max_angle_deg, "min_gap_s": rule.gap_s(timed) if timed else None,
        "min_gap_frames": rule.min_gap_frames, "frames_without_pose": missing,
    }}
    file = source.file
    return GroundTruth(matrix, path=file, sha256=sha256_file(file) if file is not None else None, notes=notes)
