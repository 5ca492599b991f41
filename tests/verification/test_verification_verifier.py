"""The Verifier on synthetic scenes: accepted under a rigid motion, rejected otherwise, fallbacks."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from stablecues.config import merge
from stablecues.errors import ConfigError, InputError
from stablecues.geometry import NoiseModel, PinholeCamera, Points3D, rotation_angle_deg
from stablecues.geometry.pose import _so3_exp
from stablecues.types import BowVector, Entry, Features, FeatureVector
from stablecues.verification import Method, Status, VerificationConfig, Verifier, View, preset
from stablecues.verification.matching import Matches
from stablecues.verification.result import Verification

CAM = PinholeCamera(450.0, 450.0, 376.0, 240.0, 752, 480)
NOISE = NoiseModel.stereo(450.0, 0.11)


def _features(kp: np.ndarray, desc: np.ndarray) -> Features:
    n = len(kp)
    return Features(
        keypoints=kp.astype(np.float32),
        descriptors=desc,
        octaves=np.zeros(n, np.int16),
        angles=np.zeros(n, np.float32),
        responses=np.ones(n, np.float32),
        sizes=np.full(n, 31.0, np.float32),
        image_size=(752, 480),
    )


def _noisy(x: np.ndarray, rng: np.random.Generator) -> Points3D:
    clean = NOISE.points(x)
    noisy = x + (x / x[:, 2:3]) * (clean.sigma_depth[:, None] * rng.normal(size=(len(x), 1)))
    return NOISE.points(noisy)


def _scene(seed: int = 0, n: int = 150, rigid: bool = True, wrong: float = 0.15, swapped: float = 0.0):
    """Candidate and query views of one scene; ``wrong`` of the query descriptors are unrelated
    (no match), ``swapped`` are exchanged between features (wrong matches)."""
    rng = np.random.default_rng(seed)
    rot = _so3_exp(rng.normal(size=3) * 0.1)
    t = rng.normal(size=3) * 0.3
    xc = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(2, 5, n)]
    xq = xc @ rot.T + t
    if not rigid:  # a different geometry seen with the same descriptors
        xq = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(2, 5, n)]
    uc, uq = CAM.project(xc), CAM.project(xq)
    inside = np.isfinite(uq).all(1) & (uq[:, 0] > 0) & (uq[:, 0] < 752) & (uq[:, 1] > 0) & (uq[:, 1] < 480)
    xc, xq, uc, uq = xc[inside], xq[inside], uc[inside], uq[inside]
    m = len(xc)
    desc_c = rng.integers(0, 256, (m, 32), dtype=np.uint8)
    desc_q = desc_c.copy()
    for row in desc_q:  # ~10 bits flipped per descriptor
        idx = rng.choice(256, 10, replace=False)
        np.bitwise_xor.at(row, idx // 8, (1 << (idx % 8)).astype(np.uint8))
    bad = rng.random(m) < wrong
    desc_q[bad] = rng.integers(0, 256, (int(bad.sum()), 32), dtype=np.uint8)
    swap = np.flatnonzero(~bad & (rng.random(m) < swapped))
    desc_q[swap] = desc_q[np.roll(swap, 1)]
    perm = rng.permutation(m)  # the query lists its features in another order
    q = View(_features(uq[perm] + rng.normal(size=(m, 2)) * 0.3, desc_q[perm]), None, _noisy(xq[perm], rng))
    c = View(_features(uc, desc_c), None, _noisy(xc, rng))
    return q, c, rot, t


@pytest.mark.parametrize("seed", range(3))
def test_rigid_scene_is_accepted_with_its_pose(seed: int) -> None:
    q, c, rot, t = _scene(seed)
    res = Verifier(camera=CAM).verify(q, c)
    assert res.accepted and res.status is Status.ACCEPTED and res.method is Method.TRIANGLES
    assert not res.fallback
    assert res.n_triangles_agree >= 2 and len(res.triangles) == 10
    assert res.rotation is not None and res.translation is not None
    assert rotation_angle_deg(res.rotation.T @ rot) < 0.5
    assert np.linalg.norm(res.translation - t) < 0.05
    assert res.n_inliers >= 20 and res.inliers.shape == (res.n_matches,)
    assert res.pose is not None and res.pixels_query is not None
    np.testing.assert_array_equal(res.pixels_query, q.features.keypoints[res.matches.query])
    assert set(res.timings) >= {"matching", "triangles", "pnp", "total"}
    json.dumps(res.to_dict())  # JSON-serialisable


@pytest.mark.parametrize("seed", range(3))
def test_non_rigid_scene_is_rejected(seed: int) -> None:
    q, c, _, _ = _scene(seed, rigid=False)
    res = Verifier(camera=CAM).verify(q, c)
    assert not res.accepted
    assert res.status is Status.TRIANGLES_DISAGREE
    assert res.n_triangles_agree <= 1
    assert res.rotation is None


def test_fallbacks_without_3d() -> None:
    q, c, rot, _ = _scene(4)
    v = Verifier(camera=CAM)
    res = v.verify(View(q.features), View(c.features))
    assert res.fallback and res.method is Method.FUNDAMENTAL and res.accepted
    assert res.fundamental is not None and res.n_inliers >= 12
    res = v.verify(View(q.features), c)  # only the candidate has 3D: PnP
    assert res.fallback and res.method is Method.PNP and res.accepted
    assert rotation_angle_deg(res.rotation.T @ rot) < 0.5
    strict = Verifier(merge(VerificationConfig(), {"fallback": False}), camera=CAM)
    res = strict.verify(View(q.features), View(c.features))
    assert not res.accepted and res.status is Status.TOO_FEW_3D


def test_classic_verifiers() -> None:
    q, c, _, _ = _scene(5)
    res = Verifier(preset("pnp"), camera=CAM).verify(q, c)
    assert res.accepted and res.method is Method.PNP and not res.fallback
    res = Verifier(preset("dloop"), camera=CAM).verify(q, c)
    assert res.accepted and res.method is Method.FUNDAMENTAL and not res.fallback
    qn, cn, _, _ = _scene(5, rigid=False)
    assert not Verifier(preset("pnp"), camera=CAM).verify(qn, cn).accepted
    assert not Verifier(preset("dloop"), camera=CAM).verify(qn, cn).accepted


def test_fundamental_inlier_ratio() -> None:
    """A loop needs max(min_fundamental_inliers, ratio * matches) inliers; with many swapped
    matches the count passes and the ratio does not."""
    q, c, _, _ = _scene(6, wrong=0.0, swapped=0.7)
    loose = Verifier(merge(preset("default"), {"method": "fundamental", "min_fundamental_ratio": 0.0}), CAM)
    res = loose.verify(q, c)
    assert res.accepted and res.n_inliers >= 20
    ratio = res.n_inliers / res.n_matches
    assert ratio < 0.9
    need = round(ratio + 0.05, 2)
    strict = Verifier(merge(loose.config, {"min_fundamental_ratio": need}), CAM).verify(q, c)
    assert not strict.accepted and strict.status is Status.TOO_FEW_FUNDAMENTAL_INLIERS
    assert f"need {need:.0%}" in strict.reason
    for method in ("ransac", "usac"):
        cfg = merge(loose.config, {"fundamental_method": method})
        assert Verifier(cfg, CAM).verify(q, c).accepted


def test_acceptance_rules() -> None:
    q, c, _, _ = _scene(6, swapped=0.25)  # many wrong matches: some triangles must disagree
    base = Verifier(camera=CAM).verify(q, c)
    assert 2 <= base.n_triangles_agree < 10
    all_rule = Verifier(preset("default", acceptance="all"), camera=CAM).verify(q, c)
    assert not all_rule.accepted and all_rule.status is Status.TRIANGLES_DISAGREE
    need = base.n_triangles_agree + 1
    at_least = Verifier(preset("default", min_agree=need), camera=CAM).verify(q, c)
    assert not at_least.accepted


def test_too_few_matches_and_empty_frames() -> None:
    empty = View(Features.empty((752, 480)), None, Points3D.empty(0))
    res = Verifier(camera=CAM).verify(empty, empty)
    assert not res.accepted and res.status is Status.TOO_FEW_MATCHES
    assert res.n_matches == 0 and res.inliers.shape == (0,)
    assert res.pixels_query is not None and res.pixels_query.shape == (0, 2)


def test_database_entry_with_stored_points() -> None:
    q, c, _, _ = _scene(7)
    entry = Entry(
        entry_id=3,
        bow=BowVector.empty(),
        fvec=FeatureVector(np.zeros(len(c.features), np.int32), 3),
        features=c.features,
        points3d=c.points.xyz if c.points is not None else None,
    )
    qv = View(q.features, FeatureVector(np.zeros(len(q.features), np.int32), 3), q.points)
    res = Verifier(camera=CAM, noise=NOISE).verify_entry(qv, entry)
    assert res.accepted
    with pytest.raises(ConfigError, match="NoiseModel"):
        Verifier(camera=CAM).verify_entry(qv, entry)


def test_settings_are_validated() -> None:
    with pytest.raises(ConfigError):
        VerificationConfig(method="homography")
    with pytest.raises(ConfigError):
        VerificationConfig(acceptance="most")
    with pytest.raises(ConfigError):
        VerificationConfig(min_agree=11)
    with pytest.raises(ConfigError):
        preset("nope")
    with pytest.raises(ConfigError):
        preset("default", triangles=3)  # a typo of n_triangles
    with pytest.raises(ConfigError, match="camera"):
        Verifier(VerificationConfig())
    assert Verifier(preset("paper")).config.tolerance == "relative"  # no PnP gate: no camera needed


def _monocular(view: View, scale: float) -> View:
    p = view.points
    assert p is not None
    pts = Points3D((p.xyz * scale).astype(np.float32), (p.sigma_depth * scale).astype(np.float32),
                   (p.sigma_lateral * scale).astype(np.float32), metric=False)
    return View(view.features, view.fvec, pts)


def test_monocular_points_are_checked_by_similar_triangles() -> None:
    q, c, _, _ = _scene(7)
    v = Verifier(preset("default"), camera=CAM, noise=NOISE)
    res = v.verify(_monocular(q, 0.4), _monocular(c, 2.5))
    assert res.accepted and res.method is Method.SIMILAR_TRIANGLES and not res.fallback
    assert "similar triangles agree" in res.reason
    assert res.rotation is not None  # PnP on the candidate's own reconstruction
    qn, cn, _, _ = _scene(7, rigid=False)
    bad = v.verify(_monocular(qn, 0.4), _monocular(cn, 2.5))
    assert not bad.accepted
    # one metric side and one monocular side: only shapes can be compared
    assert v.verify(q, _monocular(c, 2.5)).method is Method.SIMILAR_TRIANGLES


def test_monocular_candidate_without_query_points_falls_back_to_fundamental() -> None:
    q, c, _, _ = _scene(8)
    res = Verifier(preset("default"), camera=CAM, noise=NOISE).verify(View(q.features), _monocular(c, 2.0))
    assert res.method is Method.FUNDAMENTAL and res.fallback


def _moving_objects(seed: int = 3, n: int = 120, moving: int = 30) -> tuple[View, View]:
    """Two views of a scene whose first ``moving`` features moved between the visits, each its own
    way (people, cars), with the closest descriptors of all and weights of a dynamic class."""
    rng = np.random.default_rng(seed)
    xc = np.c_[rng.uniform(-1.2, 1.2, (n, 2)), rng.uniform(2, 5, n)]
    xq = xc + np.array([0.1, 0.0, 0.2])
    moved = np.arange(n) < moving
    xq[moved] += rng.normal(size=(moving, 3)) * 0.5
    desc_c = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    desc_q = desc_c.copy()
    for row in desc_q[~moved]:  # 10 bits flipped on the static features, none on the moving ones
        idx = rng.choice(256, 10, replace=False)
        np.bitwise_xor.at(row, idx // 8, (1 << (idx % 8)).astype(np.uint8))
    weights = np.where(moved, 0.3, 1.2).astype(np.float32)
    q = View(_features(CAM.project(xq), desc_q), None, NOISE.points(xq), weights)
    c = View(_features(CAM.project(xc), desc_c), None, NOISE.points(xc), weights)
    return q, c


def test_stable_cues_enter_the_triangles_first() -> None:
    """Matches on moving objects have the closest descriptors, so by distance they make the first
    triangles, which disagree; ranked with the features' stability weights, the static
    structure makes them and the loop is accepted."""
    q, c = _moving_objects()
    cfg = merge(preset("default"), {"acceptance": "all", "n_triangles": 5, "stable_ranking": True})
    ranked = Verifier(cfg, camera=CAM, noise=NOISE).verify(q, c)
    plain = Verifier(merge(cfg, {"stable_ranking": False}), camera=CAM, noise=NOISE).verify(q, c)
    assert ranked.accepted and not plain.accepted
    vertices = [ranked.matches.query[list(t.matches)] for t in ranked.triangles]
    assert len(vertices) == 5 and all((v >= 30).all() for v in vertices)  # no moving feature
    assert all((plain.matches.query[list(t.matches)] < 30).all() for t in plain.triangles[:5])
    # equal weights: the distance order, the same triangles as without weights
    ones = np.ones(len(q.features), np.float32)
    same = Verifier(cfg, camera=CAM, noise=NOISE).verify(View(q.features, None, q.points, ones),
                                                         View(c.features, None, c.points, ones))
    assert [t.matches for t in same.triangles] == [t.matches for t in plain.triangles]


def test_feature_weights_are_checked() -> None:
    q, c = _moving_objects()
    n = len(q.features)
    for bad in (np.ones(3, np.float32), -np.ones(n), np.ones(n, np.int64), np.full(n, np.nan),
                np.full(n, np.inf)):
        with pytest.raises(InputError, match="feature weights"):
            View(q.features, None, q.points, bad)
    assert c.points is not None
    fvec = FeatureVector(np.zeros(len(c.features), np.int32), 3)
    entry = Entry(entry_id=4, bow=BowVector.empty(), fvec=fvec, features=c.features, points3d=c.points.xyz,
                  arrays={"weights": np.ones(5, np.float32)})
    with pytest.raises(InputError, match="database entry 4: view: feature weights"):
        Verifier(camera=CAM, noise=NOISE).view_of_entry(entry)
    assert c.weights is not None
    good = Entry(entry_id=4, bow=BowVector.empty(), fvec=fvec, features=c.features, points3d=c.points.xyz,
                 arrays={"weights": c.weights})
    view = Verifier(camera=CAM, noise=NOISE).view_of_entry(good)
    assert view.weights is c.weights


def _with_overlay(q: View, c: View, n: int = 60, seed: int = 11) -> tuple[View, View]:
    """Both views with the same ``n`` extra features at the same pixels (an overlay fixed to the
    camera: a timestamp, the vehicle's bonnet)."""
    rng = np.random.default_rng(seed)
    kp = np.c_[rng.uniform(10, 300, n), rng.uniform(10, 60, n)]
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)

    def add(v: View) -> View:
        f = v.features
        return View(_features(np.r_[f.keypoints, kp], np.r_[f.descriptors, desc]))

    return add(q), add(c)


