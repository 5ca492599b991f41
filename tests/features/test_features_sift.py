"""SIFT extractor: float descriptors, the decoded octave, the cap, masks, a real frame."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import shared_path
from stablecues.errors import ConfigError, InputError
from stablecues.features import SiftConfig, SiftExtractor
from stablecues.features.sift import SIFT_DESCRIPTOR, unpack_sift_octave
from stablecues.types import DescriptorKind, Features


def textured(h: int = 240, w: int = 320, seed: int = 0) -> np.ndarray:
    """Grey image of random filled rectangles and discs, lightly blurred (blobs for SIFT)."""
    rng = np.random.default_rng(seed)
    img = np.full((h, w), 128, np.uint8)
    for _ in range(120):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        colour = int(rng.integers(0, 256))
        if rng.random() < 0.5:
            corner = (x + int(rng.integers(4, 30)), y + int(rng.integers(4, 30)))
            cv2.rectangle(img, (x, y), corner, colour, -1)
        else:
            cv2.circle(img, (x, y), int(rng.integers(3, 15)), colour, -1)
    return cv2.GaussianBlur(img, (3, 3), 0)


def test_unpack_octave_by_hand() -> None:
    # OpenCV packs octave & 0xFF | layer << 8 | offset << 16; the octave is a signed byte
    packed = np.array([0xFF | 2 << 8 | 77 << 16, 0x00 | 1 << 8, 0x03 | 3 << 8 | 255 << 16, 0xFE])
    assert unpack_sift_octave(packed).tolist() == [-1, 0, 3, -2]
    assert unpack_sift_octave(packed).dtype == np.int16


def test_float_descriptors_and_keypoint_fields_on_a_synthetic_image() -> None:
    ex = SiftExtractor(SiftConfig(n_features=300))
    assert ex.descriptor_kind == SIFT_DESCRIPTOR == DescriptorKind("float", 128)
    assert ex.level_scale == 2.0
    f = ex.extract(textured())
    assert 50 < len(f) <= 300
    assert f.descriptors.dtype == np.float32 and f.descriptors.shape == (len(f), 128)
    assert f.descriptor_kind == SIFT_DESCRIPTOR
    assert f.keypoints.shape == (len(f), 2) and f.image_size == (320, 240)
    assert f.octaves.dtype == np.int16 and f.octaves.min() == -1  # SIFT starts on the doubled image
    assert ((f.angles >= 0) & (f.angles < 360)).all() and (f.responses > 0).all()
    # the decoded octave is the scale: size = 2 sigma 2^(octave + (layer + offset) / 3), layer 1..3
    ratio = f.sizes / (2 * 1.6 * 2.0 ** f.octaves.astype(np.float64))
    assert ratio.min() >= 2 ** (1 / 6) - 1e-3 and ratio.max() <= 2 ** (7 / 6) + 1e-3


def test_same_keypoints_and_descriptors_as_opencv() -> None:
    img = textured(seed=1)
    f = SiftExtractor(SiftConfig(n_features=None)).extract(img)
    kps, desc = cv2.SIFT.create().detectAndCompute(img, None)
    np.testing.assert_array_equal(f.keypoints, np.array([k.pt for k in kps], np.float32))
    np.testing.assert_array_equal(f.descriptors, desc)
    np.testing.assert_array_equal(f.responses, np.array([k.response for k in kps], np.float32))


def test_cap_keeps_the_strongest() -> None:
    img = textured(seed=2)
    every = SiftExtractor(SiftConfig(n_features=None)).extract(img)
    few = SiftExtractor(SiftConfig(n_features=25)).extract(img)
    assert len(every) > 25 and len(few) <= 25
    assert few.responses.min() >= np.sort(every.responses)[::-1][min(len(every), 40) - 1]


def test_colour_and_grey_agree_and_mask_restricts() -> None:
    grey = textured(seed=3)
    ex = SiftExtractor(SiftConfig(n_features=200))
    a, b = ex.extract(grey), ex.extract(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    np.testing.assert_array_equal(a.descriptors, b.descriptors)
    mask = np.zeros_like(grey)
    mask[:, 160:] = 1
    m = ex.extract(grey, mask)
    assert len(m) > 0 and (m.keypoints[:, 0] >= 159).all()


@pytest.mark.parametrize("image", [np.zeros((0, 0), np.uint8), np.full((240, 320), 90, np.uint8)])
def test_empty_results_keep_the_float_kind(image: np.ndarray) -> None:
    f = SiftExtractor().extract(image)
    assert len(f) == 0 and f.descriptors.shape == (0, 128) and f.descriptors.dtype == np.float32


def test_zero_features_and_bad_input() -> None:
    assert len(SiftExtractor(SiftConfig(n_features=0)).extract(textured())) == 0
    with pytest.raises(InputError, match="uint8"):
        SiftExtractor().extract(np.zeros((50, 50), np.float32))
    with pytest.raises(InputError, match="mask"):
        SiftExtractor().extract(textured(), np.zeros((3, 3), np.uint8))
    with pytest.raises(ConfigError):
        SiftConfig(n_octave_layers=0)
    with pytest.raises(ConfigError, match="'sift'"):
        SiftConfig(name="orb")


def test_real_frame_descriptors_recover_a_known_similarity() -> None:
    """SIFT of a CamVid frame and of the same frame turned by 12 degrees and shrunk to 0.8:
    ratio-test matches give back the transform."""
    frame = sorted((shared_path("camvid") / "test").glob("*.jpg"))[0]
    img = cv2.imread(str(frame), cv2.IMREAD_GRAYSCALE)
    h, w = img.shape
    truth = cv2.getRotationMatrix2D((w / 2, h / 2), 12.0, 0.8)
    warped = cv2.warpAffine(img, truth, (w, h))
    ex = SiftExtractor()
    a, b = ex.extract(img), ex.extract(warped)
    assert len(a) > 200 and len(b) > 200
    # OpenCV's descriptors: a unit vector scaled to 512, clipped at 0..255
    norms = np.linalg.norm(a.descriptors, axis=1)
    assert (a.descriptors >= 0).all() and np.allclose(norms, 512, rtol=0.02)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.descriptors, b.descriptors, k=2)
    good = [m for m, n in pairs if m.distance < 0.75 * n.distance]
    assert len(good) > 50
    src = a.keypoints[[m.queryIdx for m in good]]
    dst = b.keypoints[[m.trainIdx for m in good]]
    model, inliers = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=2.0)
    assert inliers.mean() > 0.8
    np.testing.assert_allclose(model[:, :2], truth[:, :2], atol=0.005)  # rotation and scale
    np.testing.assert_allclose(model[:, 2], truth[:, 2], atol=1.0)  # translation, pixels


def test_the_binary_vocabulary_refuses_sift_descriptors_in_one_line() -> None:
    from stablecues.vocabulary import default_vocabulary

    voc = default_vocabulary()
    assert voc.descriptor_kind == DescriptorKind("binary", 32)
    sift = SiftExtractor(SiftConfig(n_features=50)).extract(textured())
    expected = "descriptors are 128-dim float32 but the vocabulary holds 32-byte binary words: train a"
    with pytest.raises(InputError, match=expected):
        voc.transform(sift.descriptors)
    with pytest.raises(InputError, match=expected):  # also when there are none
        voc.transform(Features.empty((320, 240), SIFT_DESCRIPTOR).descriptors)
    with pytest.raises(InputError, match="16-byte binary"):
        voc.transform(np.zeros((3, 16), np.uint8))
