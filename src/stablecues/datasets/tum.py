"""TUM RGB-D sequences.

Layout of a TUM RGB-D sequence (as downloaded)::

    DIR/rgb.txt           "timestamp filename" per line (``#`` comments)
    DIR/rgb/*.png         colour images
    DIR/depth.txt         "timestamp filename" per line (optional)
    DIR/depth/*.png       16-bit depth, metres = value / 5000
    DIR/groundtruth.txt   TUM trajectory ``t x y z qx qy qz qw`` (optional; any
                          ``*groundtruth*.txt`` is taken when it is the only one)

A folder without ``rgb.txt`` whose images are named by their timestamps (``1311868169.163498.png``,
in ``DIR/rgb/`` or ``DIR`` itself) is read too. Depth images are associated with colour images
as TUM's ``associate.py`` does (one-to-one, nearest first, at most ``max_difference`` apart);
ground-truth poses by the nearest ground-truth time within ``max_difference``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..fileio import read_text
from ..imageio import list_images
from ..trajectory import associate, nearest, read_tum
from .base import FrameRecord, SequenceDataset, find_first, inside

TUM_DEPTH_FACTOR = 5000.0
#: an image named by its time in seconds, as TUM's are (1311868169.163498): with a fraction, so
#: that a folder of 1.png, 2.png, ... never gets times made up from its frame numbers
_TIMESTAMP_NAME = re.compile(r"^\d+\.\d+$")
_FREIBURG = re.compile(r"(?:freiburg|fr)([123])(?![0-9])", re.IGNORECASE)
_TUM_CAMERA = re.compile(r"^fr[123]$")


def _read_list(path: Path, root: Path, what: str) -> tuple[np.ndarray, list[Path]]:
    times: list[float] = []
    files: list[Path] = []
    for lineno, line in enumerate(read_text(path, what).splitlines(), 1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        parts = text.split()
        if len(parts) != 2:
            raise DatasetError(
                f"{path}: {what} needs 'timestamp filename' per line, line {lineno} has {len(parts)} fields"
            )
        try:
            times.append(float(parts[0]))
        except ValueError:
            raise DatasetError(f"{path}: line {lineno}: timestamp {parts[0]!r} is not a number") from None
        files.append(inside(root, parts[1], path, lineno))
    if not files:
        raise DatasetError(f"{path}: expected at least one 'timestamp filename' line, found none")
    return np.asarray(times, dtype=np.float64), files


def _find_groundtruth(root: Path) -> Path | None:
    exact = root / "groundtruth.txt"
    if exact.is_file():
        return exact
    found = sorted(p for p in root.glob("*groundtruth*.txt") if p.is_file())
    return found[0] if len(found) == 1 else None


def _colour_images(root: Path) -> tuple[np.ndarray, list[Path]]:
    """The colour images and their times: from ``rgb.txt``, else from images named by timestamp.

    Raises:
        DatasetError: a malformed ``rgb.txt`` or one listing a missing image; without it,
            no images or an image not named by its timestamp.
    """
    rgb_list = root / "rgb.txt"
    if rgb_list.is_file():
        times, images = _read_list(rgb_list, root, "rgb.txt")
        for img in images:
            if not img.is_file():
                raise DatasetError(f"{rgb_list}: lists {img.relative_to(root)}, which is not there")
        return times, images
    image_dir = root / "rgb" if (root / "rgb").is_dir() else root
    images = list_images(image_dir)
    bad = [p.name for p in images if not _TIMESTAMP_NAME.match(p.stem)]
    if bad:
        raise DatasetError(
            f"{root}: expected rgb.txt, or images named by timestamp (like 1311868169.163498.png); "
            f"found {bad[0]!r}"
        )
    times = np.array([float(p.stem) for p in images], dtype=np.float64)
    order = np.argsort(times, kind="stable")
    return times[order], [images[i] for i in order]


def _attach_depth(
    records: list[FrameRecord], times: np.ndarray, depth_list: Path, root: Path, max_difference: float
) -> None:
    """Associate the images of ``depth.txt`` with the frames (at ``times``), as TUM's associate.py."""
    dtimes, dfiles = _read_list(depth_list, root, "depth.txt")
    match = associate(times, dtimes, max_difference)
    for rec, k in zip(records, match, strict=True):
        if k >= 0:
            rec.depth = dfiles[k]


def _attach_groundtruth(
    records: list[FrameRecord], times: np.ndarray, gt_file: Path, max_difference: float
) -> None:
    """Give each frame (at ``times``) the pose of the nearest ground-truth time within ``max_difference``."""
    gtimes, gposes = read_tum(gt_file)
    idx = nearest(times, gtimes, max_difference)
    for rec, k in zip(records, idx, strict=True):
        if k >= 0:
            rec.pose = gposes[k]


def _find_calibration(root: Path, calibration: str | Path | None) -> Path | None:
    """The calibration given, else ``calib.yaml``, else the TUM camera named by the folder.

    Raises:
        DatasetError: a calibration given that is neither a file nor a TUM camera name.
    """
    calib = Path(calibration) if calibration is not None else find_first(root, ("calib.yaml", "calib.yml"))
    if calib is None:
        # TUM ships no calibration file: name the camera ("fr1".."fr3") from the sequence name,
        # which stablecues.geometry.load_calibration understands
        m = _FREIBURG.search(root.name)
        return Path(f"fr{m.group(1)}") if m else None
    if not calib.is_file() and not _TUM_CAMERA.match(str(calib)):
        raise DatasetError(f"{calib}: calibration file not found")
    return calib


def open_tum(
    path: str | Path,
    *,
    max_difference: float = 0.02,
    groundtruth: str | Path | None = None,
    calibration: str | Path | None = None,
    depth_factor: float = TUM_DEPTH_FACTOR,
    grey: bool = False,
) -> SequenceDataset:
    """Open a TUM RGB-D sequence folder.

    Args:
        path: the sequence folder.
        max_difference: largest time difference in seconds when associating depth images and
            ground-truth poses with colour images (TUM's default 0.02 s).
        groundtruth: trajectory file overriding the one found in the folder.
        calibration: calibration file, or a TUM camera name "fr1" / "fr2" / "fr3"; None takes
            ``calib.yaml`` in the folder, else the camera named in the folder's name
            (``rgbd_dataset_freiburg2_desk`` -> "fr2").
        depth_factor: raw depth units per metre (5000 for TUM).
        grey: read images as (H, W) grey.

    Raises:
        DatasetError: missing folder, list or image files, or malformed lines.
    """
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(f"{root}: TUM sequence folder not found")
    times, images = _colour_images(root)
    records = [FrameRecord(image=img, timestamp=float(t)) for img, t in zip(images, times, strict=True)]
    depth_list = root / "depth.txt"
    if depth_list.is_file():
        _attach_depth(records, times, depth_list, root, max_difference)
    gt_file = Path(groundtruth) if groundtruth is not None else _find_groundtruth(root)
    if gt_file is not None:
        _attach_groundtruth(records, times, gt_file, max_difference)
    calib = _find_calibration(root, calibration)
    loops = root / "loops.npy"
    return SequenceDataset(
        root=root,
        records=records,
        format="tum",
        depth_factor=depth_factor,
        calibration_path=calib,
        gt_path=loops if loops.is_file() else None,
        grey=grey,
        poses_path=gt_file,
    )
