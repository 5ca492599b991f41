"""Small frozen dataclasses shared by every stage.

Arrays inside these objects are never modified in place by stablecues; treat them as read-only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeAlias, cast

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

    @staticmethod
    def from_cv2(
        keypoints: Sequence[Any],
        descriptors: np.ndarray | None,
        *,
        image_size: tuple[int, int],
        kind: DescriptorKind = ORB_DESCRIPTOR,
    ) -> Features:
        """Features from what OpenCV's ``detectAndCompute`` returns.

        Args:
            keypoints: ``cv2.KeyPoint`` objects (anything with ``pt``, ``octave``, ``angle``,
                ``response`` and ``size``). SIFT's packed octaves are unpacked; plain octaves
                (ORB's 0, 1, ...) are kept as they are.
            descriptors: (N, D) uint8 binary or (N, D) float32 descriptors, one row per keypoint;
                None with no keypoints (OpenCV returns None then).
            image_size: (width, height) of the image the keypoints were found in.
            kind: the descriptor kind of the empty result when there are no keypoints.

        Raises:
            InputError: a keypoint without those attributes, descriptors of another dtype, shape
                or count, or an invalid image size.
        """
        size = _image_size(image_size)
        if isinstance(keypoints, np.ndarray) or not isinstance(keypoints, Sequence):
            raise InputError(f"keypoints: expected a list of cv2.KeyPoint, got {type(keypoints).__name__} "
                             "(for an (N, 2) array of pixels use Features.from_arrays)")
        n = len(keypoints)
        if descriptors is None:
            if n:
                raise InputError(f"descriptors: expected one per keypoint ({n}), got None")
            return Features.empty(size, kind)
        DescriptorKind.of(descriptors)
        if descriptors.shape[0] != n:
            raise InputError(f"descriptors: expected one per keypoint ({n}), got shape {descriptors.shape}")
        rows = np.empty((n, 6), np.float64)
        for i, k in enumerate(keypoints):
            try:
                rows[i] = (*k.pt, k.octave, k.angle, k.response, k.size)
            except (AttributeError, TypeError, ValueError):
                raise InputError(f"keypoints[{i}]: expected a cv2.KeyPoint (pt, octave, angle, response, "
                                 f"size), got {type(k).__name__}") from None
        if not np.isfinite(rows).all():
            bad = int(np.flatnonzero(~np.isfinite(rows).all(axis=1))[0])
            raise InputError(f"keypoints[{bad}]: expected finite values, got {rows[bad].tolist()}")
        low = rows[:, 2].astype(np.int64) & 0xFF  # SIFT packs layer << 8 | octave as a signed byte
        return Features(
            keypoints=rows[:, :2].astype(np.float32),
            descriptors=np.ascontiguousarray(descriptors),
            octaves=np.where(low >= 128, low - 256, low).astype(np.int16),
            angles=rows[:, 3].astype(np.float32),
            responses=rows[:, 4].astype(np.float32),
            sizes=rows[:, 5].astype(np.float32),
            image_size=size,
        )

    @staticmethod
    def from_arrays(
        keypoints: np.ndarray,
        descriptors: np.ndarray,
        *,
        image_size: tuple[int, int],
        octaves: np.ndarray | None = None,
        angles: np.ndarray | None = None,
        responses: np.ndarray | None = None,
        sizes: np.ndarray | None = None,
    ) -> Features:
        """Features from plain arrays, converted to the dtypes :class:`Features` keeps.

        Args:
            keypoints: (N, 2) pixel coordinates (x, y), any real dtype, finite.
            descriptors: (N, D) uint8 binary or (N, D) float32 descriptors (not converted: the
                dtype says which kind they are).
            image_size: (width, height) of the image the keypoints were found in.
            octaves: (N,) integer pyramid levels in [-1, 127]; default 0 (full resolution).
            angles: (N,) orientations in degrees; default -1 (OpenCV's "not computed").
            responses: (N,) detector responses; default 0.
            sizes: (N,) patch diameters in pixels; default ORB's, ``31 * 1.2 ** octave``.

        Raises:
            InputError: any array of the wrong shape or dtype, non-finite values, or octaves out
                of range; the message names the array, the expected and the found form.
        """
        size = _image_size(image_size)
        if not isinstance(keypoints, np.ndarray) or not (
            np.issubdtype(keypoints.dtype, np.floating) or np.issubdtype(keypoints.dtype, np.integer)
        ):
            found = keypoints.dtype if isinstance(keypoints, np.ndarray) else type(keypoints).__name__
            raise InputError(f"keypoints: expected an (N, 2) array of real numbers, got {found}")
        check_array("keypoints", keypoints, shape=(None, 2))
        n = keypoints.shape[0]
        DescriptorKind.of(descriptors)
        if descriptors.shape[0] != n:
            raise InputError(f"descriptors: expected one per keypoint ({n}), got shape {descriptors.shape}")
        xy = keypoints.astype(np.float32)
        if not np.isfinite(xy).all():
            raise InputError("keypoints: expected finite pixel coordinates, got NaN or infinity")
        octv = np.zeros(n, np.int16) if octaves is None else _octaves(octaves, n)
        return Features(
            keypoints=xy,
            descriptors=np.ascontiguousarray(descriptors),
            octaves=octv,
            angles=_real_vector("angles", angles, n, -1.0),
            responses=_real_vector("responses", responses, n, 0.0),
            sizes=(np.float32(31.0) * np.power(np.float32(1.2), octv.astype(np.float32))).astype(np.float32)
            if sizes is None else _real_vector("sizes", sizes, n, 0.0),
            image_size=size,
        )

    @staticmethod
    def coerce(
        value: object, image_size: tuple[int, int], *, kind: DescriptorKind = ORB_DESCRIPTOR
    ) -> Features:
        """``value`` as Features: Features as they are, or a ``(keypoints, descriptors)`` pair,
        the keypoints a list of ``cv2.KeyPoint`` (:meth:`from_cv2`) or an (N, 2) array of pixels
        (:meth:`from_arrays`).

        Args:
            value: Features or a (keypoints, descriptors) pair.
            image_size: (width, height) of the frame's image, for a pair.
            kind: the descriptor kind of an empty pair (no keypoints, descriptors None).

        Raises:
            InputError: anything else, or a malformed pair.
        """
        if isinstance(value, Features):
            return value
        if not isinstance(value, tuple | list) or len(value) != 2:
            found = f"a {len(value)}-item {type(value).__name__}" if isinstance(value, tuple | list) else (
                type(value).__name__)
            raise InputError(f"features: expected Features or a (keypoints, descriptors) pair, got {found}")
        kps, desc = value
        if desc is not None and not isinstance(desc, np.ndarray):
            raise InputError(f"descriptors: expected a numpy array, got {type(desc).__name__}")
        if isinstance(kps, np.ndarray):
            if desc is None:
                raise InputError("descriptors: expected an (N, D) array, got None")
            return Features.from_arrays(kps, desc, image_size=image_size)
        return Features.from_cv2(kps, desc, image_size=image_size, kind=kind)


FeaturesLike: TypeAlias = "Features | tuple[Any, Any]"
"""What the API accepts as a frame's features: :class:`Features`, or a ``(keypoints,
descriptors)`` pair as OpenCV gives it (see :meth:`Features.coerce`)."""


def _image_size(size: object) -> tuple[int, int]:
    """``(width, height)`` as two positive ints, or InputError."""
    ok = isinstance(size, tuple | list) and len(size) == 2 and all(
        isinstance(v, int | np.integer) and not isinstance(v, bool) and v > 0 for v in size)
    if not ok:
        raise InputError(f"image_size: expected (width, height), two positive integers, got {size!r}")
    w, h = cast("tuple[int, int]", size)
    return int(w), int(h)


def _real_vector(name: str, values: object, n: int, default: float) -> np.ndarray:
    """(n,) float32 from a real-valued array (``default`` everywhere when None)."""
    if values is None:
        return np.full(n, default, np.float32)
    if not isinstance(values, np.ndarray) or not (
        np.issubdtype(values.dtype, np.floating) or np.issubdtype(values.dtype, np.integer)
    ):
        found = values.dtype if isinstance(values, np.ndarray) else type(values).__name__
        raise InputError(f"{name}: expected an ({n},) array of real numbers, got {found}")
    check_array(name, values, shape=(n,))
    out = values.astype(np.float32)
    if not np.isfinite(out).all():
        raise InputError(f"{name}: expected finite values, got NaN or infinity")
    return out


def _octaves(values: object, n: int) -> np.ndarray:
    """(n,) int16 pyramid levels in [-1, 127] from an integer array."""
    if not isinstance(values, np.ndarray) or not np.issubdtype(values.dtype, np.integer):
        found = values.dtype if isinstance(values, np.ndarray) else type(values).__name__
        raise InputError(f"octaves: expected an ({n},) integer array, got {found}")
    check_array("octaves", values, shape=(n,))
    if n and (values.min() < -1 or values.max() > 127):
        raise InputError(f"octaves: expected pyramid levels in [-1, 127], got {values.min()}..{values.max()}")
    return values.astype(np.int16)


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

    @cached_property
    def order(self) -> np.ndarray:
        """(N,) int64 read-only feature indices sorted by node, stably (computed once: a frame's
        direct index is matched against several neighbours and candidates)."""
        order = np.argsort(self.nodes, kind="stable")
        order.flags.writeable = False
        return order

    def groups(self) -> dict[int, np.ndarray]:
        """``node id -> (K,) int64 indices of the features under it``, in feature order."""
        if self.nodes.size == 0:
            return {}
        order = self.order
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
        arrays: the extra named arrays stored with the entry (``Database.add(arrays=...)``),
            e.g. ``"weights"``, each feature's semantic stability weight.
    """

    entry_id: int
    bow: BowVector
    fvec: FeatureVector
    features: Features
    points3d: np.ndarray | None = None
    timestamp: float = float("nan")
    pose: np.ndarray | None = None
    meta: dict[str, object] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)


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
        calibration: the object :func:`stablecues.geometry.load_calibration` returns, or the
            path of a calibration file (the detector loads it once per path), or None: the
            detector's own calibration then applies.
        calibration_path: the calibration file the dataset found (whether or not it could be
            loaded), or None.
        features: the SLAM system's own features, or None to extract ORB features here: a
            :class:`Features`, or a ``(keypoints, descriptors)`` pair (a list of ``cv2.KeyPoint``
            or an (N, 2) pixel array, and (N, D) uint8 or float32 descriptors), turned into
            Features on construction with ``image``'s size.
        points3d: (N, 3) float 3D point per feature in the camera frame in metres (NaN where the
            feature has no map point), or None; needs ``features``, in the same order.
        session: the recording session (traversal) the frame belongs to, an integer >= 0: a
            robot's runs on different days, the reference and the query pass of a place
            recognition set; stored as the map entry's session
            (:attr:`stablecues.database.Database.session`). A loop to another session's place
            is preferred over one to the session under way when both verify
            (``QueryConfig.other_sessions_first``), and a new session starts a new run of
            frames. None: the map's current session (0 unless ``Database.new_session`` moved it).

    Raises:
        InputError: ``features`` that are neither Features nor a well-formed pair, or a
            ``session`` that is neither None nor an integer >= 0.
    """

    index: int
    name: str
    timestamp: float
    image: np.ndarray
    right: np.ndarray | None = None
    depth: np.ndarray | None = None
    labels: np.ndarray | None = None
    pose: np.ndarray | None = None
    calibration: Calibration | str | Path | None = None
    calibration_path: Path | None = None
    features: FeaturesLike | None = None
    points3d: np.ndarray | None = None
    session: int | None = None

    def __post_init__(self) -> None:
        session = self.session
        if session is not None:
            if isinstance(session, bool) or not isinstance(session, int | np.integer) or session < 0:
                raise InputError(f"frame {self.index}: session must be None or an integer >= 0, "
                                 f"got {session!r}")
            object.__setattr__(self, "session", int(session))
        if self.features is not None and not isinstance(self.features, Features):
            size = frame_image_size(self)
            object.__setattr__(self, "features", Features.coerce(self.features, size))


def frame_image_size(frame: Frame) -> tuple[int, int]:
    """(width, height) of a frame's image.

    Raises:
        InputError: the image is not an (H, W) or (H, W, C) array.
    """
    image = frame.image
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or 0 in image.shape[:2]:
        found = image.shape if isinstance(image, np.ndarray) else type(image).__name__
        raise InputError(f"frame {frame.index} image: expected an (H, W) or (H, W, C) array, got {found}")
    return int(image.shape[1]), int(image.shape[0])
