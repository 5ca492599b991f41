"""Masking of keypoints by class and uncertainty, with the fallback, on hand-made label images."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues.errors import ConfigError
from stablecues.semantics import MaskingConfig, SegmentationResult, pixel_mask, select_features
from stablecues.semantics.classes import CLASS_NAMES
from stablecues.semantics.masking import KEYPOINT_RULES, MASKING_PRESETS, MODES, PIXEL_RULES
from stablecues.types import Features

SKY, BUILDING, ROAD, CAR, TREE = (CLASS_NAMES.index(n) for n in ("Sky", "Building", "Road", "Car", "Tree"))


def make_seg(labels: np.ndarray, uncertainty: np.ndarray | None = None) -> SegmentationResult:
    unc = np.zeros(labels.shape, np.float32) if uncertainty is None else uncertainty.astype(np.float32)
    return SegmentationResult(
        labels=labels.astype(np.uint8),
        confidence=np.ones(labels.shape, np.float32),
        uncertainty=unc,
        samples=1,
        prob=np.zeros((11, 1, 1), np.float32),
    )


def make_features(
    xy: list[tuple[float, float]], size: tuple[int, int] = (40, 20), kp_size: float = 4.0
) -> Features:
    n = len(xy)
    return Features(
        keypoints=np.array(xy, np.float32).reshape(n, 2),
        descriptors=np.arange(n * 32, dtype=np.int64).astype(np.uint8).reshape(n, 32),
        octaves=np.zeros(n, np.int16),
        angles=np.zeros(n, np.float32),
        responses=np.ones(n, np.float32),
        sizes=np.full(n, kp_size, np.float32),
        image_size=size,
    )


@pytest.fixture
def labels() -> np.ndarray:
    """40 x 20 frame: sky on top (rows 0-4), building left / tree right (rows 5-9), road below
    with a car at columns 30-39 (rows 10-19)."""
    lab = np.full((20, 40), ROAD, np.uint8)
    lab[:5] = SKY
    lab[5:10, :20] = BUILDING
    lab[5:10, 20:] = TREE
    lab[10:, 30:] = CAR
    return lab


# keypoints: sky, building, tree, road, car, building edge next to sky
POINTS = [(5.0, 2.0), (5.0, 7.0), (25.0, 7.0), (5.0, 15.0), (35.0, 15.0), (10.0, 5.0)]


def test_hard_mask_keeps_only_static_pixels(labels: np.ndarray) -> None:
    feats = make_features(POINTS)
    kept, report = select_features(
        feats, make_seg(labels), MaskingConfig(mode="hard", min_kept=0, min_kept_fraction=0.0)
    )
    assert report.passed.tolist() == [False, True, True, False, False, True]
    assert report.kept == 3 and report.dropped == 3 and not report.fallback
    np.testing.assert_array_equal(kept.keypoints, feats.keypoints[[1, 2, 5]])
    np.testing.assert_array_equal(kept.descriptors, feats.descriptors[[1, 2, 5]])
    assert report.classes.tolist() == [SKY, BUILDING, TREE, ROAD, CAR, BUILDING]


def test_uncertainty_threshold_drops_uncertain_static_pixels(labels: np.ndarray) -> None:
    unc = np.zeros(labels.shape, np.float32)
    unc[5:10, 20:] = 0.2  # the tree is uncertain
    cfg = MaskingConfig(mode="hard", max_uncertainty=0.1, min_kept=0, min_kept_fraction=0.0)
    _, report = select_features(make_features(POINTS), make_seg(labels, unc), cfg)
    assert report.passed.tolist() == [False, True, False, False, False, True]


def test_dynamic_mode_drops_only_confident_dynamic_classes(labels: np.ndarray) -> None:
    feats = make_features(POINTS)
    _, report = select_features(
        feats, make_seg(labels), MaskingConfig(mode="dynamic", min_kept=0, min_kept_fraction=0.0)
    )
    assert report.passed.tolist() == [True, True, True, True, False, True]
    unc = np.full(labels.shape, 0.2, np.float32)  # everything uncertain: nothing is confidently a car
    _, report = select_features(
        feats, make_seg(labels, unc), MaskingConfig(mode="dynamic", min_kept=0, min_kept_fraction=0.0)
    )
    assert report.passed.all()


def test_frames_outside_the_networks_domain_keep_every_keypoint(labels: np.ndarray) -> None:
    """min_frame_certainty: a frame the network is unsure of as a whole drops nothing."""
    feats = make_features(POINTS)
    cfg = MaskingConfig(mode="dynamic", min_kept=0, min_kept_fraction=0.0, min_frame_certainty=0.8)

    def seg(sure: float) -> SegmentationResult:
        prob = np.full((11, 5, 10), (1.0 - sure) / 10, np.float32)
        prob[CAR] = sure
        return SegmentationResult(labels, np.ones(labels.shape, np.float32),
                                  np.zeros(labels.shape, np.float32), 1, prob)

    kept, report = select_features(feats, seg(0.7), cfg)  # certainty 0.67 < 0.8
    assert report.out_of_domain and len(kept) == len(feats) and report.passed.all() and not report.fallback
    kept, report = select_features(feats, seg(0.95), cfg)  # certainty 0.945: the car is dropped
    assert not report.out_of_domain and report.passed.tolist() == [True, True, True, True, False, True]
    assert seg(1.0 / 11).frame_certainty() == pytest.approx(0.0, abs=1e-6)
    assert make_seg(labels).frame_certainty() == 1.0  # labels handed in: certain
    with pytest.raises(ConfigError, match="min_frame_certainty"):
        MaskingConfig(min_frame_certainty=1.5)


def test_dilation_keeps_points_near_static_structure(labels: np.ndarray) -> None:
    feats = make_features([(5.0, 3.0), (5.0, 0.0), (5.0, 12.0)])  # sky 2 px above the building, far sky, road
    hard = select_features(
        feats, make_seg(labels), MaskingConfig(mode="hard", min_kept=0, min_kept_fraction=0.0)
    )[1]
    dil = select_features(
        feats, make_seg(labels), MaskingConfig(mode="dilate", dilation=3, min_kept=0, min_kept_fraction=0.0)
    )[1]
    assert hard.passed.tolist() == [False, False, False]
    assert dil.passed.tolist() == [True, False, True]
    mask = pixel_mask(make_seg(labels), MaskingConfig(mode="dilate", dilation=3))
    assert mask[2, 5] and not mask[0, 5] and mask[12, 5] and not mask[15, 5]


def test_patch_mode_uses_the_static_fraction_of_the_patch(labels: np.ndarray) -> None:
    # (5, 5): first building row; a 5x5 patch (radius 2) is 3/5 building -> kept at 0.5, not at 0.7
    feats = make_features([(5.0, 5.0), (5.0, 4.0)])
    r = select_features(
        feats,
        make_seg(labels),
        MaskingConfig(mode="patch", patch_radius=2, min_kept=0, min_kept_fraction=0.0),
    )[1]
    assert r.passed.tolist() == [True, False]
    cfg = MaskingConfig(mode="patch", patch_radius=2, patch_fraction=0.7, min_kept=0, min_kept_fraction=0)
    assert select_features(feats, make_seg(labels), cfg)[1].passed.tolist() == [False, False]
    # patch radius from the keypoint size: size 2 -> radius 1 -> 3x3 patch, 2/3 building at row 5
    feats = make_features([(5.0, 5.0)], kp_size=2.0)
    assert select_features(
        feats, make_seg(labels), MaskingConfig(mode="patch", min_kept=0, min_kept_fraction=0.0)
    )[1].passed[0]


def test_fallback_keeps_everything_and_is_reported(labels: np.ndarray) -> None:
    feats = make_features(POINTS)
    kept, report = select_features(
        feats, make_seg(labels), MaskingConfig(mode="hard", min_kept=4, min_kept_fraction=0.0)
    )
    assert report.fallback and report.kept == len(feats) == report.total
    assert int(report.passed.sum()) == 3  # the decision before the fallback is still reported
    np.testing.assert_array_equal(kept.keypoints, feats.keypoints)
    # enough survivors: no fallback
    _, report = select_features(
        feats, make_seg(labels), MaskingConfig(mode="hard", min_kept=3, min_kept_fraction=0.0)
    )
    assert not report.fallback and report.kept == 3
    # every keypoint passes: nothing to fall back from even if below min_kept
    _, report = select_features(make_features(POINTS[1:3]), make_seg(labels), MaskingConfig(mode="hard"))
    assert not report.fallback and report.kept == 2


def test_indoor_like_frame_triggers_fallback() -> None:
    lab = np.full((20, 40), SKY, np.uint8)  # nothing static anywhere
    feats = make_features([(float(x), 10.0) for x in range(0, 40, 2)])
    kept, report = select_features(
        feats, make_seg(lab), MaskingConfig(mode="hard", min_kept=5, min_kept_fraction=0.0)
    )
    assert report.fallback and len(kept) == 20 and report.passed.sum() == 0


def test_empty_features_pass_through(labels: np.ndarray) -> None:
    kept, report = select_features(Features.empty((40, 20)), make_seg(labels))
    assert len(kept) == 0 and report.total == 0 and not report.fallback


def test_keypoints_of_another_image_size_are_scaled(labels: np.ndarray) -> None:
    feats = make_features([(50.0, 70.0), (50.0, 14.0)], size=(400, 200))  # 10x the segmentation
    _, report = select_features(
        feats, make_seg(labels), MaskingConfig(mode="hard", min_kept=0, min_kept_fraction=0.0)
    )
    assert report.classes.tolist() == [BUILDING, SKY]


def test_bad_settings_are_rejected() -> None:
    with pytest.raises(ConfigError, match="mode"):
        MaskingConfig(mode="soft")
    with pytest.raises(ConfigError, match="Lamppost"):
        MaskingConfig(static_classes=frozenset({"Lamppost"}))
    with pytest.raises(ConfigError):
        MaskingConfig(patch_fraction=1.5)


def test_fallback_by_fraction(labels: np.ndarray) -> None:
    feats = make_features(POINTS)  # 3 of 6 pass the hard mask
    cfg = MaskingConfig(mode="hard", min_kept=0, min_kept_fraction=0.6)
    _, report = select_features(feats, make_seg(labels), cfg)
    assert report.fallback and report.kept == 6
    cfg = MaskingConfig(mode="hard", min_kept=0, min_kept_fraction=0.5)
    _, report = select_features(feats, make_seg(labels), cfg)
    assert not report.fallback and report.kept == 3
    with pytest.raises(ConfigError, match="min_kept_fraction"):
        MaskingConfig(min_kept_fraction=2.0)


def test_modes_are_the_rule_tables_keys(labels: np.ndarray) -> None:
    assert MODES == tuple(PIXEL_RULES) == ("hard", "dilate", "patch", "dynamic", "none")
    assert set(KEYPOINT_RULES) <= set(MODES)
    assert {c.mode for c in MASKING_PRESETS.values()} == {"hard", "dilate", "patch", "dynamic", "none"}
    seg = make_seg(labels)
    static = np.isin(labels, [BUILDING, TREE])  # of the fixture's classes; sky, road and car are not
    everywhere = np.ones_like(static)
    expected = {"hard": static, "patch": static, "dilate": static, "dynamic": labels != CAR,
                "none": everywhere}
    for mode in MODES:
        got = pixel_mask(seg, MaskingConfig(mode=mode, dilation=0))
        assert got.dtype == bool and got.shape == labels.shape
        np.testing.assert_array_equal(got, expected[mode], err_msg=mode)


def test_none_mode_keeps_everything(labels: np.ndarray) -> None:
    feats = make_features(POINTS)
    kept, report = select_features(feats, make_seg(labels), MaskingConfig(mode="none"))
    assert report.passed.all() and kept.keypoints.shape == feats.keypoints.shape and not report.fallback


def test_float_descriptors_are_masked_the_same_way(labels: np.ndarray) -> None:
    binary = make_features(POINTS)
    floats = Features(
        keypoints=binary.keypoints,
        descriptors=np.random.default_rng(0).random((len(POINTS), 128)).astype(np.float32),
        octaves=binary.octaves,
        angles=binary.angles,
        responses=binary.responses,
        sizes=binary.sizes,
        image_size=binary.image_size,
    )
    cfg = MaskingConfig(mode="hard", min_kept=0, min_kept_fraction=0.0)
    kept, report = select_features(floats, make_seg(labels), cfg)
    assert report.passed.tolist() == select_features(binary, make_seg(labels), cfg)[1].passed.tolist()
    np.testing.assert_array_equal(kept.descriptors, floats.descriptors[[1, 2, 5]])
    assert kept.descriptors.dtype == np.float32
