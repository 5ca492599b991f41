"""The dataset protocol and the base of the format modules (:class:`~stablecues.types.Frame` is in types).

Every loader lists its files when it is opened (cheap: no image is read) and reads the images
of a frame only when that frame is asked for, so iterating over a long sequence keeps one frame
in memory at a time.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from ..errors import DatasetError
from ..geometry.calibration import load_calibration
from ..geometry.camera import Calibration
from ..imageio import ImageMode, read_depth, read_image, read_labels
from ..types import Frame

if TYPE_CHECKING:
    from ..groundtruth import GroundTruth

__all__ = [
    "Dataset",
    "Frame",
    "FrameRecord",
    "SequenceDataset",
    "attach_poses",
    "attach_times",
    "check_one_per_image",
    "find_first",
    "inside",
    "load_calibration_lazily",
]

logger = logging.getLogger(__name__)


@runtime_checkable
class Dataset(Protocol):
    """A sequence of frames; iterating reads images lazily, one frame at a time."""

    name: str

    def __len__(self) -> int: ...

    def __iter__(self) -> Iterator[Frame]: ...

    def __getitem__(self, index: int) -> Frame: ...

    def ground_truth_path(self) -> Path | None:
        """The loop ground-truth file shipped with the dataset, or None."""
        ...

    @property
    def times(self) -> np.ndarray:
        """(N,) float64 timestamps in seconds, NaN where unknown."""
        ...

    @property
    def poses(self) -> np.ndarray | None:
        """(N, 4, 4) float64 camera-to-world poses (NaN-filled where unknown), or None."""
        ...


@dataclass
class FrameRecord:
    """What a loader knows about one frame before reading it: file paths and metadata."""

    image: Path
    timestamp: float = float("nan")
    right: Path | None = None
    depth: Path | None = None
    labels: Path | None = None
    pose: np.ndarray | None = None
    name: str | None = None
    session: int | None = None  # Frame.session: None, the map's current session


@dataclass
class SequenceDataset:
    """A dataset given by a list of :class:`FrameRecord` s; the base of every format module.

    Attributes:
        root: the dataset folder.
        records: one record per frame, in sequence order.
        name: short name of the dataset (the folder name by default).
        format: the format module's name ("folder", "tum", ...).
        depth_factor: raw depth value per metre (depth in metres = value / depth_factor).
        calibration_path: calibration file found for the dataset, or None.
        gt_path: loop ground-truth file, or None.
        grey: convert images to (H, W) grey on reading (colour kept as BGR otherwise).
        gt_options: keyword arguments of :func:`~stablecues.groundtruth.load_ground_truth`
            that reading ``gt_path`` for this dataset needs (the reference count of a two-pass set).
        calibration_loader: reads ``calibration_path`` when the generic
            ``stablecues.geometry.load_calibration`` would not pick the right cameras (KITTI's
            colour pair); None uses the generic one.
        poses_path: the trajectory file the frames' poses were read from, or None.
    """

    root: Path
    records: list[FrameRecord]
    name: str = ""
    format: str = ""
    depth_factor: float = 1000.0
    calibration_path: Path | None = None
    gt_path: Path | None = None
    grey: bool = False
    gt_options: dict[str, Any] = field(default_factory=dict)
    calibration_loader: Callable[[Path], Calibration] | None = field(default=None, repr=False)
    poses_path: Path | None = None
    _calibration: Calibration | None = field(default=None, init=False, repr=False)
    _calibration_tried: bool = field(default=False, init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.name:
            self.name = self.root.name

    def __len__(self) -> int:
        return len(self.records)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self.records)):
            yield self[i]

    def frame_index(self, index: int) -> int:
        """``index`` as a position in ``records`` (negative counts from the end).

        Raises:
            IndexError: outside the sequence.
        """
        n = len(self.records)
        if not -n <= index < n:
            raise IndexError(f"frame {index} out of range for {n} frames")
        return index % n

    def __getitem__(self, index: int) -> Frame:
        index = self.frame_index(index)
        rec = self.records[index]
        mode: ImageMode = "8bit-grey" if self.grey else "8bit"
        image = read_image(rec.image, mode)
        right = read_image(rec.right, mode) if rec.right is not None else None
        depth = read_depth(rec.depth, self.depth_factor) if rec.depth is not None else None
        labels = read_labels(rec.labels) if rec.labels is not None else None
        return Frame(
            index=index,
            name=rec.name or _relative(rec.image, self.root),
            timestamp=float(rec.timestamp),
            image=image,
            right=right,
            depth=depth,
            labels=labels,
            pose=None if rec.pose is None else rec.pose.copy(),
            calibration=self.calibration,
            calibration_path=self.calibration_path,
            session=rec.session,
        )

    @property
    def names(self) -> list[str]:
        """Name of every frame (its image path relative to the root)."""
        return [rec.name or _relative(rec.image, self.root) for rec in self.records]

    @property
    def times(self) -> np.ndarray:
        """(N,) float64 timestamps in seconds, NaN where unknown."""
        return np.array([rec.timestamp for rec in self.records], dtype=np.float64)

    @property
    def poses(self) -> np.ndarray | None:
        """(N, 4, 4) float64 camera-to-world poses, NaN-filled where unknown; None if no pose."""
        if all(rec.pose is None for rec in self.records):
            return None
        out = np.full((len(self.records), 4, 4), np.nan)
        for i, rec in enumerate(self.records):
            if rec.pose is not None:
                out[i] = rec.pose
        return out

    def ground_truth_path(self) -> Path | None:
        """The loop ground-truth file shipped with the dataset, or None."""
        return self.gt_path

    def ground_truth(self) -> GroundTruth | None:
        """The dataset's loop ground truth in the project convention, or None when it has none.

        Raises:
            DatasetError: the file is malformed or does not have one row per frame.
        """
        if self.gt_path is None:
            return None
        from ..groundtruth import load_ground_truth

        gt = load_ground_truth(self.gt_path, **self.gt_options)
        if gt.n != len(self):
            raise DatasetError(
                f"{self.gt_path}: expected a {len(self)} x {len(self)} loop matrix, found {gt.n}"
            )
        return gt

    @property
    def calibration(self) -> Calibration | None:
        """The loaded calibration (once, on first use), or None; see :attr:`Frame.calibration`."""
        if not self._calibration_tried:
            self._calibration_tried = True
            if self.calibration_loader is not None and self.calibration_path is not None:
                self._calibration = self.calibration_loader(self.calibration_path)
            else:
                self._calibration = load_calibration_lazily(self.calibration_path)
        return self._calibration

    def use_calibration(self, path: str | Path) -> Calibration:
        """Take the calibration from ``path`` (any file :func:`stablecues.geometry.load_calibration`
        reads, or a TUM camera name) instead of the dataset's own; loaded now.

        Raises:
            CalibrationError: a missing or malformed file.
        """
        calib = load_calibration(path)
        self.calibration_path = Path(path)
        self.calibration_loader = None
        self._calibration, self._calibration_tried = calib, True
        return calib

    def describe(self) -> dict[str, Any]:
        """JSON-ready summary for a run's ``meta.json``: dataset, name, format, dataset_frames,
        stereo, depth, labels, poses, calibration and ground_truth (paths or None)."""
        rec0 = self.records[0] if self.records else None
        return {
            "dataset": str(self.root),
            "name": self.name,
            "format": self.format,
            "dataset_frames": len(self),
            "stereo": bool(rec0 and rec0.right is not None),
            "depth": bool(rec0 and rec0.depth is not None),
            "labels": bool(rec0 and rec0.labels is not None),
            "poses": self.poses is not None,
            "calibration": None if self.calibration_path is None else str(self.calibration_path),
            "ground_truth": None if self.gt_path is None else str(self.gt_path),
        }


def load_calibration_lazily(path: Path | None) -> Calibration | None:
    """Load ``path`` with :func:`stablecues.geometry.load_calibration`; None when ``path`` is None.

    Raises:
        CalibrationError: a malformed calibration file.
    """
    return None if path is None else load_calibration(path)


# ----------------------------------------------------------------------------------------------
# file helpers


def _relative(path: Path, root: Path) -> str:
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return path.name


def inside(root: Path, entry: str, manifest: Path, lineno: int) -> Path:
    """The file a manifest line names, ``root / entry``, refused when it is not inside ``root``.

    Datasets name their files relative to their own folder; an absolute path or one that climbs
    out (``../..``) would read files the dataset does not hold.

    Raises:
        DatasetError: naming the manifest and the line.
    """
    rel = Path(entry)
    if rel.is_absolute() or rel.anchor or ".." in rel.parts:
        raise DatasetError(
            f"{manifest}: line {lineno} names {entry[:80]!r}; expected a path inside the dataset folder "
            "(no absolute path, no '..')"
        )
    return root / rel


def find_first(folder: Path, names: Sequence[str]) -> Path | None:
    """The first of ``names`` that exists in ``folder`` (case as given), or None."""
    for n in names:
        p = folder / n
        if p.exists():
            return p
    return None


def check_one_per_image(path: Path, what: str, n_images: int, found: int) -> None:
    """Raise unless a file read from ``path`` gave one ``what`` ("timestamps", "poses") per image.

    Raises:
        DatasetError: ``found`` differs from ``n_images``.
    """
    if found != n_images:
        raise DatasetError(f"{path}: expected {n_images} {what} (one per image), found {found}")


def attach_times(records: Sequence[FrameRecord], path: Path, times: np.ndarray) -> None:
    """Give each record its timestamp from ``times``, read from ``path`` (named in the error).

    Raises:
        DatasetError: ``times`` does not have one entry per record.
    """
    check_one_per_image(path, "timestamps", len(records), times.shape[0])
    for rec, t in zip(records, times, strict=True):
        rec.timestamp = float(t)


def attach_poses(records: Sequence[FrameRecord], path: Path, poses: np.ndarray) -> None:
    """Give each record its (4, 4) pose from ``poses``, read from ``path`` (named in the error).

    Raises:
        DatasetError: ``poses`` does not have one pose per record.
    """
    check_one_per_image(path, "poses", len(records), poses.shape[0])
    for rec, pose in zip(records, poses, strict=True):
        rec.pose = pose
