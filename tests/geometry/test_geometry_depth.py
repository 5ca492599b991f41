"""Lifting with depth images and map points."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues.errors import InputError
from stablecues.geometry import (
    KINECT_DEPTH_COEFF,
    DepthConfig,
    NoiseModel,
    PinholeCamera,
    depth_to_metres,
    lift_depth,
    lift_map_points,
)

CAM = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)


def _plane_depth(z: float = 2.0) -> np.ndarray:
    depth = np.full((480, 640), int(z * 1000), np.uint16)
    depth[:, :8] = 0  # zero border, as a Kinect gives
    depth[100:120, 300:320] = 0  # a hole
    depth[300:, 500:] = 4000  # a step to 4 m
    return depth


def test_plane_is_lifted_with_kinect_noise() -> None:
    kp = np.array([[320.0, 240.0], [100.0, 50.0], [600.0, 100.0]], np.float32)
    pts = lift_depth(kp, _plane_depth(), CAM, depth_scale=1000.0, octaves=np.array([0, 1, 2]))
    assert pts.valid.all()
    np.testing.assert_allclose(pts.xyz[:, 2], 2.0)
    np.testing.assert_allclose(pts.xyz[1], [(100 - 320) * 2 / 500, (50 - 240) * 2 / 500, 2.0], rtol=1e-6)
    np.testing.assert_allclose(pts.sigma_depth, KINECT_DEPTH_COEFF * 4.0, rtol=1e-6)
    np.testing.assert_allclose(pts.sigma_lateral, 1.2 ** np.array([0, 1, 2]) * 2.0 / 500.0, rtol=1e-5)


def test_holes_border_and_discontinuities_give_nan() -> None:
    kp = np.array(
        [
            [3.0, 200.0],  # zero border
            [310.0, 110.0],  # in the hole
            [500.0, 300.0],  # on the 2 m / 4 m step
            [501.0, 301.0],  # one pixel inside the step: still within 2 px of it
            [560.0, 400.0],  # well inside the 4 m region
            [700.0, 10.0],  # outside the image
        ],
        np.float32,
    )
    pts = lift_depth(kp, _plane_depth(), CAM, depth_scale=1000.0)
    np.testing.assert_array_equal(pts.valid, [False, False, False, False, True, False])
    assert pts.xyz[4, 2] == pytest.approx(4.0)
    loose = DepthConfig(max_relative_step=2.0)
    relaxed = lift_depth(kp, _plane_depth(), CAM, depth_scale=1000.0, config=loose)
    assert relaxed.valid[2]


def test_depth_inputs() -> None:
    m = depth_to_metres(np.array([[0.0, 1.5], [np.nan, -1.0]], np.float32), None)
    assert m[0, 1] == 1.5 and np.isnan(m[0, 0]) and np.isnan(m[1]).all()
    with pytest.raises(InputError, match="depth scale"):
        depth_to_metres(np.ones((4, 4), np.uint16), None)
    with pytest.raises(InputError, match="like the camera"):
        lift_depth(np.zeros((1, 2), np.float32), np.ones((10, 10), np.uint16), CAM, depth_scale=1000.0)
    assert len(lift_depth(np.zeros((0, 2), np.float32), _plane_depth(), CAM, depth_scale=1000.0)) == 0


def test_map_points_pass_through() -> None:
    noise = NoiseModel.stereo(500.0, 0.1)
    xyz = np.array([[0.1, 0.2, 3.0], [np.nan, 0.0, 1.0], [0.0, 0.0, -2.0], [1.0, 1.0, 5.0]])
    pts = lift_map_points(xyz, noise, sigma_depth=np.array([0.05, np.nan, np.nan, np.nan]))
    np.testing.assert_array_equal(pts.valid, [True, False, False, True])
    np.testing.assert_allclose(pts.xyz[0], [0.1, 0.2, 3.0], rtol=1e-6)
    assert pts.sigma_depth[0] == pytest.approx(0.05)  # the SLAM system's own sigma
    assert pts.sigma_depth[3] == pytest.approx(25 * 0.3 / 50.0)  # the model's
    with pytest.raises(InputError):
        lift_map_points(np.zeros((3, 2)), noise)
    with pytest.raises(InputError):
        lift_map_points(np.zeros((3, 3), np.int32), noise)
