"""Writing posed frames: a TUM poses file, and the project's image-folder dataset.

Poses files are TUM (``t x y z qx qy qz qw``, camera-to-world, ENU metres about the solution's
origin), written by :func:`stablecues.trajectory.write_tum`; ``times.txt`` by
:func:`stablecues.trajectory.write_times`.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from ..errors import DatasetError, check_array
from ..trajectory import write_times, write_tum
from .frames import FrameSet
from .poses import FramePoses

__all__ = ["tum_comments", "write_image_folder", "write_poses"]


def tum_comments(poses: FramePoses) -> tuple[str, ...]:
    """Header comment lines describing a poses file."""
    lat, lon, alt = poses.origin
    return (
        "stablecues mav poses: t x y z qx qy qz qw, camera-to-world",
        f"world: ENU metres about lat={lat:.8f} lon={lon:.8f} alt={alt:.3f} m; source: {poses.source}",
        f"camera mount: {poses.mount}; clock offset {poses.offset:.3f} s"
        + ("" if poses.has_attitude else "; no attitude in the source: level, north-facing body assumed"),
    )


def write_poses(path: str | Path, poses: FramePoses) -> int:
    """Write the frames' poses as a TUM file (frame times, camera-to-world) with
    :func:`tum_comments` as its header.

    Returns:
        The number of poses written (frames without a pose are skipped).
    """
    return write_tum(path, poses.frame_times, poses.matrices, comments=tum_comments(poses))


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
        DatasetError: a frame's image or the calibration file is missing.
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
    write_times(out / "times.txt", poses.frame_times[keep])
    write_tum(out / "poses.txt", poses.frame_times[keep], poses.matrices[keep])
    if loops is not None:
        np.save(out / "loops.npy", loops)
    if calibration is not None:
        calib = Path(calibration)
        if not calib.is_file():
            raise DatasetError(f"{calib}: calibration file not found")
        shutil.copy2(calib, out / "calib.yaml")
    return out
