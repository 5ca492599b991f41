"""PnP recovers known random poses; the symmetric refinement; the fundamental matrix."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues.errors import InputError
from stablecues.geometry import (
    PinholeCamera,
    estimate_pose_pnp,
    fundamental_ransac,
    rotation_angle_deg,
)
from stablecues.geometry.pose import _so3_exp

CAM = PinholeCamera(450.0, 450.0, 370.0, 250.0, 752, 480)


def _problem(seed: int, n: int = 120, outliers: float = 0.3, noise_px: float = 0.5):
    rng = np.random.default_rng(seed)
    r = _so3_exp(rng.normal(size=3) * 0.15)
    t = rng.normal(size=3) * 0.3
    xc = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(2, 6, n)]
    xq = xc @ r.T + t
    uq = CAM.project(xq) + rng.normal(size=(n, 2)) * noise_px
    uc = CAM.project(xc) + rng.normal(size=(n, 2)) * noise_px
    bad = rng.random(n) < outliers
    uq[bad] = rng.uniform([0, 0], [752, 480], (int(bad.sum()), 2))
    return r, t, xc, xq, uq, uc, bad


@pytest.mark.parametrize("seed", range(4))
def test_pnp_recovers_a_known_random_pose(seed: int) -> None:
    r, t, xc, _xq, uq, _uc, bad = _problem(seed)
    pose = estimate_pose_pnp(xc, uq, CAM)
    assert pose.success
    assert rotation_angle_deg(pose.rotation.T @ r) < 0.2
    assert np.linalg.norm(pose.translation - t) < 0.02
    # inliers are the correct matches (an outlier can land near its true pixel by chance)
    assert pose.inliers[~bad].mean() > 0.95 and pose.inliers[bad].mean() < 0.1
    assert pose.rmse_px < 1.5
    np.testing.assert_allclose(pose.matrix[:3, :3], pose.rotation)


def test_pnp_with_distortion_and_symmetric_refinement() -> None:
    cam = PinholeCamera(458.654, 457.296, 367.215, 248.375, 752, 480, (-0.28, 0.07, 0.0002, 0.00002))
    rng = np.random.default_rng(3)
    r = _so3_exp(np.array([0.05, -0.2, 0.03]))
    t = np.array([0.3, -0.05, 0.1])
    xc = np.c_[rng.uniform(-1.5, 1.5, (80, 2)), rng.uniform(2, 5, 80)]
    xq = xc @ r.T + t
    uq = cam.project(xq) + rng.normal(size=(80, 2)) * 0.3
    uc = cam.project(xc) + rng.normal(size=(80, 2)) * 0.3
    xq_noisy = xq.copy()
    xq_noisy[::3] = np.nan  # some query points without depth
    pose = estimate_pose_pnp(xc, uq, cam, points_query=xq_noisy, pixels_candidate=uc)
    assert rotation_angle_deg(pose.rotation.T @ r) < 0.1
    assert np.linalg.norm(pose.translation - t) < 0.01
    assert pose.n_inliers >= 75


def test_pnp_degenerate_inputs() -> None:
    pose = estimate_pose_pnp(np.zeros((3, 3)) + [0, 0, 1], np.zeros((3, 2)), CAM)
    assert not pose.success and pose.inliers.shape == (3,)
    pose = estimate_pose_pnp(np.full((10, 3), np.nan), np.zeros((10, 2)), CAM)
    assert not pose.success
    assert not estimate_pose_pnp(np.zeros((0, 3)), np.zeros((0, 2)), CAM).success
    with pytest.raises(InputError):
        estimate_pose_pnp(np.zeros((5, 3)), np.zeros((4, 2)), CAM)
    with pytest.raises(InputError):
        estimate_pose_pnp(np.zeros((5, 3)), np.zeros((5, 2)), CAM, points_query=np.zeros((5, 3)))


def test_fundamental_matrix() -> None:
    r, t, xc, xq, uq, uc, bad = _problem(11, outliers=0.2, noise_px=0.3)
    f, inliers = fundamental_ransac(uq, uc, threshold_px=2.0)
    assert f is not None
    assert inliers[~bad].mean() > 0.9
    # x_q^T F x_c = 0 on the correct matches
    hq = np.c_[uq, np.ones(len(uq))]
    hc = np.c_[uc, np.ones(len(uc))]
    lines = hc @ f.T
    dist = np.abs(np.sum(hq * lines, axis=1)) / np.linalg.norm(lines[:, :2], axis=1)
    assert np.median(dist[~bad]) < 1.0
    f, inliers = fundamental_ransac(uq[:5], uc[:5])
    assert f is None and inliers.shape == (5,) and not inliers.any()