def test_matches_fixed_to_the_camera_are_left_out() -> None:
    """Features at the same pixels in both images fit every fundamental matrix: with them an
    unrelated pair passes; ``static_px`` leaves them out, and a true pair still passes."""
    fundamental = merge(preset("default"), {"method": "fundamental"})
    assert fundamental.static_px == 0.5  # the default
    keep_all = merge(fundamental, {"static_px": None})
    q, c, _, _ = _scene(7, rigid=False)
    assert not Verifier(keep_all, CAM).verify(View(q.features), View(c.features)).accepted
    qo, co = _with_overlay(q, c)
    fooled = Verifier(keep_all, CAM).verify(qo, co)
    assert fooled.accepted and fooled.n_inliers >= 60
    res = Verifier(fundamental, CAM).verify(qo, co)
    assert not res.accepted and res.n_matches < fooled.n_matches - 50
    assert (res.matches.query < len(q.features)).all()  # no overlay feature among the matches
    assert "matches at the same pixels in both images left out" in res.reason
    q, c, _, _ = _scene(7)
    qo, co = _with_overlay(q, c)
    res = Verifier(fundamental, CAM).verify(qo, co)
    assert res.accepted and (res.matches.query < len(q.features)).all()
    same = Verifier(fundamental, CAM).verify(qo, qo)  # the same view twice: nothing is an overlay
    assert same.accepted and same.n_matches == len(qo.features) and "left out" not in same.reason
    # the presets that reproduce published methods keep every match
    assert preset("paper").static_px is None and preset("dloop").static_px is None
    with pytest.raises(ConfigError, match="static_px"):
        merge(fundamental, {"static_px": -1.0})


