"""KITTI odometry sequences.

Layout of one sequence (``dataset/sequences/00``)::

    00/image_0/*.png   left grey images      00/image_2/*.png   left colour images
    00/image_1/*.png   right grey images     00/image_3/*.png   right colour images
    00/calib.txt       "P0: 12 numbers" ... "P3: ...", optional "Tr: ..."
    00/times.txt       one timestamp in seconds per image
    dataset/poses/00.txt   ground truth: 12 numbers per line, 3x4 row-major camera-to-world
                           pose of the left grey camera (also looked for as 00/poses.txt, 00/00.txt)

The stereo pairs are rectified. Poses of the colour cameras are the grey camera's composed with
the (pure translation) offset that ``calib.txt`` gives between the two.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..errors import DatasetError
from ..imageio import list_images, match_by_stem
from ..trajectory import read_kitti, read_times
from .base import FrameRecord, SequenceDataset


def read_kitti_calib(path: Path) -> dict[str, np.ndarray]:
    """Read KITTI ``calib.txt``: ``{"P0": (3, 4), ..., "Tr": (3, 4)}`` float64 matrices.

    Raises:
        DatasetError: missing file, a line without 12 numbers, or no P0.
    """
    if not path.is_file():
        raise DatasetError(f"{path}: KITTI calibration file not found")
    out: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        values = rest.split()
        if not sep or len(values) != 12:
            raise DatasetError(
                f"{path}: expected 'NAME: 12 numbers' per line, line {lineno} has {len(values)}"
            )
        try:
            out[key.strip()] = np.asarray([float(v) for v in values]).reshape(3, 4)
        except ValueError:
            raise DatasetError(f"{path}: line {lineno} is not numeric") from None
    if "P0" not in out:
        raise DatasetError(f"{path}: expected a P0 line, found keys {sorted(out)}")
    return out


def _find_poses(root: Path) -> Path | None:
    for cand in (
        root / "poses.txt",
        root.parent.parent / "poses" / f"{root.name}.txt",
        root / f"{root.name}.txt",
    ):
        if cand.is_file():
            return cand
    return None


def open_kitti(
    path: str | Path,
    *,
    cameras: Literal["auto", "grey", "colour"] = "auto",
    poses: str | Path | None = None,
    stereo: bool = True,
    grey: bool = False,
) -> SequenceDataset:
    """Open a KITTI odometry sequence folder.

    Args:
        path: the sequence folder (holding ``image_0`` / ``image_2``).
        cameras: "grey" (image_0/1), "colour" (image_2/3), or "auto" (grey when present).
        poses: ground-truth pose file overriding the one found.
        stereo: attach the right images.
        grey: read images as (H, W) grey.

    Raises:
        DatasetError: missing image folder, or times / poses that do not match the images.
    """
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(f"{root}: KITTI sequence folder not found")
    if cameras == "auto":
        cameras = "grey" if (root / "image_0").is_dir() else "colour"
    if cameras not in ("grey", "colour"):
        raise DatasetError(f"cameras: expected 'auto', 'grey' or 'colour', got {cameras!r}")
    left_name, right_name, pname = (
        ("image_0", "image_1", "P0") if cameras == "grey" else ("image_2", "image_3", "P2")
    )
    left_dir = root / left_name
    if not left_dir.is_dir():
        raise DatasetError(f"{root}: expected a KITTI sequence with a {left_name}/ folder, found none")
    images = list_images(left_dir, left_name)
    n = len(images)
    records = [FrameRecord(image=p) for p in images]
    if stereo and (root / right_name).is_dir():
        for rec, other in zip(records, match_by_stem(images, root / right_name, right_name), strict=True):
            rec.right = other

    times_file = root / "times.txt"
    if times_file.is_file():
        times = read_times(times_file, "times")
        if times.shape[0] != n:
            raise DatasetError(
                f"{times_file}: expected {n} timestamps (one per image), found {times.shape[0]}"
            )
        for rec, t in zip(records, times, strict=True):
            rec.timestamp = float(t)

    calib_file = root / "calib.txt"
    calib = read_kitti_calib(calib_file) if calib_file.is_file() else None
    pose_file = Path(poses) if poses is not None else _find_poses(root)
    if pose_file is not None:
        gt = read_kitti(pose_file)
        if gt.shape[0] != n:
            raise DatasetError(f"{pose_file}: expected {n} poses (one per image), found {gt.shape[0]}")
        if pname != "P0":
            if calib is None or pname not in calib:
                raise DatasetError(f"{calib_file}: {pname} needed to place the colour camera's poses")
            p = calib[pname]
            t_cam = np.linalg.solve(p[:, :3], p[:, 3])  # x_cam = x_cam0 + t_cam
            offset = np.eye(4)
            offset[:3, 3] = -t_cam
            gt = gt @ offset
        for rec, pose in zip(records, gt, strict=True):
            rec.pose = pose

    loops = root / "loops.npy"
    loader = None
    if cameras == "colour":

        def loader(path: Path) -> Any:
            from ..geometry.calibration import load_kitti

            return load_kitti(path, pair="colour")

    return SequenceDataset(
        root=root,
        records=records,
        format="kitti",
        calibration_path=calib_file if calib is not None else None,
        gt_path=loops if loops.is_file() else None,
        grey=grey,
        calibration_loader=loader,
    )
