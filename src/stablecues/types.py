"""Small frozen dataclasses shared by every stage.

Arrays inside these objects are never modified in place by stablecues; treat them as read-only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal, cast

import numpy as np

from .errors import InputError, check_array

if TYPE_CHECKING:
    from .geometry.camera import Calibration

ORB_DESCRIPTOR_BYTES = 32
"""Width in bytes of an ORB (BRIEF-256) descriptor: 256 bits."""

DESCRIPTOR_BYTES = ORB_DESCRIPTOR_BYTES
"""Width of the binary words the vocabulary holds today (ORB's); kept for the vocabulary's
descriptor operations. New code: :data:`ORB_DESCRIPTOR_BYTES` or a :class:`DescriptorKind`."""

_KIND_DTYPES: dict[str, np.dtype] = {"binary": np.dtype(np.uint8), "float": np.dtype(np.float32)}


@dataclass(frozen=True)
class DescriptorKind:
    """What a local descriptor is, so that each stage can refuse what it cannot take.

    Attributes:
        kind: ``"binary"`` (bits packed in uint8 bytes, compared by Hamming distance) or
            ``"float"`` (float32 vectors, compared by Euclidean distance).
        size: bytes per descriptor for binary kinds (32 for ORB), dimensions for float kinds
            (128 for SIFT).
    """

    kind: Literal["binary", "float"]
    size: int

    def __post_init__(self) -> None:
        if self.kind not in _KIND_DTYPES:
            raise InputError(f"descriptor kind: expected 'binary' or 'float', got {self.kind!r}")
        if isinstance(self.size, bool) or not isinstance(self.size, int | np.integer) or self.size < 1:
            raise InputError(f"descriptor size: expected a positive integer, got {self.size!r}")

    @property
    def dtype(self) -> np.dtype:
        """uint8 for binary descriptors, float32 for float ones."""
        return _KIND_DTYPES[self.kind]

    def __str__(self) -> str:
        if self.kind == "binary":
            return f"{self.size}-byte binary"
        return f"{self.size}-dim float32"

    @staticmethod
    def of(descriptors: object, name: str = "descriptors") -> DescriptorKind:
        """The kind of an (N, D) descriptor array: uint8 is binary, float32 is float.

        Raises:
            InputError: not a 2-D uint8 or float32 array with D >= 1.
        """
        check_array(name, descriptors, ndim=2)
        arr = cast(np.ndarray, descriptors)
        if arr.dtype == np.uint8:
            kind: Literal["binary", "float"] = "binary"
        elif arr.dtype == np.float32:
            kind = "float"
        else:
            raise InputError(f"{name}: expected dtype uint8 (binary) or float32 (float), got {arr.dtype}")
        if arr.shape[1] < 1:
            raise InputError(f"{name}: expected shape NxD with D >= 1, got {arr.shape}")
        return DescriptorKind(kind, int(arr.shape[1]))

    def check(self, descriptors: object, name: str = "descriptors") -> None:
        """Raise :class:`InputError` unless ``descriptors`` is an (N, size) array of this kind."""
        check_array(name, descriptors, dtype=self.dtype, shape=(None, self.size))


ORB_DESCRIPTOR = DescriptorKind("binary", ORB_DESCRIPTOR_BYTES)
"""The descriptors of ORB (and BRIEF-256): 32 bytes, 256 bits."""


@dataclass(frozen=True)
class Features:
    """Local features of one image: keypoints and one descriptor per keypoint.

    Descriptors are binary, (N, D) uint8 with D bytes per descriptor (32 for ORB), or float,
    (N, D) float32 (128 for SIFT); :attr:`descriptor_kind` says which.

    Attributes:
        keypoints: (N, 2) float32 pixel coordinates (x, y) in the full-resolution image.
        descriptors: (N, D) uint8 binary or (N, D) float32 descriptors.
        octaves: (N,) int16 pyramid level each keypoint was found at (level ``o`` is the image
            scaled down by the extractor's ``level_scale ** o``; SIFT's upsampled first octave
            is -1).
        angles: (N,) float32 orientation in degrees, as OpenCV gives it.
        responses: (N,) float32 detector response (higher is stronger).
        sizes: (N,) float32 diameter of the keypoint's patch in pixels.
        image_size: (width, height) of the image the features come from.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    octaves: np.ndarray
    angles: np.ndarray
    responses: np.ndarray
    sizes: np.ndarray
    image_size: tuple[int, int]

    def __post_init__(self) -> None:
        check_array("keypoints", self.keypoints, dtype=np.float32, shape=(None, 2))
        n = self.keypoints.shape[0]
        DescriptorKind.of(self.descriptors)
        if self.descriptors.shape[0] != n:
            raise InputError(
                f"descriptors: expected one per keypoint ({n}), got shape {self.descriptors.shape}"
            )
        for name in ("octaves", "angles", "responses", "sizes"):
            arr = getattr(self, name)
            check_array(name, arr, shape=(n,))

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])

    @property
    def descriptor_kind(self) -> DescriptorKind:
        """Binary with the byte width, or float with the dimension, of the descriptors."""
        return DescriptorKind.of(self.descriptors)

    @staticmethod
    def empty(image_size: tuple[int, int], kind: DescriptorKind = ORB_DESCRIPTOR) -> Features:
        """Features with zero keypoints, correctly shaped: descriptors (0, D) of ``kind``."""
        return Features(
            keypoints=np.zeros((0, 2), np.float32),
            descriptors=np.zeros((0, kind.size), kind.dtype),
            octaves=np.zeros(0, np.int16),
            angles=np.zeros(0, np.float32),
            responses=np.zeros(0, np.float32),
            sizes=np.zeros(0, np.float32),
            image_size=image_size,
        )

    def subset(self, index: np.ndarray) -> Features:
        """Features selected by a boolean mask or an integer index array (descriptors keep
        their kind, also when nothing is selected)."""
        index = np.asarray(index)
        if index.dtype == bool and index.shape != (len(self),):
            raise InputError(f"mask: expected shape ({len(self)},), got {index.shape}")
        return Features(
            keypoints=self.keypoints[index],
            descriptors=self.descriptors[index],
            octaves=self.octaves[index],
            angles=self.angles[index],
            responses=self.responses[index],
            sizes=self.sizes[index],
            image_size=self.image_size,
        )


