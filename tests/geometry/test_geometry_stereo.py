"""Sparse stereo: a synthetic rectified pair with known disparity, degenerate inputs, real KITTI."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import shared_path
from stablecues.errors import CalibrationError, InputError
from stablecues.geometry import (
    Calibration,
    PinholeCamera,
    StereoConfig,
    StereoLifter,
    load_calibration,
    stereo_disparities,
)


def _texture(h: int = 240, w: int = 320, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 1.5)
    img = (img - img.min()) / (img.max() - img.min()) * 255
    return img.astype(np.uint8)


def _shift(left: np.ndarray, d: float) -> np.ndarray:
    """Right image of a fronto-parallel plane at disparity d: right(x) = left(x + d)."""
    m = np.array([[1.0, 0.0, d], [0.0, 1.0, 0.0]])
    flags = cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP
    return cv2.warpAffine(left, m, (left.shape[1], left.shape[0]), flags=flags)


def _keypoints(n: int = 60, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(80, 300, n), rng.uniform(10, 230, n)].astype(np.float32)


@pytest.mark.parametrize("d", [17.0, 23.4, 8.7])
@pytest.mark.parametrize("coarse", [True, False])
def test_known_disparity(d: float, coarse: bool) -> None:
    left = _texture()
    right = _shift(left, d)
    cfg = StereoConfig(coarse_to_fine=coarse)
    disp, score = stereo_disparities(left, right, _keypoints(), min_disparity=1, max_disparity=60, config=cfg)
    ok = np.isfinite(disp)
    assert ok.mean() > 0.9
    assert np.abs(disp[ok] - d).max() < 0.25
    assert np.median(np.abs(disp[ok] - d)) < 0.1
    assert (score[ok] > 0.9).all()


def test_lifter_depth_and_noise() -> None:
    cam = PinholeCamera(400.0, 400.0, 160.0, 120.0, 320, 240)
    calib = Calibration.rectified_stereo(cam, 0.1)
    left = _texture()
    right = _shift(left, 20.0)  # z = f B / d = 2 m
    kp = _keypoints()
    pts = StereoLifter(calib).lift(kp, left, right, octaves=np.zeros(len(kp), np.int16))
    ok = pts.valid
    assert ok.mean() > 0.9
    np.testing.assert_allclose(pts.xyz[ok, 2], 2.0, rtol=0.015)  # sub-pixel error < 0.3 px of 20
    # back-projection: x = (u - cx) z / f
    np.testing.assert_allclose(pts.xyz[ok, 0], (kp[ok, 0] - 160.0) * pts.xyz[ok, 2] / 400.0, rtol=1e-4)
    # noise: sigma_z = z^2 sigma_d / (f B) = 4 * 0.3 / 40
    np.testing.assert_allclose(pts.sigma_depth[ok], 0.03, rtol=0.04)
    np.testing.assert_allclose(pts.sigma_lateral[ok], pts.xyz[ok, 2] / 400.0, rtol=1e-4)  # 1 px * z / f


def test_flat_and_occluded_regions_give_nan() -> None:
    left = _texture()
    left[:, :150] = 128  # flat: no texture to match
    right = _shift(left, 15.0)
    right[:, 200:] = _texture(seed=7)[:, 200:]  # these left points are not in the right image
    kp = np.array([[100.0, 120.0], [260.0, 120.0], [280.0, 60.0]], np.float32)
    disp, _ = stereo_disparities(left, right, kp, min_disparity=1, max_disparity=60)
    assert np.isnan(disp[0])
    # points whose right patch was replaced: rejected (or, by chance, matched elsewhere; never 15)
    assert not np.any(np.abs(disp[1:] - 15.0) < 0.5)


def test_degenerate_inputs() -> None:
    left = _texture()
    disp, score = stereo_disparities(left, left, np.zeros((0, 2)), min_disparity=1, max_disparity=30)
    assert disp.shape == (0,) and score.shape == (0,)
    border = np.array([[1.0, 1.0], [319.0, 239.0], [5.0, 120.0]], np.float32)  # too close to the border
    disp, _ = stereo_disparities(left, _shift(left, 10.0), border, min_disparity=1, max_disparity=30)
    assert np.isnan(disp).all()
    with pytest.raises(InputError):
        stereo_disparities(left, left[:100], border, min_disparity=1, max_disparity=30)
    with pytest.raises(InputError):
        stereo_disparities(left, left, border, min_disparity=10, max_disparity=5)
    with pytest.raises(CalibrationError):
        StereoLifter(Calibration(left=PinholeCamera(1.0, 1.0, 0.0, 0.0)))
    cam = PinholeCamera(400.0, 400.0, 160.0, 120.0, 320, 240)
    lifter = StereoLifter(Calibration.rectified_stereo(cam, 0.1))
    assert len(lifter.lift(np.zeros((0, 2), np.float32), left, left)) == 0


def test_kitti_stereo_pair_is_consistent_with_the_baseline() -> None:
    folder = shared_path("kitti", "stereo_pair")
    calib = load_calibration(shared_path("calibration", "KITTI00-02.yaml"))  # bf = 386.1448 px m
    left = cv2.imread(str(folder / "left.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(folder / "right.png"), cv2.IMREAD_GRAYSCALE)
    # a grid on the road ahead (the image's lower middle)
    xs, ys = np.meshgrid(np.arange(420, 760, 12), np.arange(240, 368, 8))
    kp = np.c_[xs.ravel(), ys.ravel()].astype(np.float32)
    pts = StereoLifter(calib).lift(kp, left, right)
    ok = pts.valid
    assert ok.sum() > 100
    assert (pts.xyz[ok, 2] > 0).all()
    # road points lie ~1.65 m below the camera (KITTI's camera height): a baseline off by more
    # than ~15 % would move this median outside the band
    height = np.median(pts.xyz[ok, 1])
    assert 1.35 < height < 1.95
    # and their depth follows the flat-ground prediction z = f h / (v - cy)
    z_flat = calib.left.fy * 1.65 / (kp[ok, 1] - calib.left.cy)
    assert 0.8 < np.median(pts.xyz[ok, 2] / z_flat) < 1.2
    assert (pts.xyz[ok, 2] < 40).all()
