"""stablecues.datasets.kitti on a tiny odometry sequence built in the test, and malformed files."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.datasets import open_dataset
from stablecues.errors import DatasetError


def _img(path: Path, value: int, shape: tuple[int, ...] = (6, 8)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full(shape, value, np.uint8))


def test_kitti(tmp_path: Path) -> None:
    seq = tmp_path / "sequences" / "07"
    for k in range(3):
        _img(seq / "image_0" / f"{k:06d}.png", k)
        _img(seq / "image_1" / f"{k:06d}.png", 50 + k)
        _img(seq / "image_2" / f"{k:06d}.png", k, (6, 8, 3))
    fx, base = 700.0, 0.5
    p0 = f"{fx} 0 600 0 0 {fx} 180 0 0 0 1 0"
    p1 = f"{fx} 0 600 {-fx * base} 0 {fx} 180 0 0 0 1 0"
    p2 = f"{fx} 0 600 {fx * 0.06} 0 {fx} 180 0 0 0 1 0"
    (seq / "calib.txt").write_text(f"P0: {p0}\nP1: {p1}\nP2: {p2}\nP3: {p1}\n")
    (seq / "times.txt").write_text("0.0\n0.1\n0.2\n")
    (tmp_path / "poses").mkdir()
    (tmp_path / "poses" / "07.txt").write_text(
        "".join(f"1 0 0 {k} 0 1 0 0 0 0 1 {2 * k}\n" for k in range(3))
    )
    ds = open_dataset(seq)
    assert ds.format == "kitti" and len(ds) == 3
    f = ds[2]
    assert f.right is not None and f.right[0, 0] == 52 and f.timestamp == pytest.approx(0.2)
    assert f.pose is not None
    np.testing.assert_allclose(f.pose[:3, 3], [2, 0, 4])
    assert f.calibration_path == seq / "calib.txt"
    colour = open_dataset(seq, cameras="colour")
    assert colour[0].image.shape == (6, 8, 3) and colour[0].right is None
    grey_cal, colour_cal = ds.calibration, colour.calibration
    if grey_cal is not None and colour_cal is not None:  # the geometry module reads calib.txt
        assert grey_cal.bf == pytest.approx(fx * base) and colour_cal.bf == pytest.approx(fx * (base + 0.06))
    assert colour[1].pose is not None
    np.testing.assert_allclose(colour[1].pose[:3, 3], [1 - 0.06, 0, 2])  # cam2 is 6 cm left of cam0
    (seq / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(DatasetError, match="expected 3 timestamps"):
        open_dataset(seq)
    (seq / "times.txt").write_text("0.0\n0.1\n0.2\n")
    (tmp_path / "poses" / "07.txt").write_text("1 0 0\n")
    with pytest.raises(DatasetError, match="12 numbers"):
        open_dataset(seq)


def test_kitti_calibration_and_camera_errors(tmp_path: Path) -> None:
    seq = tmp_path / "05"
    for k in range(2):
        _img(seq / "image_2" / f"{k:06d}.png", k, (6, 8, 3))
    ds = open_dataset(seq, format="kitti")  # no image_0: the colour pair
    assert ds.calibration_path is None and ds[0].image.shape == (6, 8, 3)
    (seq / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match="calib.txt: P2 needed to place the colour camera's poses"):
        open_dataset(seq, format="kitti")
    with pytest.raises(DatasetError, match="cameras: expected 'auto', 'grey' or 'colour', got 'rgb'"):
        open_dataset(seq, format="kitti", cameras="rgb")
    with pytest.raises(DatasetError, match="with a image_0/ folder, found none"):
        open_dataset(seq, format="kitti", cameras="grey")
    (seq / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(DatasetError, match="'NAME: 12 numbers' per line, line 1 has 3"):
        open_dataset(seq, format="kitti")
    (seq / "calib.txt").write_text("P1: " + " ".join(["1"] * 12) + "\n")
    with pytest.raises(DatasetError, match=r"expected a P0 line, found keys \['P1'\]"):
        open_dataset(seq, format="kitti")
    (seq / "calib.txt").write_text("P0: " + " ".join(["x"] * 12) + "\n")
    with pytest.raises(DatasetError, match="line 1 is not numeric"):
        open_dataset(seq, format="kitti")
