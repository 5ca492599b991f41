"""stablecues.datasets.tum on a tiny TUM RGB-D sequence built in the test, and malformed lists."""

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


def test_tum(tmp_path: Path) -> None:
    rgb_t = [1.00, 1.10, 1.20, 1.30]
    depth_t = [1.005, 1.095, 1.31]
    for t in rgb_t:
        _img(tmp_path / "rgb" / f"{t:.6f}.png", 5, (4, 4, 3))
    for t in depth_t:
        (tmp_path / "depth").mkdir(exist_ok=True)
        cv2.imwrite(str(tmp_path / "depth" / f"{t:.6f}.png"), np.full((4, 4), 10000, np.uint16))
    (tmp_path / "rgb.txt").write_text(
        "# color images\n# timestamp filename\n" + "".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in rgb_t)
    )
    (tmp_path / "depth.txt").write_text("".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in depth_t))
    (tmp_path / "groundtruth.txt").write_text(
        "# timestamp tx ty tz qx qy qz qw\n" + "".join(f"{t:.4f} {t} 0 0 0 0 0 1\n" for t in (1.0, 1.11, 1.5))
    )
    ds = open_dataset(tmp_path)
    assert ds.format == "tum" and len(ds) == 4
    depths = [ds.records[i].depth for i in range(4)]
    assert [d.name if d else None for d in depths] == ["1.005000.png", "1.095000.png", None, "1.310000.png"]
    assert ds[0].depth is not None and float(ds[0].depth[0, 0]) == pytest.approx(2.0)
    poses = ds.poses
    assert poses is not None
    np.testing.assert_allclose(poses[:2, 0, 3], [1.0, 1.11])
    assert np.isnan(poses[2]).all() and np.isnan(poses[3]).all()
    (tmp_path / "rgb.txt").write_text("1.0 rgb/absent.png\n")
    with pytest.raises(DatasetError, match="absent.png"):
        open_dataset(tmp_path)
    (tmp_path / "rgb.txt").write_text("1.0\n")
    with pytest.raises(DatasetError, match="timestamp filename"):
        open_dataset(tmp_path)


def test_tum_timestamp_names_and_calibration(tmp_path: Path) -> None:
    seq = tmp_path / "rgbd_dataset_freiburg3_office"
    for t in (2.5, 1.5, 10.0):  # listed in natural order, sorted here by time
        _img(seq / f"{t:.6f}.png", int(t), (4, 4, 3))
    ds = open_dataset(seq, format="tum")
    np.testing.assert_array_equal(ds.times, [1.5, 2.5, 10.0])
    assert ds.calibration_path == Path("fr3")  # the camera named by the folder
    assert open_dataset(seq, format="tum", calibration="fr1").calibration_path == Path("fr1")
    with pytest.raises(DatasetError, match="fr9: calibration file not found"):
        open_dataset(seq, format="tum", calibration="fr9")
    (seq / "calib.yaml").write_text("%YAML:1.0\n")
    assert open_dataset(seq, format="tum").calibration_path == seq / "calib.yaml"
    with pytest.raises(DatasetError, match="absent.txt: TUM trajectory .* not found"):
        open_dataset(seq, format="tum", groundtruth=seq / "absent.txt")
    (seq / "gt_groundtruth.txt").write_text("2.5 1 2 3 0 0 0 1\n")
    ds = open_dataset(seq, format="tum", max_difference=0.0)
    poses = ds.poses
    assert poses is not None and np.isnan(poses[0]).all() and np.isnan(poses[2]).all()
    np.testing.assert_array_equal(poses[1, :3, 3], [1, 2, 3])
    _img(seq / "frame.png", 1, (4, 4, 3))
    with pytest.raises(DatasetError, match="images named by timestamp .* found 'frame.png'"):
        open_dataset(seq, format="tum")
    numbered = tmp_path / "numbered"  # frame numbers are no times: none made up (issue 35)
    for k in (1, 2, 10):
        _img(numbered / f"{k}.png", k, (4, 4, 3))
    with pytest.raises(DatasetError, match="images named by timestamp .* found '1.png'"):
        open_dataset(numbered, format="tum")


def test_tum_malformed_lists(tmp_path: Path) -> None:
    _img(tmp_path / "rgb" / "1.0.png", 1, (4, 4, 3))
    (tmp_path / "rgb.txt").write_text("1.0 rgb/1.0.png\n")
    (tmp_path / "depth.txt").write_text("# nothing\n")
    with pytest.raises(DatasetError, match="depth.txt: expected at least one 'timestamp filename' line"):
        open_dataset(tmp_path)
    (tmp_path / "depth.txt").write_text("x depth/1.png\n")
    with pytest.raises(DatasetError, match=r"depth.txt: line 1: timestamp 'x' is not a number"):
        open_dataset(tmp_path)
    (tmp_path / "depth.txt").write_text("1.0 depth/1.png extra\n")
    with pytest.raises(DatasetError, match="line 1 has 3 fields"):
        open_dataset(tmp_path)
