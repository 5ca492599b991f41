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
from typing import Literal

import numpy as np

from ..errors import DatasetError
from ..fileio import read_text
from ..geometry.calibration import load_kitti
from ..geometry.camera import Calibration
from ..imageio import list_images, match_by_stem
from ..trajectory import read_kitti, read_times
from .base import FrameRecord, SequenceDataset, attach_poses, attach_times, check_one_per_image


def read_kitti_calib(path: Path) -> dict[str, np.ndarray]:
    """Read KITTI ``calib.txt``: ``{"P0": (3, 4), ..., "Tr": (3, 4)}`` float64 matrices.

    Raises:
        DatasetError: missing file, a line without 12 numbers, or no P0.
    """
    if not path.is_file():
        raise DatasetError(f"{path}: KITTI calibration file not found")
    out: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(read_text(path, "KITTI calibration").splitlines(), 1):
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
        if not np.isfinite(out[key.strip()]).all():
            raise DatasetError(f"{path}: line {lineno}: expected 12 finite numbers")
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


def _resolve_cameras(root: Path, cameras: str) -> str:
    """The cameras to read, "grey" or "colour"; "auto" is grey when ``image_0/`` is present.

    Raises:
        DatasetError: an unknown camera choice.
    """
    if cameras == "auto":
        cameras = "grey" if (root / "image_0").is_dir() else "colour"
    if cameras not in ("grey", "colour"):
        raise DatasetError(f"cameras: expected 'auto', 'grey' or 'colour', got {cameras!r}")
    return cameras


def _camera_offset(calib: dict[str, np.ndarray] | None, calib_file: Path, pname: str) -> np.ndarray:
    """(4, 4) float64 pose of camera ``pname`` in the grey camera's frame (a pure translation).

    Raises:
        DatasetError: ``calib.txt`` is missing or has no ``pname`` line.
    """
    if calib is None or pname not in calib:
        raise DatasetError(f"{calib_file}: {pname} needed to place the colour camera's poses")
    p = calib[pname]
    k = p[:, :3]
    if not (k[0, 0] > 0 and k[1, 1] > 0 and abs(np.linalg.det(k)) > 1e-12):
        raise DatasetError(
            f"{calib_file}: {pname}: expected a camera matrix with focal lengths > 0 (it is singular)"
        )
    t_cam = np.linalg.solve(k, p[:, 3])  # x_cam = x_cam0 + t_cam
    offset = np.eye(4)
    offset[:3, 3] = -t_cam
    return offset


def _load_colour_calibration(path: Path) -> Calibration:
    """The colour pair's calibration from KITTI ``calib.txt`` (P2 / P3)."""
    return load_kitti(path, pair="colour")


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
    pair = _resolve_cameras(root, cameras)
    left_name, right_name, pname = (
        ("image_0", "image_1", "P0") if pair == "grey" else ("image_2", "image_3", "P2")
    )
    left_dir = root / left_name
    if not left_dir.is_dir():
        raise DatasetError(f"{root}: expected a KITTI sequence with a {left_name}/ folder, found none")
    images = list_images(left_dir, left_name)
    records = [FrameRecord(image=p) for p in images]
    if stereo and (root / right_name).is_dir():
        for rec, other in zip(records, match_by_stem(images, root / right_name, right_name), strict=True):
            rec.right = other
    times_file = root / "times.txt"
    if times_file.is_file():
        attach_times(records, times_file, read_times(times_file, "times"))

    calib_file = root / "calib.txt"
    calib = read_kitti_calib(calib_file) if calib_file.is_file() else None
    pose_file = Path(poses) if poses is not None else _find_poses(root)
    if pose_file is not None:
        gt = read_kitti(pose_file)
        check_one_per_image(pose_file, "poses", len(records), gt.shape[0])
        if pname != "P0":
            gt = gt @ _camera_offset(calib, calib_file, pname)
        attach_poses(records, pose_file, gt)

    loops = root / "loops.npy"
    loader = _load_colour_calibration if pair == "colour" else None
    return SequenceDataset(
        root=root,
        records=records,
        format="kitti",
        calibration_path=calib_file if calib is not None else None,
        gt_path=loops if loops.is_file() else None,
        grey=grey,
        calibration_loader=loader,
        poses_path=pose_file,
    )
