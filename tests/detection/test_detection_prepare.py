"""FramePreparer: the one path from a frame to features, BoW, direct index and 3D points."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from conftest import shared_path
from stablecues.config import merge
from stablecues.detection import DetectorConfig, FramePreparer, ImagePairVerifier, preset
from stablecues.errors import ConfigError, InputError
from stablecues.features import OrbConfig
from stablecues.geometry import Calibration, NoiseModel, PinholeCamera, load_calibration
from stablecues.imageio import read_image
from stablecues.semantics.masking import MaskingConfig
from stablecues.types import Features, Frame
from stablecues.verification.matching import match_features
from stablecues.vocabulary import default_vocabulary


def textured(seed: int = 0, shape: tuple[int, int] = (240, 320)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (shape[0] // 8, shape[1] // 8), dtype=np.uint8)
    return np.kron(small, np.ones((8, 8), np.uint8))


def frame(image: np.ndarray, **kwargs: object) -> Frame:
    return Frame(index=3, name="f3", timestamp=0.0, image=image, **kwargs)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def preparer() -> FramePreparer:
    return FramePreparer(DetectorConfig(), default_vocabulary())


def test_monocular_frame_has_features_bow_and_no_3d(preparer: FramePreparer) -> None:
    prep = preparer.prepare(frame(textured()))
    assert prep.n_features == len(prep.features) > 100
    assert len(prep.fvec) == len(prep.features) and len(prep.bow) > 0
    assert prep.points is None and prep.calibration is None and not prep.mask_fallback
    assert set(prep.timings) == {"extract", "transform", "lift"}
    bow, _ = default_vocabulary().transform(prep.features.descriptors)
    np.testing.assert_array_equal(prep.bow.words, bow.words)
    view = prep.view
    assert view.features is prep.features and view.fvec is prep.fvec and view.points is None


def test_map_points_follow_the_features_they_came_with(preparer: FramePreparer) -> None:
    img = textured(1)
    feats = preparer.extractor.extract(img)
    xyz = np.column_stack([feats.keypoints / 100.0, np.full(len(feats), 2.0)]).astype(np.float32)
    prep = preparer.prepare(frame(img, points3d=xyz), feats)
    assert prep.points is not None
    np.testing.assert_allclose(prep.points.xyz, xyz)
    # the generic map-point noise: 1 % depth noise at 1 m, f = 500 px, when nothing is known
    assert preparer.noise(None) == NoiseModel(0.01, 500.0)


def test_map_points_without_their_features_are_refused(preparer: FramePreparer) -> None:
    with pytest.raises(InputError, match="map points need the SLAM system's own features"):
        preparer.prepare(frame(textured(), points3d=np.zeros((5, 3), np.float32)))
    feats = preparer.extractor.extract(textured())
    with pytest.raises(InputError, match=r"frame 3 \(f3\): points3d has shape \(5, 3\)"):
        preparer.prepare(frame(textured(), points3d=np.zeros((5, 3), np.float32)), feats)


def test_masking_from_labels_keeps_the_map_points_of_kept_features() -> None:
    masking = MaskingConfig(mode="hard", min_kept=0, min_kept_fraction=0.0)
    config = dataclasses.replace(preset("default"), masking=masking, semantic_source="labels")
    prep_ = FramePreparer(config, default_vocabulary())
    img = textured(2)
    feats = prep_.extractor.extract(img)
    labels = np.zeros(img.shape, np.uint8)  # 0 = Sky: not static
    labels[:, : img.shape[1] // 2] = 1  # 1 = Building: static
    xyz = np.column_stack([feats.keypoints, np.arange(len(feats))]).astype(np.float32)
    prep = prep_.prepare(frame(img, labels=labels, points3d=xyz), feats)
    left = feats.keypoints[:, 0] < img.shape[1] // 2
    assert 0 < len(prep.features) < len(feats) and prep.n_features == len(feats)
    assert (prep.features.keypoints[:, 0] < img.shape[1] // 2 + 2).all()
    assert prep.points is not None
    np.testing.assert_allclose(prep.points.xyz[:, :2], prep.features.keypoints)  # each kept its own point
    assert len(prep.features) <= int(left.sum()) + 5
    assert {"segment", "mask"} <= set(prep.timings)
    with pytest.raises(InputError, match="has no label image"):
        prep_.prepare(frame(img))


def test_verifier_per_calibration() -> None:
    prep_ = FramePreparer(DetectorConfig(), default_vocabulary())
    calib = Calibration(left=PinholeCamera(400.0, 400.0, 160.0, 120.0, 320, 240), depth_scale=1000.0)
    v = prep_.verifier(calib)
    assert v is prep_.verifier(calib) and v.camera is calib.left
    assert prep_.verifier(None).camera is None  # map points without a camera: no PnP vote
    off = FramePreparer(merge(DetectorConfig(), {"verification": None}), default_vocabulary())
    with pytest.raises(ConfigError, match="verification is off"):
        off.verifier(calib)


def test_empty_image_prepares_to_empty(preparer: FramePreparer) -> None:
    prep = preparer.prepare(frame(np.full((240, 320), 128, np.uint8)))
    assert len(prep.features) == 0 and len(prep.bow) == 0 and len(prep.fvec) == 0
    assert isinstance(prep.features, Features)


def test_detector_and_pair_verifier_prepare_alike() -> None:
    """The pair verifier prepares a raw stereo frame exactly as the detector does."""
    folder = shared_path("euroc", "loop_pairs")
    calib = load_calibration(folder / "sensorLeft.yaml")
    left = read_image(folder / "left_img_0.png", "grey")
    right = read_image(folder / "right_img_0.png", "grey")
    config = merge(DetectorConfig(), {"features": {"n_features": 2000}, "masking": None})
    detector_side = FramePreparer(config, default_vocabulary(), calib).prepare(
        Frame(index=0, name="0", timestamp=math.nan, image=left, right=right)
    )
    pair = ImagePairVerifier(calib, n_features=2000)
    pair_side = pair.frame(left, right=right).view
    np.testing.assert_array_equal(detector_side.features.keypoints, pair_side.features.keypoints)
    assert detector_side.points is not None and pair_side.points is not None
    np.testing.assert_array_equal(detector_side.points.xyz, pair_side.points.xyz)
    assert pair.verifier.camera is calib.left  # keypoints and points refer to the raw left camera
    assert OrbConfig(n_features=2000) == config.features



def test_an_older_neighbour_is_tried_only_after_too_little_baseline() -> None:
    """Monocular 3D: the newest neighbour first; an older one when the newer lacked baseline, but
    not when the newer one had too few matches or matches that hold no one motion."""
    from stablecues.synthetic import SyntheticTown, SyntheticTownConfig

    # 320x240: at 256x192, OpenCV 5.1's ORB left the pair 28 well-triangulated points (30 needed;
    # 5.0's passed); here the pair has 39-41 essential-matrix inliers with either
    town = SyntheticTown(SyntheticTownConfig(frames=36, width=320, height=240, loops=1, seed=1, noise=1.0))
    images = [town.frame(i, right=False, depth=False, labels=False).image for i in range(2)]
    cfg = preset("fast", {"monocular": {}})

    def prepared(*newest_last: tuple[Features, object]) -> object:
        prep = FramePreparer(cfg, default_vocabulary())
        for feats, fvec in newest_last:
            prep.remember(feats, fvec)  # type: ignore[arg-type]
        return prep.prepare(frame(images[1]))

    base = FramePreparer(cfg, default_vocabulary())
    older, current = (base.prepare(frame(im)) for im in images)
    good = prepared((older.features, older.fvec))  # the older frame alone gives points
    assert good.points is not None and good.points_source == "mono-guessed-focal"  # type: ignore[attr-defined]
    assert int(good.points.valid.sum()) >= 30  # type: ignore[attr-defined]

    # the frame itself as the newest neighbour: no baseline at all, so the older one is tried
    same = prepared((older.features, older.fvec), (current.features, current.fvec))
    np.testing.assert_array_equal(same.points.xyz, good.points.xyz)  # type: ignore[attr-defined]

    # an unrelated newest neighbour (too few matches) ends the search
    other = base.prepare(frame(textured(5, (240, 320))))
    assert len(match_features(current.features, other.features, current.fvec, other.fvec, ratio=0.75)) < 30
    assert prepared((older.features, older.fvec), (other.features, other.fvec)).points is None  # type: ignore[attr-defined]

    # so does one whose matches fit no one motion: 40 of the frame's own descriptors at random places
    pick = np.arange(40)
    spots = np.random.default_rng(0).uniform(0, 190, (40, 2)).astype(np.float32)
    shuffled = (dataclasses.replace(current.features.subset(pick), keypoints=spots),
                dataclasses.replace(current.fvec, nodes=current.fvec.nodes[pick]))
    assert prepared((older.features, older.fvec), shuffled).points is None  # type: ignore[attr-defined]