def _scaled(scale: float, n: int = 60, outliers: int = 0, seed: int = 21) -> Verification:
    """A verification whose inlier pixels in the query are those of the candidate zoomed by
    ``scale`` about a point, rotated 30 degrees and shifted; ``outliers`` of them scattered."""
    rng = np.random.default_rng(seed)
    pc = rng.uniform(0, 480, (n, 2))
    a = np.deg2rad(30.0)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    pq = (pc - 240.0) @ rot.T * scale + 250.0 + rng.normal(0, 0.5, (n, 2))
    pq[:outliers] = rng.uniform(0, 480, (outliers, 2))
    idx = np.arange(n, dtype=np.int32)
    m = Matches(idx, idx, np.zeros(n, np.int32), np.zeros(n, np.float32))
    return Verification(True, Method.FUNDAMENTAL, Status.ACCEPTED, "", matches=m, inliers=np.ones(n, bool),
                        pixels_query=pq.astype(np.float32), pixels_candidate=pc.astype(np.float32))


def test_scale_change_of_the_inliers() -> None:
    """The image scale between the views: log 1.3 for a candidate zoomed by 1.3 (and rotated),
    its opposite the other way, robust to a fifth of scattered matches, NaN with too few."""
    assert _scaled(1.3).scale_change == pytest.approx(np.log(1.3), abs=0.01)
    assert _scaled(1 / 1.3).scale_change == pytest.approx(-np.log(1.3), abs=0.01)
    assert _scaled(1.0).scale_change == pytest.approx(0.0, abs=0.01)
    assert _scaled(1.3, outliers=12).scale_change == pytest.approx(np.log(1.3), abs=0.05)
    assert np.isnan(_scaled(1.3, n=2).scale_change)
    res = _scaled(1.3)
    assert np.isnan(dataclasses.replace(res, pixels_query=None).scale_change)
