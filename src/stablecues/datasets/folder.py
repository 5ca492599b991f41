"""The project's image-folder format, and plain folders of images.

Layout (everything but the images optional)::

    DIR/images/*.png     left (or only) images, sorted by name (digit runs compare as numbers);
                         without ``images/``, ``DIR/frames/`` or ``DIR/color/`` is read the same way
    DIR/right/           rectified right images, same names (any image suffix)
    DIR/depth/           16-bit depth PNG, metres = value / DepthMapFactor (calib.yaml; else 1000)
    DIR/labels/          uint8 PNG of CamVid class ids
    DIR/times.txt        one timestamp in seconds per line, one line per image
    DIR/poses.txt        TUM format ``t x y z qx qy qz qw``, camera-to-world, one line per image
    DIR/calib.yaml       ORB-SLAM settings style (``%YAML:1.0``, Camera.fx, ..., DepthMapFactor)
    DIR/loops.npy        loop ground truth, (N, N) bool lower-triangular (or, beside an
                         ``images/`` or ``frames/`` folder, ``gt.png`` / ``gt.npy``: any matrix
                         :func:`stablecues.groundtruth.load_ground_truth` reads)

A plain folder of images (no ``images/`` or ``frames/`` sub-folder) is read the same way, with
the images directly in ``DIR``.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..fileio import read_text
from ..imageio import list_images, match_by_stem
from ..limits import MAX_CALIBRATION_BYTES
from ..trajectory import read_times, read_tum
from .base import FrameRecord, SequenceDataset, attach_poses, attach_times, find_first

logger = logging.getLogger(__name__)

DEFAULT_DEPTH_FACTOR = 1000.0
#: sub-folders holding the (left) images, the first present one wins; else the images are in DIR
IMAGE_FOLDERS = ("images", "frames", "color")
#: loop ground truth beside an image sub-folder when there is no loops.npy
GT_NAMES = ("gt.npy", "gt.png")


def read_settings_value(path: Path, key: str) -> float | None:
    """A scalar ``key: value`` from an ORB-SLAM / OpenCV settings yaml, or None when absent.

    Raises:
        DatasetError: the file is missing, or the key's value is not a number.
    """
    if not path.is_file():
        raise DatasetError(f"{path}: settings file not found")
    pattern = re.compile(rf"^\s*{re.escape(key)}\s*:\s*(\S+)")
    for line in read_text(path, "settings file", limit=MAX_CALIBRATION_BYTES).splitlines():
        m = pattern.match(line)
        if m:
            try:
                return float(m.group(1))
            except ValueError:
                raise DatasetError(f"{path}: {key} should be a number, found {m.group(1)!r}") from None
    return None


def _no_images(folder: Path) -> None:
    """Raise the error of a folder without images, naming its sub-folders when it has some (a
    folder of datasets, or of a layout the folder format does not know).

    Raises:
        DatasetError: always.
    """
    subs = sorted(p.name for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))
    if subs:
        shown = ", ".join(subs[:6]) + (f", ... ({len(subs)} folders)" if len(subs) > 6 else "")
        raise DatasetError(f"{folder}: no images here, only folders ({shown}): give the dataset's own "
                           "folder, or its format with --format")
    list_images(folder)  # the usual message


def _attach_side_folders(root: Path, images: list[Path], records: list[FrameRecord]) -> None:
    """Attach the right / depth / labels image of the same name to each record, per folder present.

    Raises:
        DatasetError: a side folder lacks the image of some frame.
    """
    for sub, attr in (("right", "right"), ("depth", "depth"), ("labels", "labels")):
        folder = root / sub
        if folder.is_dir():
            for rec, other in zip(records, match_by_stem(images, folder, sub), strict=True):
                setattr(rec, attr, other)


def _attach_tum_poses(records: list[FrameRecord], poses_file: Path) -> None:
    """Attach ``poses.txt`` (TUM format, one line per image); its times fill missing timestamps.

    Raises:
        DatasetError: a malformed file, or not one pose per image.
    """
    ptimes, poses = read_tum(poses_file)
    attach_poses(records, poses_file, poses)
    for rec, t in zip(records, ptimes, strict=True):
        if not np.isfinite(rec.timestamp):
            rec.timestamp = float(t)


def _depth_factor(
    root: Path, calib: Path | None, depth_factor: float | None, records: list[FrameRecord]
) -> float:
    """Raw depth units per metre: the one given, else calib.yaml's DepthMapFactor, else 1000.

    Raises:
        DatasetError: a factor that is not > 0, or a DepthMapFactor that is not a number.
    """
    factor = depth_factor
    if factor is None and calib is not None and calib.suffix in (".yaml", ".yml"):
        factor = read_settings_value(calib, "DepthMapFactor")
    if factor is None:
        factor = DEFAULT_DEPTH_FACTOR
        if records and records[0].depth is not None:
            logger.warning("%s: no DepthMapFactor given; assuming %g depth units per metre", root, factor)
    if not factor > 0 or not math.isfinite(factor):
        raise DatasetError(f"{calib or root}: DepthMapFactor must be > 0, found {factor}")
    return float(factor)


def open_folder(
    path: str | Path,
    *,
    calibration: str | Path | None = None,
    depth_factor: float | None = None,
    grey: bool = False,
) -> SequenceDataset:
    """Open an image folder (project layout or a plain folder of images).

    Args:
        path: the dataset folder.
        calibration: calibration file overriding ``DIR/calib.yaml``.
        depth_factor: raw depth units per metre, overriding calib.yaml's ``DepthMapFactor``.
        grey: read images as (H, W) grey.

    Raises:
        DatasetError: missing folder or images, a side folder lacking an image, or a
            ``times.txt`` / ``poses.txt`` whose line count differs from the image count.
    """
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder not found")
    image_dir = next((root / sub for sub in IMAGE_FOLDERS if (root / sub).is_dir()), root)
    images = list_images(image_dir, allow_empty=True)
    if not images:
        _no_images(image_dir)
    records = [FrameRecord(image=p) for p in images]
    _attach_side_folders(root, images, records)
    times_file = root / "times.txt"
    if times_file.is_file():
        attach_times(records, times_file, read_times(times_file))
    poses_file = root / "poses.txt"
    if poses_file.is_file():
        _attach_tum_poses(records, poses_file)

    calib = Path(calibration) if calibration is not None else find_first(root, ("calib.yaml", "calib.yml"))
    if calib is not None and not calib.is_file():
        raise DatasetError(f"{calib}: calibration file not found")
    factor = _depth_factor(root, calib, depth_factor, records)

    loops = root / "loops.npy"
    if not loops.is_file() and image_dir != root:  # beside the images' folder, a gt.* is no frame
        loops = find_first(root, GT_NAMES) or loops
    return SequenceDataset(
        root=root,
        records=records,
        format="folder",
        depth_factor=factor,
        calibration_path=calib,
        gt_path=loops if loops.is_file() else None,
        grey=grey,
        poses_path=poses_file if poses_file.is_file() else None,
    )
