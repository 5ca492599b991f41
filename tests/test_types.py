"""Shared values: Features with binary descriptors of any width and float descriptors, built from
OpenCV keypoints or plain arrays; Frame's features."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stablecues.errors import InputError
from stablecues.types import ORB_DESCRIPTOR, ORB_DESCRIPTOR_BYTES, DescriptorKind, Features, Frame


def make(descriptors: np.ndarray, n: int | None = None) -> Features:
    n = descriptors.shape[0] if n is None else n
    return Features(
        keypoints=np.arange(2 * n, dtype=np.float32).reshape(n, 2),
        descriptors=descriptors,
        octaves=np.arange(n, dtype=np.int16),
        angles=np.zeros(n, np.float32),
        responses=np.linspace(1, 2, n, dtype=np.float32),
        sizes=np.full(n, 31, np.float32),
        image_size=(64, 48),
    )


def test_descriptor_kinds() -> None:
    assert ORB_DESCRIPTOR == DescriptorKind("binary", ORB_DESCRIPTOR_BYTES) == DescriptorKind("binary", 32)
    assert str(ORB_DESCRIPTOR) == "32-byte binary" and ORB_DESCRIPTOR.dtype == np.uint8
    sift = DescriptorKind("float", 128)
    assert str(sift) == "128-dim float32" and sift.dtype == np.float32 and sift != ORB_DESCRIPTOR
    assert DescriptorKind.of(np.zeros((5, 61), np.uint8)) == DescriptorKind("binary", 61)
    assert DescriptorKind.of(np.zeros((0, 128), np.float32)) == sift
    with pytest.raises(InputError, match="float64"):
        DescriptorKind.of(np.zeros((3, 128), np.float64))
    with pytest.raises(InputError, match="dimensions"):
        DescriptorKind.of(np.zeros(32, np.uint8))
    with pytest.raises(InputError, match="D >= 1"):
        DescriptorKind.of(np.zeros((3, 0), np.uint8))
    with pytest.raises(InputError, match="'binary' or 'float'"):
        DescriptorKind("ternary", 8)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="positive integer"):
        DescriptorKind("float", 0)
    sift.check(np.zeros((2, 128), np.float32))
    with pytest.raises(InputError, match="Nx128"):
        sift.check(np.zeros((2, 64), np.float32))


@pytest.mark.parametrize(
    ("dtype", "width", "kind"),
    [(np.uint8, 32, "binary"), (np.uint8, 16, "binary"), (np.uint8, 61, "binary"), (np.float32, 128, "float"),
     (np.float32, 64, "float")],
)
def test_features_take_binary_of_any_width_and_float(dtype: type, width: int, kind: str) -> None:
    desc = (np.arange(5 * width) % 251).astype(dtype).reshape(5, width)
    f = make(desc)
    assert len(f) == 5 and f.descriptor_kind == DescriptorKind(kind, width)  # type: ignore[arg-type]
    sub = f.subset(np.array([True, False, True, False, True]))
    assert len(sub) == 3 and sub.descriptor_kind == f.descriptor_kind
    np.testing.assert_array_equal(sub.descriptors, desc[[0, 2, 4]])
    np.testing.assert_array_equal(sub.octaves, [0, 2, 4])
    by_index = f.subset(np.array([4, 1]))
    np.testing.assert_array_equal(by_index.keypoints, f.keypoints[[4, 1]])
    none = f.subset(np.zeros(5, bool))
    assert len(none) == 0 and none.descriptors.shape == (0, width) and none.descriptors.dtype == dtype


def test_empty_keeps_the_kind() -> None:
    orb = Features.empty((640, 480))
    assert orb.descriptors.shape == (0, 32) and orb.descriptors.dtype == np.uint8
    assert orb.descriptor_kind == ORB_DESCRIPTOR and orb.image_size == (640, 480)
    sift = Features.empty((640, 480), DescriptorKind("float", 128))
    assert sift.descriptors.shape == (0, 128) and sift.descriptors.dtype == np.float32
    assert len(sift) == 0 and sift.keypoints.shape == (0, 2) and sift.octaves.dtype == np.int16


def test_wrong_descriptors_are_refused_with_what_was_found() -> None:
    with pytest.raises(InputError, match=r"descriptors: expected dtype uint8 \(binary\) or float32 .*int32"):
        make(np.zeros((4, 32), np.int32))
    with pytest.raises(InputError, match="float64"):
        make(np.zeros((4, 128), np.float64))
    with pytest.raises(InputError, match=r"one per keypoint \(4\), got shape \(3, 32\)"):
        make(np.zeros((3, 32), np.uint8), n=4)
    with pytest.raises(InputError, match="dimensions"):
        make(np.zeros((4, 4, 8), np.uint8))
    with pytest.raises(InputError, match="numpy array"):
        make([[0] * 32] * 4, n=4)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="mask"):
        make(np.zeros((4, 32), np.uint8)).subset(np.ones(3, bool))


# --- Features from OpenCV and from plain arrays; Frame's features ----------------------------------

def textured(seed: int = 0, size: tuple[int, int] = (240, 320)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.full(size, 100, np.uint8)
    for _ in range(300):
        x, y = int(rng.integers(0, size[1])), int(rng.integers(0, size[0]))
        cv2.rectangle(img, (x, y), (x + int(rng.integers(3, 20)), y + int(rng.integers(3, 20))),
                      int(rng.integers(0, 256)), -1)
    return cv2.GaussianBlur(img, (3, 3), 0)


def test_from_cv2_keeps_every_keypoint_field() -> None:
    img = textured()
    kps, desc = cv2.ORB_create(300).detectAndCompute(img, None)
    f = Features.from_cv2(kps, desc, image_size=(320, 240))
    assert len(f) == len(kps) > 50 and f.descriptor_kind == ORB_DESCRIPTOR and f.image_size == (320, 240)
    assert f.keypoints.dtype == np.float32 and f.octaves.dtype == np.int16
    k = kps[7]
    np.testing.assert_allclose(f.keypoints[7], k.pt, atol=1e-4)
    assert (f.octaves[7], f.angles[7], f.sizes[7]) == (k.octave, np.float32(k.angle), np.float32(k.size))
    assert f.responses[7] == np.float32(k.response)
    np.testing.assert_array_equal(f.descriptors, desc)
    assert set(np.unique(f.octaves)) <= set(range(8))


def test_from_cv2_unpacks_sift_octaves() -> None:
    from stablecues.features.sift import unpack_sift_octave

    kps, desc = cv2.SIFT_create(200).detectAndCompute(textured(), None)
    f = Features.from_cv2(kps, desc, image_size=(320, 240))
    assert f.descriptor_kind == DescriptorKind("float", 128)
    np.testing.assert_array_equal(f.octaves, unpack_sift_octave(np.array([k.octave for k in kps])))
    assert f.octaves.min() == -1  # SIFT's doubled first octave


def test_from_cv2_with_no_keypoints_is_empty_of_the_kind() -> None:
    f = Features.from_cv2((), None, image_size=(64, 48))
    assert len(f) == 0 and f.descriptors.shape == (0, 32) and f.descriptors.dtype == np.uint8
    sift = Features.from_cv2([], None, image_size=(64, 48), kind=DescriptorKind("float", 128))
    assert sift.descriptors.shape == (0, 128) and sift.descriptors.dtype == np.float32


def test_from_cv2_refuses_what_it_cannot_read() -> None:
    kps, desc = cv2.ORB_create(100).detectAndCompute(textured(), None)
    with pytest.raises(InputError, match=r"one per keypoint \(\d+\), got None"):
        Features.from_cv2(kps, None, image_size=(320, 240))
    with pytest.raises(InputError, match=r"one per keypoint .* got shape"):
        Features.from_cv2(kps[:-1], desc, image_size=(320, 240))
    with pytest.raises(InputError, match="dtype uint8 .* got int64"):
        Features.from_cv2(kps, desc.astype(np.int64), image_size=(320, 240))
    with pytest.raises(InputError, match=r"keypoints\[1\]: expected a cv2.KeyPoint .* got str"):
        Features.from_cv2([kps[0], "x"], desc[:2], image_size=(320, 240))
    with pytest.raises(InputError, match="Features.from_arrays"):
        Features.from_cv2(np.zeros((2, 2), np.float32), desc[:2], image_size=(320, 240))  # type: ignore[arg-type]
    with pytest.raises(InputError, match="image_size: expected .* got 320"):
        Features.from_cv2(kps, desc, image_size=320)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="image_size"):
        Features.from_cv2(kps, desc, image_size=(320, 0))
    bad = cv2.KeyPoint(float("nan"), 2.0, 31.0)
    with pytest.raises(InputError, match=r"keypoints\[0\]: expected finite"):
        Features.from_cv2([bad], desc[:1], image_size=(320, 240))


def test_from_arrays_converts_and_defaults() -> None:
    xy = np.array([[1, 2], [3.5, 4], [10, 20]], np.float64)
    desc = np.arange(96, dtype=np.uint8).reshape(3, 32)
    f = Features.from_arrays(xy, desc, image_size=(64, 48))
    assert f.keypoints.dtype == np.float32 and f.keypoints.tolist() == [[1, 2], [3.5, 4], [10, 20]]
    assert f.octaves.tolist() == [0, 0, 0] and f.angles.tolist() == [-1, -1, -1]
    assert f.responses.tolist() == [0, 0, 0] and f.sizes.tolist() == [31, 31, 31]
    g = Features.from_arrays(xy.astype(np.int32), desc, image_size=(64, 48), octaves=np.array([0, 1, 2]),
                             angles=np.array([10, 20, 30]), responses=np.ones(3), sizes=np.full(3, 9.0))
    assert g.octaves.dtype == np.int16 and g.octaves.tolist() == [0, 1, 2]
    levels = Features.from_arrays(xy, desc, image_size=(64, 48), octaves=np.array([0, 1, 2]))
    np.testing.assert_allclose(levels.sizes, [31, 31 * 1.2, 31 * 1.44], rtol=1e-6)
    assert g.angles.tolist() == [10, 20, 30] and g.sizes.dtype == np.float32
    empty = Features.from_arrays(np.zeros((0, 2)), np.zeros((0, 128), np.float32), image_size=(64, 48))
    assert len(empty) == 0 and empty.descriptor_kind == DescriptorKind("float", 128)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"keypoints": np.zeros((3, 3))}, r"keypoints: expected shape Nx2, got \(3, 3\)"),
        ({"keypoints": np.zeros((3, 2), bool)}, "keypoints: expected an .* real numbers, got bool"),
        ({"keypoints": [[0, 0]] * 3}, "keypoints: expected an .* got list"),
        ({"keypoints": np.full((3, 2), np.nan)}, "keypoints: expected finite"),
        ({"descriptors": np.zeros((3, 32), np.float64)}, "float64"),
        ({"descriptors": np.zeros((2, 32), np.uint8)}, r"one per keypoint \(3\)"),
        ({"octaves": np.zeros(3, np.float32)}, "octaves: expected an .* integer array, got float32"),
        ({"octaves": np.array([0, 1, 300])}, r"octaves: expected pyramid levels in \[-1, 127\], got 0..300"),
        ({"angles": np.zeros(2)}, r"angles: expected shape 3"),
        ({"responses": np.array([1, np.inf, 0])}, "responses: expected finite"),
        ({"sizes": "big"}, "sizes: expected an .* got str"),
        ({"image_size": (64.0, 48)}, "image_size"),
    ],
)
def test_from_arrays_says_what_is_wrong(kwargs: dict[str, object], message: str) -> None:
    args: dict[str, object] = {"keypoints": np.zeros((3, 2)), "descriptors": np.zeros((3, 32), np.uint8),
                               "image_size": (64, 48), **kwargs}
    with pytest.raises(InputError, match=message):
        Features.from_arrays(**args)  # type: ignore[arg-type]


def test_coerce_takes_features_and_pairs_only() -> None:
    kps, desc = cv2.ORB_create(100).detectAndCompute(textured(), None)
    f = Features.from_cv2(kps, desc, image_size=(320, 240))
    assert Features.coerce(f, (1, 1)) is f
    from_pair = Features.coerce((kps, desc), (320, 240))
    np.testing.assert_array_equal(from_pair.keypoints, f.keypoints)
    arrays = Features.coerce([f.keypoints, desc], (320, 240))
    np.testing.assert_array_equal(arrays.descriptors, desc)
    with pytest.raises(InputError, match="Features or a .* pair, got a 3-item tuple"):
        Features.coerce((kps, desc, None), (320, 240))
    with pytest.raises(InputError, match="Features or a .* pair, got str"):
        Features.coerce("features.npz", (320, 240))
    with pytest.raises(InputError, match="descriptors: expected a numpy array, got list"):
        Features.coerce((kps, [1, 2]), (320, 240))
    with pytest.raises(InputError, match="descriptors: expected an .* got None"):
        Features.coerce((f.keypoints, None), (320, 240))


def test_frame_takes_features_as_a_pair_and_has_no_dead_keypoints_field() -> None:
    img = textured()
    kps, desc = cv2.ORB_create(100).detectAndCompute(img, None)
    frame = Frame(index=3, name="a", timestamp=0.0, image=img, features=(kps, desc))
    assert isinstance(frame.features, Features) and frame.features.image_size == (320, 240)
    assert len(frame.features) == len(kps)
    assert "keypoints" not in Frame.__dataclass_fields__
    with pytest.raises(InputError, match="features: expected Features or"):
        Frame(index=3, name="a", timestamp=0.0, image=img, features=desc)  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"frame 3 image: expected an \(H, W\)"):
        Frame(index=3, name="a", timestamp=0.0, image=None, features=(kps, desc))  # type: ignore[arg-type]
