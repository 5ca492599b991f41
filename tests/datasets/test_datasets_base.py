"""stablecues.datasets.base: SequenceDataset over records made in the test, and the shared helpers."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.datasets.base import (
    FrameRecord,
    SequenceDataset,
    attach_poses,
    attach_times,
    check_one_per_image,
    find_first,
)
from stablecues.errors import DatasetError
from stablecues.geometry import Calibration, PinholeCamera


def _records(root: Path, n: int = 3) -> list[FrameRecord]:
    (root / "img").mkdir(parents=True, exist_ok=True)
    records = []
    for k in range(n):
        path = root / "img" / f"{k}.png"
        image = np.zeros((4, 5, 3), np.uint8)
        image[..., 2] = 10 * k  # red channel
        cv2.imwrite(str(path), image)
        records.append(FrameRecord(image=path, timestamp=0.5 * k))
    return records


def test_frames_are_read_lazily_with_names_and_indices(tmp_path: Path) -> None:
    records = _records(tmp_path)
    ds = SequenceDataset(root=tmp_path, records=records, format="test")
    assert ds.name == tmp_path.name and len(ds) == 3
    (tmp_path / "img" / "2.png").unlink()  # nothing was read when the dataset was made
    f = ds[1]
    assert f.index == 1 and f.name == "img/1.png" and f.timestamp == 0.5
    assert f.image.shape == (4, 5, 3) and f.image[0, 0, 2] == 10
    assert f.right is None and f.depth is None and f.labels is None and f.pose is None
    assert ds[-2].index == 1
    with pytest.raises(IndexError, match="frame 3 out of range for 3 frames"):
        ds[3]
    with pytest.raises(IndexError, match="frame -4 out of range"):
        ds[-4]
    with pytest.raises(DatasetError, match="2.png"):
        ds[2]


def test_grey_names_times_and_poses(tmp_path: Path) -> None:
    records = _records(tmp_path)
    records[0].name = "first"
    records[2].image = tmp_path.parent / "elsewhere.png"  # outside the root: its file name
    records[1].pose = np.diag([1.0, 1.0, 1.0, 1.0])
    records[1].pose[:3, 3] = [1, 2, 3]
    ds = SequenceDataset(root=tmp_path, records=records, grey=True)
    assert ds.names == ["first", "img/1.png", "elsewhere.png"]
    assert ds[0].image.shape == (4, 5)
    np.testing.assert_array_equal(ds.times, [0.0, 0.5, 1.0])
    poses = ds.poses
    assert poses is not None and poses.shape == (3, 4, 4)
    assert np.isnan(poses[0]).all() and np.isnan(poses[2]).all()
    np.testing.assert_array_equal(poses[1, :3, 3], [1, 2, 3])
    frame_pose = ds[1].pose
    assert frame_pose is not None
    frame_pose[0, 3] = 99.0  # a frame's pose is a copy
    assert records[1].pose[0, 3] == 1.0
    assert SequenceDataset(root=tmp_path, records=_records(tmp_path)).poses is None


def test_ground_truth_and_describe(tmp_path: Path) -> None:
    ds = SequenceDataset(root=tmp_path, records=_records(tmp_path), format="test")
    assert ds.ground_truth_path() is None and ds.ground_truth() is None
    desc = ds.describe()
    assert desc == {
        "dataset": str(tmp_path),
        "name": tmp_path.name,
        "format": "test",
        "dataset_frames": 3,
        "stereo": False,
        "depth": False,
        "labels": False,
        "poses": False,
        "calibration": None,
        "ground_truth": None,
    }
    np.save(tmp_path / "loops.npy", np.zeros((2, 2), bool))
    ds.gt_path = tmp_path / "loops.npy"
    with pytest.raises(DatasetError, match=r"loops.npy: expected a 3 x 3 loop matrix, found 2"):
        ds.ground_truth()
    empty = SequenceDataset(root=tmp_path, records=[])
    assert empty.describe()["stereo"] is False and list(empty) == []


def test_calibration_is_loaded_once(tmp_path: Path) -> None:
    calls: list[Path] = []

    def loader(path: Path) -> Calibration:
        calls.append(path)
        return Calibration(PinholeCamera(100.0, 100.0, 2.0, 2.0))

    ds = SequenceDataset(
        root=tmp_path,
        records=_records(tmp_path),
        calibration_path=tmp_path / "calib.txt",
        calibration_loader=loader,
    )
    assert calls == []
    first = ds[0].calibration
    assert first is not None and first is ds[1].calibration and calls == [tmp_path / "calib.txt"]
    assert SequenceDataset(root=tmp_path, records=_records(tmp_path)).calibration is None


def test_attach_helpers_check_counts(tmp_path: Path) -> None:
    records = [FrameRecord(image=tmp_path / f"{k}.png") for k in range(2)]
    attach_times(records, tmp_path / "times.txt", np.array([1.0, 2.0]))
    assert [r.timestamp for r in records] == [1.0, 2.0]
    with pytest.raises(DatasetError, match=r"times.txt: expected 2 timestamps \(one per image\), found 3"):
        attach_times(records, tmp_path / "times.txt", np.zeros(3))
    poses = np.tile(np.eye(4), (2, 1, 1))
    attach_poses(records, tmp_path / "poses.txt", poses)
    assert records[1].pose is not None and records[1].pose.shape == (4, 4)
    with pytest.raises(DatasetError, match=r"poses.txt: expected 2 poses \(one per image\), found 1"):
        attach_poses(records, tmp_path / "poses.txt", poses[:1])
    check_one_per_image(tmp_path / "x", "things", 4, 4)
    with pytest.raises(DatasetError, match="expected 4 things"):
        check_one_per_image(tmp_path / "x", "things", 4, 5)


def test_find_first(tmp_path: Path) -> None:
    (tmp_path / "calib.yml").write_text("x")
    assert find_first(tmp_path, ("calib.yaml", "calib.yml")) == tmp_path / "calib.yml"
    (tmp_path / "calib.yaml").write_text("x")
    assert find_first(tmp_path, ("calib.yaml", "calib.yml")) == tmp_path / "calib.yaml"
    assert find_first(tmp_path, ("absent",)) is None
