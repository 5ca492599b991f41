"""The frame type, the dataset protocol, and helpers shared by the format modules.

Every loader lists its files when it is opened (cheap: no image is read) and reads the images
of a frame only when that frame is asked for, so iterating over a long sequence keeps one frame
in memory at a time.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import cv2
import numpy as np

from ..errors import DatasetError

if TYPE_CHECKING:
    from ..evaluation.groundtruth import GroundTruth

logger = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff")


@dataclass(frozen=True, eq=False)
class Frame:
    """One frame of a sequence, as handed to the loop detector.

    Attributes:
        index: position of the frame in its dataset (0, 1, 2, ...); loop ground truth and
            every results file use this index.
        name: the image's path relative to the dataset root (or a label), for reports.
        timestamp: seconds, NaN when unknown.
        image: (H, W) uint8 grey or (H, W, 3) uint8 BGR left (or only) image, as stored.
        right: the right image of a stereo pair, same form, as stored; the calibration says
            whether the pair is rectified. None for monocular data.
        depth: (H, W) float32 depth in metres registered to ``image``, NaN where unknown.
        labels: (H, W) uint8 CamVid class ids (0..11) for ``image``.
        pose: (4, 4) float64 camera-to-world pose of the left camera (ground truth), or None.
        calibration: the object :func:`stablecues.geometry.load_calibration` returns, or None
            when there is no calibration file or the geometry module is not available.
        calibration_path: the calibration file the dataset found (whether or not it could be
            loaded), or None.
        keypoints: (N, 2) float32 keypoints handed in by a SLAM system, or None.
        points3d: (N, 3) float32 3D point per keypoint in the camera frame (NaN unknown), or None.
    """

    index: int
    name: str
    timestamp: float
    image: np.ndarray
    right: np.ndarray | None = None
    depth: np.ndarray | None = None
    labels: np.ndarray | None = None
    pose: np.ndarray | None = None
    calibration: Any | None = None
    calibration_path: Path | None = None
    keypoints: np.ndarray | None = None
    points3d: np.ndarray | None = None


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
        gt_options: keyword arguments of :func:`~stablecues.evaluation.groundtruth.load_ground_truth`
            that reading ``gt_path`` for this dataset needs (the reference count of a two-pass set).
        calibration_loader: reads ``calibration_path`` when the generic
            ``stablecues.geometry.load_calibration`` would not pick the right cameras (KITTI's
            colour pair); None uses the generic one.
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
    calibration_loader: Callable[[Path], Any] | None = field(default=None, repr=False)
    _calibration: Any = field(default=None, init=False, repr=False)
    _calibration_tried: bool = field(default=False, init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.name:
            self.name = self.root.name

    def __len__(self) -> int:
        return len(self.records)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self.records)):
            yield self[i]

    def __getitem__(self, index: int) -> Frame:
        n = len(self.records)
        if not -n <= index < n:
            raise IndexError(f"frame {index} out of range for {n} frames")
        index %= n
        rec = self.records[index]
        image = read_image(rec.image, grey=self.grey)
        right = read_image(rec.right, grey=self.grey) if rec.right is not None else None
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
        from ..evaluation.groundtruth import load_ground_truth

        gt = load_ground_truth(self.gt_path, **self.gt_options)
        if gt.n != len(self):
            raise DatasetError(
                f"{self.gt_path}: expected a {len(self)} x {len(self)} loop matrix, found {gt.n}"
            )
        return gt

    @property
    def calibration(self) -> Any | None:
        """The loaded calibration (once, on first use), or None; see :attr:`Frame.calibration`."""
        if not self._calibration_tried:
            self._calibration_tried = True
            if self.calibration_loader is not None and self.calibration_path is not None:
                self._calibration = self.calibration_loader(self.calibration_path)
            else:
                self._calibration = load_calibration_lazily(self.calibration_path)
        return self._calibration

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


def load_calibration_lazily(path: Path | None) -> Any | None:
    """Load ``path`` with ``stablecues.geometry.load_calibration`` if that exists.

    Returns None when ``path`` is None or the geometry module has no ``load_calibration`` yet;
    errors of the calibration loader itself (a malformed file) propagate.
    """
    if path is None:
        return None
    import importlib

    loader: Callable[[Path], Any] | None = None
    for module_name in ("stablecues.geometry", "stablecues.geometry.calibration"):
        try:
            module = importlib.import_module(module_name)
        except ImportError:
            continue
        loader = getattr(module, "load_calibration", None)
        if loader is not None:
            break
    if loader is None:
        logger.debug("stablecues.geometry.load_calibration not available; keeping %s only", path)
        return None
    return loader(path)


# ----------------------------------------------------------------------------------------------
# file helpers


def natural_key(name: str) -> tuple[Any, ...]:
    """Sort key comparing digit runs as numbers: ``2.png`` before ``10.png``."""
    parts = re.split(r"(\d+)", name)
    return tuple((0, int(p), p) if p.isdigit() else (1, p.lower(), p) for p in parts)


def list_images(folder: Path, what: str = "images") -> list[Path]:
    """Image files directly in ``folder``, in natural name order.

    Raises:
        DatasetError: the folder is missing or holds no image file.
    """
    if not folder.is_dir():
        raise DatasetError(f"{folder}: {what} folder not found")
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    if not files:
        raise DatasetError(f"{folder}: expected image files ({', '.join(IMAGE_SUFFIXES)}), found none")
    return sorted(files, key=lambda p: natural_key(p.name))


def match_by_stem(images: Sequence[Path], folder: Path, what: str) -> list[Path]:
    """The file in ``folder`` with the same stem as each of ``images`` (any image suffix).

    Raises:
        DatasetError: some image has no counterpart in ``folder``.
    """
    by_stem = {p.stem: p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
    out = []
    for img in images:
        other = by_stem.get(img.stem)
        if other is None:
            raise DatasetError(f"{folder}: expected a {what} image named {img.stem}.*, found none")
        out.append(other)
    return out


def read_image(path: Path, *, grey: bool = False) -> np.ndarray:
    """Read an 8-bit image: (H, W) grey or (H, W, 3) BGR uint8 (16-bit files are scaled down).

    Raises:
        DatasetError: missing or unreadable file.
    """
    raw = _imread(path, cv2.IMREAD_UNCHANGED)
    if raw.dtype == np.uint16:
        raw = (raw >> 8).astype(np.uint8)
    elif raw.dtype != np.uint8:
        raise DatasetError(f"{path}: expected an 8-bit image, found dtype {raw.dtype}")
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[:, :, 0]
    elif raw.ndim == 3 and raw.shape[2] == 4:
        raw = cv2.cvtColor(raw, cv2.COLOR_BGRA2BGR)
    if grey and raw.ndim == 3:
        raw = cv2.cvtColor(raw, cv2.COLOR_BGR2GRAY)
    return raw


def read_depth(path: Path, factor: float) -> np.ndarray:
    """Read a depth image: (H, W) float32 metres = value / ``factor``, zeros become NaN.

    Raises:
        DatasetError: missing, unreadable or multi-channel file.
    """
    raw = _imread(path, cv2.IMREAD_UNCHANGED)
    if raw.ndim != 2:
        raise DatasetError(f"{path}: expected a single-channel depth image, found shape {raw.shape}")
    depth = raw.astype(np.float32)
    if np.issubdtype(raw.dtype, np.integer):
        depth /= np.float32(factor)
    depth[(raw == 0) | ~np.isfinite(depth)] = np.nan
    return depth


def read_labels(path: Path) -> np.ndarray:
    """Read a label image: (H, W) uint8 class ids.

    Raises:
        DatasetError: missing file, or not a single-channel 8-bit image.
    """
    raw = _imread(path, cv2.IMREAD_UNCHANGED)
    if raw.ndim != 2 or raw.dtype != np.uint8:
        raise DatasetError(
            f"{path}: expected a single-channel uint8 label image, found shape {raw.shape} {raw.dtype}"
        )
    return raw


def _imread(path: Path, flags: int) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(f"{path}: image file not found")
    data = np.fromfile(str(path), dtype=np.uint8)
    image = cv2.imdecode(data, flags) if data.size else None
    if image is None:
        raise DatasetError(f"{path}: not a readable image (corrupt or unknown format)")
    return image


def _relative(path: Path, root: Path) -> str:
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return path.name


# ----------------------------------------------------------------------------------------------
# text files: timestamps and trajectories


def read_number_rows(path: Path, columns: int | tuple[int, ...], what: str) -> np.ndarray:
    """Read whitespace- or comma-separated numbers, skipping blank and ``#`` lines.

    Args:
        path: the text file.
        columns: the number of numbers each line must have (or the allowed numbers).
        what: what the file is, for messages ("TUM trajectory").

    Returns:
        (M, C) float64 array.

    Raises:
        DatasetError: missing file, a non-numeric value, or a line of the wrong length.
    """
    if not path.is_file():
        raise DatasetError(f"{path}: {what} file not found")
    allowed = (columns,) if isinstance(columns, int) else columns
    rows: list[list[float]] = []
    width: int | None = None
    with path.open("r", encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
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


def quat_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """(M, 4) quaternions (qx, qy, qz, qw) -> (M, 3, 3) rotation matrices (normalised first)."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    norm[norm == 0] = 1.0
    x, y, z, w = (q / norm).T
    r = np.empty((q.shape[0], 3, 3))
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - z * w)
    r[:, 0, 2] = 2 * (x * z + y * w)
    r[:, 1, 0] = 2 * (x * y + z * w)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - x * w)
    r[:, 2, 0] = 2 * (x * z - y * w)
    r[:, 2, 1] = 2 * (y * z + x * w)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def tum_poses(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TUM rows ``t x y z qx qy qz qw`` -> ((M,) times, (M, 4, 4) float64 poses)."""
    poses = np.tile(np.eye(4), (rows.shape[0], 1, 1))
    poses[:, :3, :3] = quat_to_matrix(rows[:, 4:8])
    poses[:, :3, 3] = rows[:, 1:4]
    return rows[:, 0].copy(), poses


def read_tum_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file (``t x y z qx qy qz qw`` per line).

    Returns:
        (M,) float64 times in seconds and (M, 4, 4) float64 poses.

    Raises:
        DatasetError: missing file or malformed line.
    """
    return tum_poses(read_number_rows(path, 8, "TUM trajectory (t x y z qx qy qz qw)"))


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


def find_first(folder: Path, names: Sequence[str]) -> Path | None:
    """The first of ``names`` that exists in ``folder`` (case as given), or None."""
    for n in names:
        p = folder / n
        if p.exists():
            return p
    return None
