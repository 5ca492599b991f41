"""The triangle check: rigid motions pass, non-rigid changes fail, degenerate triangles are skipped."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues.errors import ConfigError, InputError
from stablecues.geometry import NoiseModel, Points3D, TriangleConfig, check_triangles, side_sigma
from stablecues.geometry.pose import _so3_exp

NOISE = NoiseModel.stereo(450.0, 0.11)  # EuRoC-like: sigma_z = z^2 * 0.3 / 49.5


def _scene(n: int = 60, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-1.5, 1.5, (n, 2)), rng.uniform(1.5, 4.0, n)]


def _rigid(x: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    r = _so3_exp(rng.normal(size=3) * 0.2)
    t = rng.normal(size=3) * 0.3
    return x @ r.T + t


def _noisy(x: np.ndarray, seed: int) -> Points3D:
    """Points perturbed as the noise model says (depth along the ray, lateral)."""
    rng = np.random.default_rng(seed)
    clean = NOISE.points(x)
    ray = x / x[:, 2:3]
    noisy = x + ray * (clean.sigma_depth[:, None] * rng.normal(size=(len(x), 1)))
    noisy[:, :2] += clean.sigma_lateral[:, None] * rng.normal(size=(len(x), 2))
    return NOISE.points(noisy)


@pytest.mark.parametrize("seed", range(5))
def test_rigid_motion_is_accepted(seed: int) -> None:
    cand = _scene(seed=seed)
    query = _rigid(cand, seed + 100)
    res = check_triangles(_noisy(query, seed + 1), _noisy(cand, seed + 2))
    assert res.n_checked == 10
    assert res.n_agree >= 9  # a correct side fails the 3-sigma gate with p = 0.27 %


def test_non_rigid_change_is_rejected() -> None:
    cand = _scene(seed=3)
    query = _rigid(cand, 7)
    rng = np.random.default_rng(5)
    bent = query + rng.normal(size=query.shape) * 0.4  # every point moved by ~0.4 m
    res = check_triangles(NOISE.points(bent), NOISE.points(cand))
    assert res.n_agree <= 1
    # a wrong correspondence (shuffled matches) breaks triangles as well
    perm = rng.permutation(len(query))
    assert check_triangles(NOISE.points(query[perm]), NOISE.points(cand)).n_agree <= 1


def test_relative_tolerance_by_hand() -> None:
    tri = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [0.0, 1.0, 2.0]])
    scaled = tri * np.array([1.015, 1.015, 1.0])  # x and y sides 1.5 % longer
    cfg = TriangleConfig(n_triangles=1, tolerance="relative", relative_tolerance=0.02, min_side_sigma=0.0)
    pts = lambda x: Points3D(x.astype(np.float32), np.zeros(3, np.float32), np.zeros(3, np.float32))  # noqa: E731
    res = check_triangles(pts(scaled), pts(tri), cfg)
    assert res.n_agree == 1
    np.testing.assert_allclose(res.triangles[0].sides_candidate, [1.0, np.sqrt(2), 1.0], rtol=1e-6)
    np.testing.assert_allclose(res.triangles[0].allowed[0], 0.02 * (1.015 + 1.0) / 2, rtol=1e-6)
    worse = tri * np.array([1.03, 1.03, 1.0])
    assert check_triangles(pts(worse), pts(tri), cfg).n_agree == 0


def test_degenerate_triangles_are_skipped_and_replaced() -> None:
    p = np.array(
        [
            [0.0, 0.0, 2.0],
            [1.0, 0.0, 2.0],
            [2.0, 0.001, 2.0],  # collinear with the first two
            [1.0, 0.0, 2.0],  # the same point as the second
            [np.nan, np.nan, np.nan],  # no depth
            [0.2, 1.0, 2.5],
        ]
    )
    pts = NOISE.points(p)
    res = check_triangles(pts, pts, TriangleConfig(n_triangles=1))
    assert res.n_usable == 5
    assert res.triangles[0].matches == (0, 1, 5)
    assert dict(res.skipped) == {2: "collinear", 3: "too_close"}
    assert res.n_agree == 1


def test_empty_and_mismatched_inputs() -> None:
    res = check_triangles(Points3D.empty(0), Points3D.empty(0))
    assert res.n_checked == 0 and res.n_agree == 0 and res.triangles == ()
    assert check_triangles(Points3D.empty(5), Points3D.empty(5)).n_usable == 0
    with pytest.raises(InputError):
        check_triangles(Points3D.empty(2), Points3D.empty(3))
    with pytest.raises(ConfigError):
        TriangleConfig(tolerance="fixed")


def test_side_sigma_by_hand() -> None:
    # two points at the same depth on the x axis: the side is lateral, its sigma the lateral ones
    x = np.array([[-0.5, 0.0, 2.0], [0.5, 0.0, 2.0]])
    sd = np.array([0.1, 0.1])
    sl = np.array([0.01, 0.02])
    s = side_sigma(x, sd, sl, np.array([0]), np.array([1]))
    # u = (-1, 0, 0); r0 = (-0.25, 0, 1): u.r0 = 0.25; r1 = (0.25, 0, 1): u.r1 = -0.25
    expected = np.sqrt(0.1**2 * 0.25**2 * 2 + 0.01**2 + 0.02**2)
    assert s[0] == pytest.approx(expected)


def _relative(p: Points3D) -> Points3D:
    return Points3D(p.xyz, p.sigma_depth, p.sigma_lateral, metric=False)


def _scaled(points: Points3D, s: float) -> Points3D:
    return Points3D((points.xyz * s).astype(np.float32), (points.sigma_depth * s).astype(np.float32),
                    (points.sigma_lateral * s).astype(np.float32), metric=False)


SIMILAR = TriangleConfig(tolerance="similar")


def test_a_scaled_and_rotated_copy_is_similar() -> None:
    """Monocular reconstructions differ by a similarity: same shapes, one scale for all."""
    cand = _scene(seed=3)
    query = _rigid(cand, 7)
    q = _scaled(_noisy(query, 1), 0.37)  # the query's reconstruction in its own unit
    c = _relative(_noisy(cand, 2))
    res = check_triangles(q, c, SIMILAR)
    assert res.n_checked == 10 and res.n_agree >= 9
    scales = [t.scale for t in res.triangles if t.agree]
    assert np.allclose(scales, 0.37, rtol=0.1)
    # the metric check of the same points fails: the sides differ by the scale
    assert check_triangles(q, c, TriangleConfig()).n_agree == 0


def test_a_perturbed_copy_is_not_similar() -> None:
    cand = _scene(seed=4)
    query = _rigid(cand, 8)
    rng = np.random.default_rng(0)
    warped = query.copy()
    warped[:, :2] += rng.normal(0, 0.4, (len(query), 2))  # a different shape (40 cm per point)
    res = check_triangles(_scaled(_noisy(warped, 1), 2.0), _relative(_noisy(cand, 2)), SIMILAR)
    assert res.n_checked >= 5 and res.n_agree <= 1


def test_similar_shapes_at_another_scale_do_not_agree() -> None:
    """Two triangles of the right shape but of scales 1 and 3: one similarity cannot map both."""
    cand = _scene(seed=5)
    q = _noisy(_rigid(cand, 9), 1)
    xyz = q.xyz.copy()
    xyz[3:6] *= 3.0  # the second triangle (matches 3-5), alone, is three times larger
    q3 = Points3D(xyz, q.sigma_depth, q.sigma_lateral, metric=False)
    config = TriangleConfig(tolerance="similar", n_triangles=3, min_side_sigma=0.0, min_angle_deg=0.0)
    res = check_triangles(q3, _relative(_noisy(cand, 2)), config)
    assert [t.agree for t in res.triangles] == [True, False, True]


def test_matches_enter_triangles_in_the_order_given() -> None:
    """``order`` decides which matches form the triangles; positions still refer to the list."""
    cand = _scene(seed=4)
    query = _rigid(cand, 9)
    query[:30] += np.random.default_rng(2).normal(size=(30, 3)) * 0.5  # the first 30 moved
    q, c = NOISE.points(query), NOISE.points(cand)
    cfg = TriangleConfig(n_triangles=5)
    assert check_triangles(q, c, cfg).n_agree <= 1
    last = np.r_[30:60, 0:30]  # the moved ones last
    res = check_triangles(q, c, cfg, order=last)
    assert res.n_agree == 5 and all(min(t.matches) >= 30 for t in res.triangles)
    same = check_triangles(q, c, cfg, order=np.arange(60))
    assert [t.matches for t in same.triangles] == [t.matches for t in check_triangles(q, c, cfg).triangles]
    for bad in (np.arange(59), np.r_[0, 0:59], np.arange(1, 61)):
        with pytest.raises(InputError, match="permutation"):
            check_triangles(q, c, cfg, order=bad)
