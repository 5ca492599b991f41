"""stablecues.datasets: detecting a folder's format and opening it with the format's options."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.datasets import FORMATS, detect_format, open_dataset
from stablecues.errors import ConfigError, DatasetError


def _img(path: Path, value: int, shape: tuple[int, ...] = (6, 8)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full(shape, value, np.uint8))


@pytest.mark.parametrize(
    ("files", "expected"),
    [
        (["mav0/cam0/data/1.png"], "euroc"),
        (["rgb.txt", "rgb/1.0.png"], "tum"),
        (["image_0/000000.png"], "kitti"),
        (["image_2/000000.png"], "kitti"),
        (["ref/0.jpg", "query/0.jpg"], "vprbench"),
        (["Images/0001.jpg"], "fabmap"),
        (["0001.jpg", "NewCollegeGroundTruth.mat"], "fabmap"),
        (["rgb/1311868169.163498.png", "groundtruth.txt"], "tum"),
        (["1311868169.163498.png", "fr1_groundtruth.txt"], "tum"),
        (["1311868169.163498.png"], "folder"),  # timestamps without a trajectory: a plain folder
        (["images/0.png", "times.txt"], "folder"),
        (["0.png"], "folder"),
    ],
)
def test_detect_format(tmp_path: Path, files: list[str], expected: str) -> None:
    for name in files:
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.suffix in (".png", ".jpg"):
            _img(path, 0)
        else:
            path.write_bytes(b"")
    assert detect_format(tmp_path) == expected


def test_detect_format_on_mav0_itself(tmp_path: Path) -> None:
    (tmp_path / "mav0" / "cam0").mkdir(parents=True)
    assert detect_format(tmp_path / "mav0") == "euroc"


def test_open_dataset_errors(tmp_path: Path) -> None:
    for k in range(3):
        _img(tmp_path / f"{k:03d}.jpg", k)
    assert detect_format(tmp_path) == "folder"
    with pytest.raises(ConfigError):
        open_dataset(tmp_path, format="nope")
    with pytest.raises(ConfigError, match="unknown dataset format 'nope'; known: auto, folder, tum"):
        open_dataset(tmp_path, format="nope")
    with pytest.raises(ConfigError, match="view"):
        open_dataset(tmp_path, format="folder", view="left")
    with pytest.raises(ConfigError, match="known: calibration, depth_factor, grey"):
        open_dataset(tmp_path, format="folder", view="left")
    with pytest.raises(DatasetError, match="dataset folder not found"):
        detect_format(tmp_path / "absent")
    assert open_dataset(tmp_path, format="folder", grey=True)[0].image.ndim == 2
    assert set(FORMATS) == {"folder", "tum", "kitti", "euroc", "fabmap", "vprbench", "rosbag"}
