"""stablecues.datasets.folder: the project layout and plain folders, built in the test, and
malformed side files that must raise."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.datasets import Dataset, open_dataset, open_folder
from stablecues.datasets.folder import read_settings_value
from stablecues.errors import DatasetError


def _img(path: Path, value: int, shape: tuple[int, ...] = (6, 8)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full(shape, value, np.uint8))


def test_folder_layout_full(tmp_path: Path) -> None:
    for k, name in enumerate(["1.png", "2.png", "10.png"]):  # natural order: 1, 2, 10
        _img(tmp_path / "images" / name, 10 * k, (6, 8, 3))
        _img(tmp_path / "right" / name, 100 + k)
    (tmp_path / "depth").mkdir()
    (tmp_path / "labels").mkdir()
    for name in ["1.png", "2.png", "10.png"]:
        cv2.imwrite(str(tmp_path / "depth" / name), np.array([[0, 5000], [2500, 1]], np.uint16))
        cv2.imwrite(str(tmp_path / "labels" / name), np.array([[0, 3], [11, 8]], np.uint8))
    (tmp_path / "times.txt").write_text("0.0\n0.5\n1.0\n")
    (tmp_path / "poses.txt").write_text(
        "0 1 2 3 0 0 0 1\n0.5 0 0 0 0 0 0.7071068 0.7071068\n1.0 0 0 0 0 0 0 1\n"
    )
    (tmp_path / "calib.yaml").write_text(
        "%YAML:1.0\nCamera.fx: 500.0\nCamera.fy: 500.0\nCamera.cx: 4.0\nCamera.cy: 3.0\n"
        "Camera.k1: 0.0\nCamera.k2: 0.0\nCamera.p1: 0.0\nCamera.p2: 0.0\n"
        "Camera.width: 8\nCamera.height: 6\nCamera.bf: 40.0\nDepthMapFactor: 5000.0\n"
    )
    np.save(tmp_path / "loops.npy", np.tril(np.ones((3, 3), bool), -2))
    ds = open_dataset(tmp_path)
    assert isinstance(ds, Dataset) and ds.format == "folder" and len(ds) == 3
    assert ds.names == ["images/1.png", "images/2.png", "images/10.png"]
    frames = list(ds)
    assert [f.index for f in frames] == [0, 1, 2]
    f = frames[2]
    assert f.image.shape == (6, 8, 3) and f.image.dtype == np.uint8 and f.image[0, 0, 0] == 20
    assert f.right is not None and f.right[0, 0] == 102
    assert f.depth is not None and f.depth.dtype == np.float32
    np.testing.assert_allclose(f.depth, [[np.nan, 1.0], [0.5, 0.0002]], rtol=1e-6)
    assert f.labels is not None and f.labels.tolist() == [[0, 3], [11, 8]]
    np.testing.assert_array_equal(ds.times, [0.0, 0.5, 1.0])
    poses = ds.poses
    assert poses is not None and poses.shape == (3, 4, 4)
    np.testing.assert_allclose(poses[0, :3, 3], [1, 2, 3])
    np.testing.assert_allclose(poses[1, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)
    assert f.calibration_path == tmp_path / "calib.yaml"
    gt = ds.ground_truth()
    assert gt is not None and gt.matrix.sum() == 1 and gt.matrix[2, 0]


def test_plain_folder_and_errors(tmp_path: Path) -> None:
    for k in range(3):
        _img(tmp_path / f"{k:03d}.jpg", k)
    ds = open_dataset(tmp_path, grey=True)
    assert len(ds) == 3
    assert ds[1].image.ndim == 2 and np.isnan(ds[1].timestamp) and ds.poses is None
    assert ds.ground_truth_path() is None and ds[-1].index == 2
    (tmp_path / "times.txt").write_text("0\n1\n")
    with pytest.raises(DatasetError, match="expected 3 timestamps"):
        open_dataset(tmp_path)
    (tmp_path / "times.txt").write_text("0\n1\nx\n")
    with pytest.raises(DatasetError, match="not numeric"):
        open_dataset(tmp_path)
    (tmp_path / "times.txt").unlink()
    (tmp_path / "right").mkdir()
    _img(tmp_path / "right" / "000.png", 1)
    with pytest.raises(DatasetError, match="001"):
        open_dataset(tmp_path)
    with pytest.raises(DatasetError, match="not found"):
        open_dataset(tmp_path / "absent")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError, match="found none"):
        open_dataset(empty)
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "x.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match="not a readable image"):
        open_dataset(tmp_path / "bad")[0]


def test_poses_fill_missing_timestamps(tmp_path: Path) -> None:
    for k in range(2):
        _img(tmp_path / "images" / f"{k}.png", k)
    (tmp_path / "poses.txt").write_text("10.5 0 0 0 0 0 0 1\n11.5 1 0 0 0 0 0 1\n")
    ds = open_folder(tmp_path)
    np.testing.assert_array_equal(ds.times, [10.5, 11.5])  # no times.txt: the poses' times
    (tmp_path / "times.txt").write_text("0.0\n0.1\n")
    np.testing.assert_array_equal(open_folder(tmp_path).times, [0.0, 0.1])  # times.txt wins
    (tmp_path / "poses.txt").write_text("10.5 0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"poses.txt: expected 2 poses \(one per image\), found 1"):
        open_folder(tmp_path)
    (tmp_path / "poses.txt").write_text("10.5 0 0 0 0 0 0 1\n11.5 1 0 0\n")
    with pytest.raises(DatasetError, match="poses.txt: .* line 2 has 4"):
        open_folder(tmp_path)


def test_depth_factor_sources(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    _img(tmp_path / "images" / "0.png", 0)
    (tmp_path / "depth").mkdir()
    cv2.imwrite(str(tmp_path / "depth" / "0.png"), np.full((2, 2), 2000, np.uint16))
    with caplog.at_level(logging.WARNING, logger="stablecues.datasets.folder"):
        ds = open_folder(tmp_path)
    assert ds.depth_factor == 1000.0 and "no DepthMapFactor" in caplog.text
    depth = ds[0].depth
    assert depth is not None and float(depth[0, 0]) == pytest.approx(2.0)
    (tmp_path / "calib.yaml").write_text("%YAML:1.0\nDepthMapFactor: 5000.0\n")
    assert open_folder(tmp_path).depth_factor == 5000.0
    assert open_folder(tmp_path, depth_factor=250.0).depth_factor == 250.0  # the argument wins
    (tmp_path / "calib.yaml").write_text("DepthMapFactor: abc\n")
    with pytest.raises(DatasetError, match="DepthMapFactor should be a number, found 'abc'"):
        open_folder(tmp_path)
    (tmp_path / "calib.yaml").write_text("DepthMapFactor: 0\n")
    with pytest.raises(DatasetError, match="calib.yaml: DepthMapFactor must be > 0, found 0.0"):
        open_folder(tmp_path)
    with pytest.raises(DatasetError, match="must be > 0"):
        open_folder(tmp_path, depth_factor=-1.0)
    with pytest.raises(DatasetError, match="other.yaml: calibration file not found"):
        open_folder(tmp_path, calibration=tmp_path / "other.yaml")


def test_read_settings_value(tmp_path: Path) -> None:
    path = tmp_path / "s.yaml"
    path.write_text("%YAML:1.0\nCamera.fx: 458.6\n  Camera.bf:47.9\n")
    assert read_settings_value(path, "Camera.fx") == pytest.approx(458.6)
    assert read_settings_value(path, "Camera.bf") == pytest.approx(47.9)
    assert read_settings_value(path, "Camera.fy") is None
    assert read_settings_value(path, "Camera") is None  # whole keys only, no prefix match
    with pytest.raises(DatasetError, match="settings file not found"):
        read_settings_value(tmp_path / "absent.yaml", "x")


def test_frames_folder_with_labels_and_gt_png_beside_it(tmp_path: Path) -> None:
    """CamVid revisit sets keep their images in frames/ (JPEG), labels/ (PNG, same stems) and
    gt.png beside them: `info` failed on labels/ (gt.png was read as a frame, issue 35). The
    frames folder is read as images/ is, and a gt.* beside it is the loop ground truth."""
    for k in range(3):
        _img(tmp_path / "frames" / f"{k + 1:04d}.jpg", 20 * k, (6, 8, 3))
        _img(tmp_path / "labels" / f"{k + 1:04d}.png", k)
    gt = np.zeros((3, 3), np.uint8)
    gt[2, 0] = 255
    cv2.imwrite(str(tmp_path / "gt.png"), gt)
    ds = open_dataset(tmp_path)
    assert ds.format == "folder" and len(ds) == 3
    assert [r.image.name for r in ds.records] == ["0001.jpg", "0002.jpg", "0003.jpg"]
    assert ds.records[2].labels == tmp_path / "labels" / "0003.png"
    assert ds.ground_truth_path() == tmp_path / "gt.png"
    truth = ds.ground_truth()
    assert truth is not None and truth.matrix[2, 0] and truth.matrix.sum() == 1


def test_a_folder_of_datasets_names_its_folders(tmp_path: Path) -> None:
    """A folder holding datasets (../shared/data/tum) is no dataset: the one line names what it
    holds instead of only saying that no image was found."""
    for name in ("fr2_desk", "fr3_office"):
        _img(tmp_path / name / "rgb" / "1.png", 1)
    with pytest.raises(DatasetError, match=r"no images here, only folders \(fr2_desk, fr3_office\)"):
        open_dataset(tmp_path)


def test_info_on_the_real_revisit_sets(capsys: pytest.CaptureFixture[str]) -> None:
    from conftest import shared_path
    from stablecues.cli.main import main

    for name in ("val_drive", "train_drives"):
        root = shared_path("camvid_revisit_dev", name)
        assert main(["info", str(root)]) == 0
        out = capsys.readouterr().out
        assert f"ground truth: {root / 'gt.png'}" in out
