"""Calibration readers: EuRoC, KITTI, ORB-SLAM settings, TUM; missing fields name the field."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path
from stablecues.errors import CalibrationError
from stablecues.geometry import (
    StereoRectifier,
    load_calibration,
    load_euroc_stereo,
    load_kitti,
    tum_calibration,
)

EUROC_LEFT = """%YAML:1.0
camera_id: camera
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""
EUROC_RIGHT = """%YAML:1.0
T_BS:
  cols: 4
  rows: 4
  data: [0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556,
         0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024,
        -0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038,
         0.0, 0.0, 0.0, 1.0]
resolution: [752, 480]
camera_model: pinhole
intrinsics: [457.587, 456.134, 379.999, 255.238]
distortion_model: radial-tangential
distortion_coefficients: [-0.28368365,  0.07451284, -0.00010473, -3.55590700e-05]
"""
ORBSLAM_RGBD = """%YAML:1.0
Camera.fx: 517.306408
Camera.fy: 516.469215
Camera.cx: 318.643040
Camera.cy: 255.313989
Camera.k1: 0.262383
Camera.k2: -0.953104
Camera.p1: -0.005358
Camera.p2: 0.002628
Camera.k3: 1.163314
Camera.width: 640
Camera.height: 480
Camera.bf: 40.0
DepthMapFactor: 5000.0
"""
_P0 = [718.856, 0, 607.1928, 0, 0, 718.856, 185.2157, 0, 0, 0, 1, 0]
_P1 = [718.856, 0, 607.1928, -386.1448, 0, 718.856, 185.2157, 0, 0, 0, 1, 0]
_P2 = [718.856, 0, 607.1928, 45.38225, 0, 718.856, 185.2157, -0.1130887, 0, 0, 1, 0.003779761]
_P3 = [718.856, 0, 607.1928, -337.2877, 0, 718.856, 185.2157, 2.369057, 0, 0, 1, 0.004915215]
KITTI_CALIB = "".join(
    f"{name}: {' '.join(f'{v:.12e}' for v in row)}\n"
    for name, row in (("P0", _P0), ("P1", _P1), ("P2", _P2), ("P3", _P3), ("Tr", [0.0] * 12))
)


def _write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_euroc_pair_found_beside_and_extrinsics(tmp_path: Path) -> None:
    left = _write(tmp_path, "sensorLeft.yaml", EUROC_LEFT)
    _write(tmp_path, "sensorRight.yaml", EUROC_RIGHT)
    cal = load_calibration(left)
    assert cal.is_stereo and not cal.rectified
    assert cal.left.fx == pytest.approx(458.654) and cal.right is not None
    assert cal.right.cx == pytest.approx(379.999)
    assert cal.left.image_size == (752, 480)
    # left-to-right is inv(T_BS_R) T_BS_L: the right camera sits ~11 cm along +x of the left
    assert cal.baseline == pytest.approx(0.110, abs=0.002)
    assert cal.translation is not None and cal.translation[0] == pytest.approx(-0.110, abs=0.002)


def test_euroc_asl_layout(tmp_path: Path) -> None:
    left = _write(tmp_path, "mav0/cam0/sensor.yaml", EUROC_LEFT)
    _write(tmp_path, "mav0/cam1/sensor.yaml", EUROC_RIGHT)
    assert load_calibration(left).is_stereo
    stereo = load_euroc_stereo(left, tmp_path / "mav0/cam1/sensor.yaml")
    assert stereo.baseline == pytest.approx(0.110, abs=0.002)
    # without the right file: monocular
    alone = _write(tmp_path, "other/sensor.yaml", EUROC_LEFT)
    assert not load_calibration(alone).is_stereo


