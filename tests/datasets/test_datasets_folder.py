"""Each dataset loader on a tiny fixture built in the test, plus malformed inputs that must raise."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.datasets import Dataset, detect_format, open_dataset
from stablecues.geometry.rotations import quat_to_matrix
from stablecues.trajectory import associate, nearest
from stablecues.errors import ConfigError, DatasetError


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
    assert detect_format(tmp_path) == "folder" and len(ds) == 3
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
    with pytest.raises(ConfigError):
        open_dataset(tmp_path, format="nope")
    with pytest.raises(ConfigError, match="view"):
        open_dataset(tmp_path, format="folder", view="left")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError, match="found none"):
        open_dataset(empty)
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "x.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match="not a readable image"):
        open_dataset(tmp_path / "bad")[0]


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


def test_euroc(tmp_path: Path) -> None:
    mav0 = tmp_path / "MH_09_test" / "mav0"
    stamps = [1_000_000_000_000_000_000 + k * 50_000_000 for k in range(3)]
    for cam in ("cam0", "cam1"):
        (mav0 / cam / "data").mkdir(parents=True)
        (mav0 / cam / "data.csv").write_text(
            "#timestamp [ns],filename\n" + "".join(f"{s},{s}.png\n" for s in stamps)
        )
        for k, s in enumerate(stamps):
            _img(mav0 / cam / "data" / f"{s}.png", k + (100 if cam == "cam1" else 0))
    t_bs = np.eye(4)
    t_bs[:3, 3] = [0.1, 0.0, 0.0]
    (mav0 / "cam0" / "sensor.yaml").write_text(
        "%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: ["
        + ", ".join(str(v) for v in t_bs.ravel())
        + "]\nintrinsics: [458.0, 457.0, 367.0, 248.0]\nresolution: [8, 6]\ncamera_model: pinhole\n"
        + "distortion_model: radial-tangential\ndistortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n"
    )
    gt_dir = mav0 / "state_groundtruth_estimate0"
    gt_dir.mkdir()
    # body rotated 90 degrees about z (q_w, q_x, q_y, q_z), at x = k
    lines = "".join(f"{s},{k},0,0,0.7071068,0,0,0.7071068" + ",0" * 9 + "\n" for k, s in enumerate(stamps))
    (gt_dir / "data.csv").write_text("#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z,...\n" + lines)
    ds = open_dataset(tmp_path / "MH_09_test")
    assert ds.format == "euroc" and len(ds) == 3
    f = ds[1]
    assert f.timestamp == pytest.approx(1e9 + 0.05) and f.right is not None and f.right[0, 0] == 101
    assert f.pose is not None
    np.testing.assert_allclose(f.pose[:3, 3], [1.0, 0.1, 0.0], atol=1e-6)  # body x=1, cam offset rotated
    assert f.calibration_path == mav0 / "cam0" / "sensor.yaml"
    (mav0 / "cam0" / "data.csv").write_text("#timestamp [ns],filename\nabc,def.png\n")
    with pytest.raises(DatasetError, match="timestamp_ns,filename"):
        open_dataset(mav0)


def test_fabmap(tmp_path: Path) -> None:
    for k in range(1, 7):  # 0001 left, 0002 right, ...
        _img(tmp_path / "Images" / f"{k:04d}.jpg", 10 * k)
    full = np.zeros((6, 6), np.uint8)
    full[4, 0] = 1  # left image of pair 2 sees left image of pair 0
    full[5, 3] = 1  # right of pair 2 sees right of pair 1
    import scipy.io

    scipy.io.savemat(tmp_path / "TinyGroundTruth.mat", {"truth": full.T})  # stored upper-triangular
    left = open_dataset(tmp_path)
    assert left.format == "fabmap" and len(left) == 3
    assert [n.split("/")[-1] for n in left.names] == ["0001.jpg", "0003.jpg", "0005.jpg"]
    gt = left.ground_truth()
    assert gt is not None and gt.transposed and gt.view == "left"
    assert list(zip(*np.nonzero(gt.matrix), strict=True)) == [(2, 0)]
    right = open_dataset(tmp_path, view="right")
    assert right.names[0].endswith("0002.jpg")
    rgt = right.ground_truth()
    assert rgt is not None and list(zip(*np.nonzero(rgt.matrix), strict=True)) == [(2, 1)]
    every = open_dataset(tmp_path, view="all")
    egt = every.ground_truth()
    assert len(every) == 6 and egt is not None and egt.matrix.sum() == 2


def test_vprbench(tmp_path: Path) -> None:
    for k in range(3):
        _img(tmp_path / "ref" / f"{k:07d}.jpg", k)
    for k in range(2):
        _img(tmp_path / "query" / f"{k:07d}.jpg", 100 + k)
    table = np.empty((2, 2), dtype=object)
    table[0, 0], table[0, 1] = 0, [0, 1]
    table[1, 0], table[1, 1] = 1, [-1]
    np.save(tmp_path / "ground_truth_new.npy", table, allow_pickle=True)
    ds = open_dataset(tmp_path)
    assert ds.format == "vprbench" and len(ds) == 5
    assert ds.names == [f"ref/{k:07d}.jpg" for k in range(3)] + [f"query/{k:07d}.jpg" for k in range(2)]
    assert ds[3].image[0, 0] == 100
    gt = ds.ground_truth()
    assert gt is not None and gt.query_mask is not None
    assert list(zip(*np.nonzero(gt.matrix), strict=True)) == [(3, 0), (3, 1)]
    assert gt.query_mask.tolist() == [False, False, False, True, True]
    (tmp_path / "query").rename(tmp_path / "q")
    with pytest.raises(DatasetError, match="query/"):
        open_dataset(tmp_path, format="vprbench")


def test_association_helpers() -> None:
    q = np.array([0.0, 1.0, 2.0])
    r = np.array([2.01, 0.5, 1.0, 0.99])
    assert associate(q, r, 0.02).tolist() == [-1, 2, 0]
    assert nearest(q, r, 0.6).tolist() == [1, 2, 0]
    assert nearest(q, np.array([5.0]), 0.1).tolist() == [-1, -1, -1]
    rot = quat_to_matrix(np.array([[0, 0, 0, 2.0]]))  # unnormalised identity
    np.testing.assert_allclose(rot[0], np.eye(3))
