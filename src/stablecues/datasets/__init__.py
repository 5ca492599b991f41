"""Datasets: one module per format, each yielding :class:`Frame` s lazily.

``open_dataset(path, format="auto")`` opens any of them; the formats are

========== =====================================================================
folder     the project's image-folder layout, or a plain folder of images
tum        TUM RGB-D (rgb.txt, depth.txt, groundtruth.txt)
kitti      KITTI odometry sequence (image_0/1 or image_2/3, calib.txt, times.txt, poses)
euroc      EuRoC MAV, ASL layout (mav0/cam0, cam1, sensor.yaml, ground truth)
fabmap     FAB-MAP New College / City Centre (left/right images interleaved)
vprbench   two-pass VPR-Bench set (ref/, query/, ground_truth_new.npy) as one sequence
rosbag     ROS 1 .bag, ROS 2 bag folder (metadata.yaml + .db3 / .mcap) or a bare .db3 / .mcap
========== =====================================================================
"""

from __future__ import annotations

import difflib
import inspect
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import ConfigError, DatasetError
from ..imageio import natural_key
from ..types import Frame
from .base import Dataset, FrameRecord, SequenceDataset
from .euroc import open_euroc
from .fabmap import FabmapDataset, open_fabmap
from .folder import open_folder
from .kitti import open_kitti
from .rosbag import RosbagDataset, is_bag, open_rosbag
from .tum import open_tum
from .vprbench import open_vprbench

__all__ = [
    "FORMATS",
    "Dataset",
    "FabmapDataset",
    "Frame",
    "FrameRecord",
    "RosbagDataset",
    "SequenceDataset",
    "detect_format",
    "natural_key",
    "open_dataset",
    "open_euroc",
    "open_fabmap",
    "open_folder",
    "open_kitti",
    "open_rosbag",
    "open_tum",
    "open_vprbench",
]

FORMATS: dict[str, Callable[..., SequenceDataset]] = {
    "folder": open_folder,
    "tum": open_tum,
    "kitti": open_kitti,
    "euroc": open_euroc,
    "fabmap": open_fabmap,
    "vprbench": open_vprbench,
    "rosbag": open_rosbag,
}

_TIMESTAMP_IMAGE = re.compile(r"^\d{6,}\.\d+\.(png|jpg)$", re.IGNORECASE)


def detect_format(path: str | Path) -> str:
    """Guess a dataset folder's format from its layout.

    Rules, first match wins: a ROS bag (a ``.bag``, ``.db3`` or ``.mcap`` file, or a folder with
    a ROS 2 ``metadata.yaml``) -> rosbag; ``mav0/cam0`` -> euroc; ``rgb.txt`` -> tum; ``image_0/`` or
    ``image_2/`` -> kitti; ``ref/`` and ``query/`` -> vprbench; ``Images/`` or a
    ``*GroundTruth*.mat`` -> fabmap; images named by timestamps beside a ``*groundtruth*.txt``
    -> tum; anything else -> folder.

    Raises:
        DatasetError: the path is not a folder.
    """
    root = Path(path)
    if is_bag(root):
        return "rosbag"
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder not found")
    if (root / "mav0" / "cam0").is_dir() or (root.name == "mav0" and (root / "cam0").is_dir()):
        return "euroc"
    if (root / "rgb.txt").is_file():
        return "tum"
    if (root / "image_0").is_dir() or (root / "image_2").is_dir():
        return "kitti"
    if (root / "ref").is_dir() and (root / "query").is_dir():
        return "vprbench"
    if (root / "Images").is_dir() or any(root.glob("*[Gg]round[Tt]ruth*.mat")):
        return "fabmap"
    image_dir = root / "rgb" if (root / "rgb").is_dir() else root
    if any(root.glob("*groundtruth*.txt")) and any(
        _TIMESTAMP_IMAGE.match(p.name) for p in image_dir.iterdir()
    ):
        return "tum"
    return "folder"


def open_dataset(path: str | Path, format: str = "auto", **options: Any) -> SequenceDataset:
    """Open a dataset folder.

    Args:
        path: the dataset folder (or a ROS bag file).
        format: "auto" (see :func:`detect_format`), "folder", "tum", "kitti", "euroc",
            "fabmap", "vprbench" or "rosbag".
        **options: keyword options of that format's ``open_*`` function (e.g. ``grey=True``,
            ``view="right"`` for fabmap, ``groundtruth=...`` for tum / euroc); every format takes
            ``calibration`` (a file any reader of :func:`stablecues.geometry.load_calibration`
            reads, in place of the dataset's own; a folder's also gives the DepthMapFactor).

    Returns:
        The dataset; iterate it for frames.

    Raises:
        ConfigError: unknown format or an option the format does not take.
        DatasetError: missing or malformed files.
    """
    fmt = detect_format(path) if format == "auto" else format
    opener = FORMATS.get(fmt)
    if opener is None:
        close = difflib.get_close_matches(str(format), ["auto", *FORMATS], n=1, cutoff=0.6)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ConfigError(f"unknown dataset format {format!r}{hint}; known: auto, {', '.join(FORMATS)}")
    accepted = set(inspect.signature(opener).parameters) - {"path"}
    calibration = None
    if "calibration" not in accepted:  # every format takes one, after opening (use_calibration)
        calibration = options.pop("calibration", None)
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise ConfigError(
            f"dataset format {fmt!r} takes no option {unknown[0]!r}; known: "
            f"{', '.join(sorted(accepted | {'calibration'}))}"
        )
    dataset = opener(path, **options)
    if calibration is not None:
        dataset.use_calibration(calibration)
    return dataset