def test_rectification_of_euroc(tmp_path: Path) -> None:
    left = _write(tmp_path, "sensorLeft.yaml", EUROC_LEFT)
    _write(tmp_path, "sensorRight.yaml", EUROC_RIGHT)
    rect = StereoRectifier(load_calibration(left))
    r = rect.rectified
    assert r.rectified and not r.left.has_distortion
    assert r.baseline == pytest.approx(0.110, abs=0.002)
    # a raw point and its rectified image point see the same ray (R1 rotates raw -> rectified)
    raw = np.array([[100.0, 80.0], [400.0, 300.0]])
    rays_raw = rect.raw.left.unproject(raw)
    rays_rect = r.left.unproject(rect.rectify_keypoints(raw))
    rotated = rays_raw @ rect.rotation_raw_to_rectified.T
    np.testing.assert_allclose(rotated[:, :2] / rotated[:, 2:], rays_rect[:, :2], atol=1e-6)
    img = np.random.default_rng(0).integers(0, 255, (480, 752), dtype=np.uint8)
    assert rect.rectify_left(img).shape == img.shape


def test_kitti_calib(tmp_path: Path) -> None:
    path = _write(tmp_path, "calib.txt", KITTI_CALIB)
    cal = load_calibration(path)
    assert cal.rectified and cal.is_stereo
    assert cal.left.fx == pytest.approx(718.856)
    assert cal.baseline == pytest.approx(386.1448 / 718.856)
    colour = load_kitti(path, pair="colour")
    assert colour.baseline == pytest.approx((45.38225 + 337.2877) / 718.856)


def test_orbslam_rgbd(tmp_path: Path) -> None:
    cal = load_calibration(_write(tmp_path, "TUM1.yaml", ORBSLAM_RGBD))
    assert cal.depth_scale == 5000.0
    assert cal.left.distortion == pytest.approx((0.262383, -0.953104, -0.005358, 0.002628, 1.163314))
    assert cal.left.image_size == (640, 480)


def test_tum_names() -> None:
    cal = load_calibration("fr2")
    assert cal.left.fx == pytest.approx(520.9) and cal.depth_scale == 5000.0
    assert tum_calibration("freiburg3").left.has_distortion is False
    with pytest.raises(CalibrationError, match="fr1, fr2, fr3"):
        tum_calibration("fr9")


@pytest.mark.parametrize(
    ("text", "name", "drop", "field"),
    [
        (EUROC_LEFT, "sensor.yaml", "intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv\n", ""),
        (EUROC_LEFT, "sensor.yaml", "resolution: [752, 480]\n", "resolution"),
        (ORBSLAM_RGBD, "settings.yaml", "Camera.cy: 255.313989\n", "Camera.cy"),
        (KITTI_CALIB, "calib.txt", KITTI_CALIB.splitlines(keepends=True)[1], "P1"),
    ],
)
def test_missing_field_is_named(tmp_path: Path, text: str, name: str, drop: str, field: str) -> None:
    assert drop in text
    path = _write(tmp_path, name, text.replace(drop, ""))
    with pytest.raises(CalibrationError) as err:
        load_calibration(path)
    msg = str(err.value)
    assert str(path) in msg
    if field:
        assert f"missing field '{field}'" in msg
    else:  # no intrinsics: not recognisable as any format
        assert "unknown calibration format" in msg


def test_bad_values(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="does not exist"):
        load_calibration(tmp_path / "nope.yaml")
    bad = _write(tmp_path, "s.yaml", EUROC_LEFT.replace("[458.654, 457.296, 367.215, 248.375]", "[1, 2, 3]"))
    with pytest.raises(CalibrationError, match="expected 4 numbers, got 3"):
        load_calibration(bad)


def test_shared_calibration_files() -> None:
    folder = shared_path("calibration")
    kitti = load_calibration(folder / "KITTI00-02.yaml")
    assert kitti.rectified and kitti.baseline == pytest.approx(386.1448 / 718.856)
    tum = load_calibration(folder / "TUM1.yaml")
    assert tum.depth_scale == 5000.0
    euroc = load_calibration(folder / "EuRoC_stereo.yaml")
    assert not euroc.rectified and euroc.rectification is not None
    assert euroc.baseline == pytest.approx(47.90639384423901 / 435.2046959714599)
    rect = StereoRectifier(euroc).rectified
    assert rect.left.fx == pytest.approx(435.2046959714599)


def test_shared_euroc_pair() -> None:
    folder = shared_path("euroc", "loop_pairs")
    cal = load_calibration(folder / "sensorLeft.yaml")
    assert cal.is_stereo and cal.baseline == pytest.approx(0.110, abs=0.002)
