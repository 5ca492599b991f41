"""Two-view triangulation of monocular frames: shape up to scale, sigmas, real EuRoC frames."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import shared_path
from stablecues.detection import FramePreparer, preset
from stablecues.errors import ConfigError
from stablecues.geometry import PinholeCamera, load_euroc_stereo
from stablecues.geometry.rotations import quat_from_rotvec, quat_to_matrix
from stablecues.geometry.twoview import (
    GUESSED_FOCAL_FACTOR,
    TwoViewConfig,
    guess_camera,
    triangulate_two_view,
)
from stablecues.imageio import read_image
from stablecues.types import Frame
from stablecues.verification.matching import match_features
from stablecues.vocabulary import default_vocabulary

CAM = PinholeCamera(400.0, 400.0, 240.0, 180.0, 480, 360)


def _views(seed: int, n: int = 300, noise: float = 0.3, forward: float = 0.3):
    rng = np.random.default_rng(seed)
    x = np.c_[rng.uniform(-4, 4, n), rng.uniform(-2, 2, n), rng.uniform(4, 15, n)]
    rot = quat_to_matrix(quat_from_rotvec(np.array([0.0, 0.05, 0.01])))
    t = np.array([0.5, 0.0, forward])
    xa = x @ CAM.K.T
    xb = (x @ rot.T + t) @ CAM.K.T
    pa = xa[:, :2] / xa[:, 2:] + rng.normal(0, noise, (n, 2))
    pb = xb[:, :2] / xb[:, 2:] + rng.normal(0, noise, (n, 2))
    return x, rot, t, pa, pb


@pytest.mark.parametrize("seed", range(3))
def test_known_structure_is_recovered_up_to_scale(seed: int) -> None:
    x, rot, t, pa, pb = _views(seed)
    tv = triangulate_two_view(pa, pb, CAM)
    assert tv.ok and tv.reason == "" and tv.n_inliers > 250
    assert tv.rotation is not None and tv.translation is not None
    np.testing.assert_allclose(tv.rotation, rot, atol=5e-3)
    np.testing.assert_allclose(tv.translation, t / np.linalg.norm(t), atol=2e-2)
    ok = tv.points.valid
    assert ok.sum() > 250 and not tv.points.metric
    scale = np.linalg.norm(t)  # monocular points are in units of the baseline
    rel = np.abs(tv.points.xyz[ok] * scale - x[ok]).max(axis=1) / x[ok, 2]
    assert np.median(rel) < 0.05
    # the propagated depth sigma covers the real error (about 3 sigma for nearly all points)
    z_err = np.abs(tv.points.xyz[ok, 2] * scale - x[ok, 2])
    assert np.mean(z_err <= 3 * tv.points.sigma_depth[ok] * scale) > 0.95


def test_too_little_parallax_and_too_few_matches() -> None:
    x, rot, _, pa, _ = _views(0)
    xb = (x @ rot.T + np.array([1e-4, 0.0, 0.0])) @ CAM.K.T  # the camera hardly moved
    tv = triangulate_two_view(pa, xb[:, :2] / xb[:, 2:], CAM)
    assert not tv.ok and not tv.points.valid.any()
    assert "parallax" in tv.reason or "translation" in tv.reason or "inliers" in tv.reason
    tv = triangulate_two_view(pa[:10], pa[:10], CAM, TwoViewConfig(min_inliers=30))
    assert not tv.ok and "10 matches" in tv.reason and len(tv.points) == 10


def test_ransac_iterations_follow_the_share_of_inliers_a_pair_needs() -> None:
    cfg = TwoViewConfig(min_inliers=30, confidence=0.999, max_iterations=1000, iteration_margin=4.0)
    counts = [cfg.iterations(m) for m in (5, 30, 31, 37, 50, 78, 200)]
    assert counts == sorted(counts) and counts[0] == counts[1] == 4 and counts[-1] == 1000
    # 37 matches with 30 inliers needed: 0.81^5 of the samples are all inliers
    share = 30 / 37
    assert counts[3] == int(np.ceil(4.0 * np.log(0.001) / np.log1p(-(share**5))))
    for margin in (0.5, float("inf"), float("nan")):
        with pytest.raises(ConfigError):
            TwoViewConfig(iteration_margin=margin)


@pytest.mark.parametrize("seed", range(3))
def test_fewer_iterations_give_the_same_pose_when_the_pair_has_its_inliers(seed: int) -> None:
    """USAC stops by its own rule on a good pair, before the cap: the same points and pose as
    with 1000 iterations; a pair with too few inliers fails both ways."""
    _, _, _, pa, pb = _views(seed, n=45, noise=0.4)
    for m in (45, 36, 30):
        a = triangulate_two_view(pa[:m], pb[:m], CAM, TwoViewConfig(min_inliers=30))
        b = triangulate_two_view(pa[:m], pb[:m], CAM, TwoViewConfig(min_inliers=30, iteration_margin=1e9))
        assert a.ok and b.ok and a.n_inliers == b.n_inliers
        if m > 30:
            np.testing.assert_array_equal(a.points.xyz, b.points.xyz)
        else:  # every match must be an inlier: 4 iterations, where USAC polishes longer up to 1000
            np.testing.assert_allclose(a.points.xyz, b.points.xyz, rtol=1e-3)
    rng = np.random.default_rng(seed)
    junk = rng.uniform(0, 400, (40, 2))  # 40 random pairs: no 30 of them fit one motion
    assert not triangulate_two_view(pa[:40], junk, CAM, TwoViewConfig(min_inliers=30)).ok


def test_guessed_camera() -> None:
    cam = guess_camera(640, 480)
    assert cam.fx == cam.fy == GUESSED_FOCAL_FACTOR * 640 and (cam.cx, cam.cy) == (320.0, 240.0)


@pytest.mark.parametrize(("current", "neighbour"), [(1, 0), (0, 1), (3, 2), (2, 3)])
def test_euroc_monocular_points_agree_in_shape_with_stereo(current: int, neighbour: int) -> None:
    """Real EuRoC V1 left frames a few decimetres apart: the features triangulated from the
    motion alone agree with the stereo points of the same features once scale-aligned.

    (The frames of ``euroc/V1_01_micro`` cannot serve: the drone stands on the ground for the
    whole excerpt, its ground truth moves less than 1 mm between frames, so there is no parallax.)
    """
    root = shared_path("euroc", "loop_pairs")
    calib = load_euroc_stereo(root / "sensorLeft.yaml", root / "sensorRight.yaml")
    prep = FramePreparer(preset("fast", {"features": {"n_features": 2000}}), default_vocabulary(), calib)

    def frame(i: int) -> Frame:
        left, right = (read_image(root / f"{side}_img_{i}.png", "grey") for side in ("left", "right"))
        return Frame(index=i, name=str(i), timestamp=float(i), image=left, right=right)

    a, b = prep.prepare(frame(current)), prep.prepare(frame(neighbour))
    m = match_features(a.features, b.features, a.fvec, b.fvec, ratio=0.8)
    tv = triangulate_two_view(a.features.keypoints[m.query], b.features.keypoints[m.candidate], calib.left)
    assert tv.ok, tv.reason
    assert a.points is not None and a.points.metric and not tv.points.metric
    stereo = a.points.xyz[m.query]
    both = tv.points.valid & a.points.valid[m.query]
    assert both.sum() >= 50
    scale = np.median(stereo[both, 2] / tv.points.xyz[both, 2])  # the baseline in metres
    assert 0.1 < scale < 1.0  # the loop pairs are a few decimetres apart
    err = np.linalg.norm(tv.points.xyz[both] * scale - stereo[both], axis=1) / stereo[both, 2]
    assert np.median(err) < 0.08


def test_bad_settings_name_the_field() -> None:
    from stablecues.detection.config import MonocularConfig

    with pytest.raises(ConfigError, match="min_inliers must be >= 5"):
        TwoViewConfig(min_inliers=2)
    with pytest.raises(ConfigError, match="^monocular: threshold_px must be > 0, got -1"):
        MonocularConfig(threshold_px=-1)  # checked with the detector's settings, not at a frame


def test_a_failure_says_whether_more_baseline_may_help() -> None:
    """Too little parallax or translation: a neighbour further back may do; too few matches or
    matches that fit no one motion: it will not."""
    x, rot, _, pa, pb = _views(0)
    assert triangulate_two_view(pa, pb, CAM).ok
    xb = (x @ rot.T + np.array([1e-4, 0.0, 0.0])) @ CAM.K.T  # the camera hardly moved
    still = triangulate_two_view(pa, xb[:, :2] / xb[:, 2:], CAM)
    assert not still.ok and still.baseline_limited
    junk = np.random.default_rng(0).uniform(0, 400, (40, 2))
    assert not triangulate_two_view(pa[:40], junk, CAM, TwoViewConfig(min_inliers=30)).baseline_limited
    assert not triangulate_two_view(pa[:10], pb[:10], CAM, TwoViewConfig(min_inliers=30)).baseline_limited
