"""Pinhole camera: projection round trips, undistortion, invalid values."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues.errors import CalibrationError, InputError
from stablecues.geometry import Calibration, PinholeCamera

EUROC_LEFT = PinholeCamera(
    458.654, 457.296, 367.215, 248.375, 752, 480, (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
)


def test_k_matrix_by_hand() -> None:
    cam = PinholeCamera(500.0, 510.0, 320.0, 240.0)
    np.testing.assert_array_equal(cam.K, [[500, 0, 320], [0, 510, 240], [0, 0, 1]])
    np.testing.assert_array_equal(cam.dist, np.zeros(5))
    assert not cam.has_distortion
    assert cam.image_size is None


def test_project_by_hand() -> None:
    cam = PinholeCamera(500.0, 500.0, 320.0, 240.0)
    px = cam.project(np.array([[1.0, -0.5, 2.0], [0.0, 0.0, -1.0]]))
    np.testing.assert_allclose(px[0], [320 + 250, 240 - 125])
    assert np.isnan(px[1]).all()  # behind the camera


@pytest.mark.parametrize("cam", [PinholeCamera(400.0, 410.0, 300.0, 200.0), EUROC_LEFT])
def test_unproject_project_round_trip(cam: PinholeCamera) -> None:
    rng = np.random.default_rng(0)
    pixels = rng.uniform([60, 60], [690, 420], size=(50, 2))
    depth = rng.uniform(0.5, 10.0, 50)
    pts = cam.unproject(pixels, depth)
    np.testing.assert_allclose(pts[:, 2], depth)
    np.testing.assert_allclose(cam.project(pts), pixels, atol=1e-3)


def test_undistort_points_matches_ideal_projection() -> None:
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-1, 1, (20, 2)), np.full(20, 3.0)]
    distorted = EUROC_LEFT.project(pts)
    ideal = PinholeCamera(EUROC_LEFT.fx, EUROC_LEFT.fy, EUROC_LEFT.cx, EUROC_LEFT.cy).project(pts)
    np.testing.assert_allclose(EUROC_LEFT.undistort_points(distorted), ideal, atol=1e-3)


def test_empty_inputs() -> None:
    assert EUROC_LEFT.unproject(np.zeros((0, 2)), np.zeros(0)).shape == (0, 3)
    assert EUROC_LEFT.project(np.zeros((0, 3))).shape == (0, 2)


def test_invalid_values_raise() -> None:
    with pytest.raises(CalibrationError, match="focal"):
        PinholeCamera(-1.0, 1.0, 0.0, 0.0)
    with pytest.raises(CalibrationError, match="distortion"):
        PinholeCamera(1.0, 1.0, 0.0, 0.0, distortion=(0.1, 0.2, 0.3))
    with pytest.raises(InputError, match="depth"):
        EUROC_LEFT.unproject(np.zeros((3, 2)), np.zeros(2))
    with pytest.raises(CalibrationError, match="orthonormal"):
        Calibration(left=EUROC_LEFT, right=EUROC_LEFT, rotation=np.ones((3, 3)), translation=np.zeros(3))


def test_rectified_stereo_baseline() -> None:
    cal = Calibration.rectified_stereo(PinholeCamera(700.0, 700.0, 600.0, 180.0), 0.5)
    assert cal.is_stereo and cal.rectified
    assert cal.baseline == pytest.approx(0.5)
    assert cal.bf == pytest.approx(350.0)
    np.testing.assert_allclose(cal.translation, [-0.5, 0, 0])