@dataclass(frozen=True)
class BowVector:
    """Sparse bag-of-words vector.

    Attributes:
        words: (M,) int32 word ids, sorted ascending and unique.
        weights: (M,) float64 weights, normalised as the vocabulary's scoring asks.
    """

    words: np.ndarray
    weights: np.ndarray

    def __post_init__(self) -> None:
        check_array("bow words", self.words, dtype=np.int32, ndim=1)
        check_array("bow weights", self.weights, dtype=np.float64, shape=(self.words.shape[0],))

    def __len__(self) -> int:
        return int(self.words.shape[0])

    @staticmethod
    def empty() -> BowVector:
        return BowVector(np.zeros(0, np.int32), np.zeros(0, np.float64))

    def as_dict(self) -> dict[int, float]:
        return {int(w): float(v) for w, v in zip(self.words, self.weights, strict=True)}


@dataclass(frozen=True)
class FeatureVector:
    """Direct index of one image: the vocabulary node each feature falls under.

    DBoW2 stores ``node -> [feature indices]`` at ``levels_up`` levels above the leaves; the
    same information is kept here per feature, which is more compact, and grouped on demand.

    Attributes:
        nodes: (N,) int32 node id of each feature at the direct-index level (-1: none).
        levels_up: how many levels above the leaves the nodes are taken.
    """

    nodes: np.ndarray
    levels_up: int

    def __post_init__(self) -> None:
        check_array("feature-vector nodes", self.nodes, dtype=np.int32, ndim=1)

    def __len__(self) -> int:
        return int(self.nodes.shape[0])

    def groups(self) -> dict[int, np.ndarray]:
        """``node id -> (K,) int64 indices of the features under it``, in feature order."""
        if self.nodes.size == 0:
            return {}
        order = np.argsort(self.nodes, kind="stable")
        sorted_nodes = self.nodes[order]
        cuts = np.flatnonzero(np.diff(sorted_nodes)) + 1
        starts = np.concatenate(([0], cuts))
        ends = np.concatenate((cuts, [order.size]))
        return {
            int(sorted_nodes[s]): order[s:e]
            for s, e in zip(starts, ends, strict=True)
            if sorted_nodes[s] >= 0
        }


@dataclass(frozen=True)
class QueryResult:
    """One database hit: the entry id and its similarity score (higher is more similar)."""

    entry_id: int
    score: float


@dataclass(frozen=True)
class Entry:
    """Everything a database keeps about one image.

    Attributes:
        entry_id: id given by the database (0, 1, 2, ... in insertion order).
        bow: the image's bag-of-words vector.
        fvec: the image's direct index.
        features: keypoints and descriptors (the full local features).
        points3d: (N, 3) float32 3D point per keypoint in the image's camera frame (NaN where
            unknown), or None when the image had no 3D information.
        timestamp: seconds, or NaN when unknown.
        pose: (4, 4) float64 camera-to-world pose, or None.
        meta: free-form JSON-serialisable metadata (e.g. the image path).
    """

    entry_id: int
    bow: BowVector
    fvec: FeatureVector
    features: Features
    points3d: np.ndarray | None = None
    timestamp: float = float("nan")
    pose: np.ndarray | None = None
    meta: dict[str, object] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class Frame:
    """One frame of a sequence, as handed to the loop detector.

    Attributes:
        index: position of the frame in its dataset (0, 1, 2, ...); loop ground truth and
            every results file use this index.
        name: the image's path relative to the dataset root (or a label), for reports.
        timestamp: seconds, NaN when unknown.
        image: (H, W) uint8 grey or (H, W, 3) uint8 BGR left (or only) image, as stored.
        right: the right image of a stereo pair, same form, as stored; the calibration says
            whether the pair is rectified. None for monocular data.
        depth: (H, W) float32 depth in metres registered to ``image``, NaN where unknown.
        labels: (H, W) uint8 CamVid class ids (0..11) for ``image``.
        pose: (4, 4) float64 camera-to-world pose of the left camera (ground truth), or None.
        calibration: the object :func:`stablecues.geometry.load_calibration` returns, or None
            when there is no calibration file or the geometry module is not available.
        calibration_path: the calibration file the dataset found (whether or not it could be
            loaded), or None.
        keypoints: (N, 2) float32 keypoints handed in by a SLAM system, or None.
        points3d: (N, 3) float32 3D point per keypoint in the camera frame (NaN unknown), or None.
    """

    index: int
    name: str
    timestamp: float
    image: np.ndarray
    right: np.ndarray | None = None
    depth: np.ndarray | None = None
    labels: np.ndarray | None = None
    pose: np.ndarray | None = None
    calibration: Calibration | None = None
    calibration_path: Path | None = None
    keypoints: np.ndarray | None = None
    points3d: np.ndarray | None = None
