"""Smoke tests of the loaders on the real data in ../shared/data (skipped when absent)."""

from __future__ import annotations

import numpy as np

from conftest import shared_path
from stablecues.datasets import detect_format, open_dataset


def test_euroc_micro() -> None:
    ds = open_dataset(shared_path("euroc", "V1_01_micro"))
    assert ds.format == "euroc" and len(ds) == 19
    f = ds[0]
    assert f.image.shape == (480, 752) and f.right is not None and f.right.shape == (480, 752)
    assert f.timestamp == np.float64(1403715273.262142976)
    poses = ds.poses  # from ../V1_01_groundtruth_tum.txt (body) composed with cam0's T_BS
    assert poses is not None and np.isfinite(poses).all()
    # the first body position of the TUM file is (0.878895, 2.183400, 0.948427); the camera is
    # offset from the body by |T_BS translation| ~ 0.069 m
    assert np.linalg.norm(poses[0, :3, 3] - [0.878895, 2.1834, 0.948427]) < 0.1
    np.testing.assert_allclose(
        poses[:, :3, :3] @ poses[:, :3, :3].transpose(0, 2, 1), np.tile(np.eye(3), (19, 1, 1)), atol=1e-5
    )
    assert np.all(np.diff(ds.times) > 0)


def test_tum_fr2_desk() -> None:
    ds = open_dataset(shared_path("tum", "fr2_desk"))
    assert ds.format == "tum" and len(ds) == 20
    assert ds[0].image.shape == (480, 640, 3)
    poses = ds.poses
    assert poses is not None and np.isfinite(poses).all()
    assert str(ds.calibration_path) == "fr2"


def test_corridor_two_pass() -> None:
    ds = open_dataset(shared_path("corridor"))
    assert ds.format == "vprbench" and len(ds) == 222
    assert ds[111].name == "query/0000000.jpg"
    gt = ds.ground_truth()
    assert gt is not None and gt.n == 222 and gt.query_mask is not None
    assert gt.query_mask.sum() == 111
    # query i matches reference i-2..i+2 (clipped)
    assert set(np.nonzero(gt.matrix[111 + 50])[0]) == {48, 49, 50, 51, 52}
    assert not gt.matrix[:111].any()


def test_kitti_frames_as_plain_folder() -> None:
    path = shared_path("kitti", "frames_seq0x")
    assert detect_format(path) == "folder"
    ds = open_dataset(path)
    assert len(ds) == 20 and ds[0].image.shape == (376, 1241)
    assert ds.names[0] == "000100.png"


def test_desk_loop10_natural_order() -> None:
    ds = open_dataset(shared_path("desk_loop10"))
    assert ds.names == [f"{k}.png" for k in range(1, 11)]
