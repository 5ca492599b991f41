"""Shared values: Features with binary descriptors of any width and float descriptors."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues.errors import InputError
from stablecues.types import ORB_DESCRIPTOR, ORB_DESCRIPTOR_BYTES, DescriptorKind, Features


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
