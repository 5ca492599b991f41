"""One frame-preparation path: extract, mask, transform, lift.

The loop detector and the two-image verifier (``stablecues verify``) both turn a
:class:`~stablecues.types.Frame` into a :class:`PreparedFrame` here, so a pair verified on the
command line is checked exactly as the detector would check it:

1. features: the SLAM system's own, or extracted on the frame's image as stored (raw, not
   rectified: keypoints refer to the camera the calibration describes);
2. semantic selection (``DetectorConfig.masking``), from the network or the frame's labels;
3. the BoW vector and the direct index from the vocabulary;
4. 3D points per kept feature, from the first source the frame has: map points handed in,
   a stereo pair (a raw pair is rectified inside the lifter, whose remap tables are cached per
   calibration, and the points rotated back into the raw left camera), a depth image, or
   (``DetectorConfig.monocular``) triangulation against a neighbouring frame of the stream, with
   the calibration's camera or, without one, a focal length guessed from the image size.

It also owns what depends only on the calibration: the 3D noise model and the
:class:`~stablecues.verification.Verifier` for frames of that camera.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import merge
from ..errors import ConfigError, InputError
from ..features import make_extractor
from ..geometry.calibration import load_calibration
from ..geometry.camera import Calibration
from ..geometry.depth import DepthConfig, lift_depth, lift_map_points
from ..geometry.points import NoiseModel, Points3D
from ..geometry.stereo import StereoConfig, StereoLifter
from ..geometry.twoview import TwoViewConfig, guess_camera, triangulate_two_view
from ..imageio import to_grey
from ..semantics.classes import NUM_CLASSES
from ..semantics.inference import SegmentationModel, SegmentationResult
from ..semantics.masking import select_features
from ..semantics.weighting import feature_weights
from ..types import BowVector, Features, FeaturesLike, FeatureVector, Frame, frame_image_size
from ..verification.matching import match_features
from ..verification.verifier import Verifier, View
from ..vocabulary import Vocabulary
from ..vocabulary.incremental import IncrementalVocabulary
from .config import DetectorConfig

__all__ = ["FramePreparer", "PreparedFrame", "Segmenter", "as_calibration"]

log = logging.getLogger(__name__)

Segmenter = Callable[[np.ndarray], SegmentationResult]
"""``image -> SegmentationResult``: the shipped network, or any replacement."""


def as_calibration(calibration: object, what: str = "calibration") -> Calibration | None:
    """A calibration given as an object or as the path of a calibration file (loaded here).

    Args:
        calibration: a :class:`~stablecues.geometry.Calibration`, a path (``str`` or
            ``Path``, any format :func:`~stablecues.geometry.load_calibration` reads, or a TUM
            camera name), or None.
        what: what the value is, for messages.

    Raises:
        CalibrationError: a path that does not exist or does not hold a calibration.
        InputError: anything else.
    """
    if calibration is None or isinstance(calibration, Calibration):
        return calibration
    if isinstance(calibration, str | Path):
        return load_calibration(calibration)
    raise InputError(f"{what}: expected a Calibration or the path of a calibration file, "
                     f"got {type(calibration).__name__}")


# map points from a SLAM system with nothing known of their sensor: 1 % depth noise at 1 m
_MAP_POINT_DEPTH_NOISE = 0.01
_MAP_POINT_FOCAL = 500.0


@dataclass(frozen=True, eq=False)
class PreparedFrame:
    """One frame, ready to query, verify and store.

    Attributes:
        features: the kept features (all of them without masking or when masking fell back).
        bow: their bag-of-words vector.
        fvec: their direct index.
        points: 3D point per kept feature in the frame's camera, or None without 3D.
        calibration: the calibration the frame was prepared with (its own, else the default;
            for monocular 3D without either, one with a focal length guessed from the image size).
        points_source: where the 3D points come from: "map", "stereo", "depth", "mono",
            "mono-guessed-focal", or None without 3D.
        n_features: features before semantic selection.
        mask_fallback: masking kept too few features, so every feature was kept.
        timings: milliseconds per stage (extract, segment, mask, transform, lift).
        t_start: ``time.perf_counter()`` when preparation began.
        certainty: the frame certainty of the network's segmentation of this frame (None when
            the network did not run), kept with the entry so a reopened map restores the
            stream's domain window (``DetectorConfig.domain_window``).
        weights: (N,) float32 semantic stability weight of each kept feature (None without
            ``DetectorConfig.weighting``): they weight the BoW vector, order the matches for
            triangles with ``verification.stable_ranking``, and are kept with the entry.
    """

    features: Features
    bow: BowVector
    fvec: FeatureVector
    points: Points3D | None
    calibration: Calibration | None
    n_features: int
    mask_fallback: bool
    points_source: str | None = None
    timings: dict[str, float] = field(default_factory=dict)
    t_start: float = 0.0
    certainty: float | None = None
    weights: np.ndarray | None = None

    @property
    def view(self) -> View:
        """What the verifier needs of this frame."""
        return View(self.features, self.fvec, self.points, self.weights)


class _Laps:
    """Milliseconds per stage, measured between consecutive calls."""

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}
        self.start = self._t = time.perf_counter()

    def __call__(self, stage: str) -> None:
        now = time.perf_counter()
        self.timings[stage] = self.timings.get(stage, 0.0) + (now - self._t) * 1e3  # a stage may recur
        self._t = now


class FramePreparer:
    """Prepares frames for one detector configuration and vocabulary.

    Args:
        config: the detector settings (features, masking, semantic source, verification).
        vocabulary: the vocabulary for BoW vectors and direct indexes.
        calibration: the calibration used for frames that carry none, or its file's path.
        segmenter: replaces the shipped network (``image -> SegmentationResult``).
        stereo: sparse stereo matching settings.
        depth: depth-image lifting settings.
    """

    def __init__(
        self,
        config: DetectorConfig,
        vocabulary: Vocabulary | IncrementalVocabulary,
        calibration: Calibration | str | Path | None = None,
        segmenter: Segmenter | None = None,
        *,
        stereo: StereoConfig | None = None,
        depth: DepthConfig | None = None,
    ) -> None:
        self.config = config
        self.vocabulary = vocabulary
        self.calibration = as_calibration(calibration)
        self._loaded: dict[str, Calibration | None] = {}
        self._unused_said = False  # a right or depth image without a calibration: said once
        self.extractor = make_extractor(config.features)
        if self.extractor.descriptor_kind != vocabulary.descriptor_kind:
            raise ConfigError(
                f"features {config.features.name!r} give {self.extractor.descriptor_kind} descriptors but "
                f"the vocabulary holds {vocabulary.descriptor_kind} words: train a vocabulary for them"
            )
        self.stereo_config = stereo or StereoConfig()
        self.depth_config = depth or DepthConfig()
        self._segmenter = segmenter
        self._certainties: deque[float] = deque(maxlen=config.domain_window)
        self._frame_certainty: float | None = None
        self._lifters: dict[int, StereoLifter] = {}
        self._verifiers: dict[int, Verifier] = {}
        self._guessed: dict[tuple[int, int], Calibration] = {}
        mono = config.monocular
        self._recent: deque[tuple[Features, FeatureVector]] = deque(maxlen=mono.neighbours if mono else 1)

    # ------------------------------------------------------------------ per calibration
    def calibration_of(self, frame: Frame) -> Calibration | None:
        """The frame's own calibration (a path is loaded once), else the default one."""
        own = frame.calibration
        if own is None or isinstance(own, Calibration):
            return own if own is not None else self.calibration
        key = str(own) if isinstance(own, str | Path) else ""
        if key not in self._loaded:
            self._loaded[key] = as_calibration(own, f"frame {frame.index} calibration")
        return self._loaded[key]

    def _check_frame_against(self, frame: Frame, calib: Calibration | None) -> None:
        """A frame the calibration cannot describe is refused (its image size differs from the
        calibration's); a right or depth image that cannot be used without a calibration is
        said once (the frame runs monocular), never dropped without a word.

        Raises:
            InputError: naming the frame, both sizes and the calibration's source.
        """
        size = calib.left.image_size if calib is not None else None
        if calib is not None and size is not None and frame.image is not None:
            h, w = np.asarray(frame.image).shape[:2]
            if (w, h) != size:
                raise InputError(f"frame {frame.index} ({frame.name}): a {w}x{h} image, but the calibration "
                                 f"({calib.source or 'given'}) is for {size[0]}x{size[1]} images")
        if (calib is None and self.config.verification is not None and not self._unused_said
                and (frame.right is not None or frame.depth is not None)):
            what = "right image" if frame.right is not None else "depth image"
            log.warning("frame %d (%s) has a %s but the detector has no calibration: it runs monocular, "
                        "its %s unused (give calibration= to the detector or Frame.calibration)",
                        frame.index, frame.name, what, what)
            self._unused_said = True

    def lifter(self, calib: Calibration) -> StereoLifter:
        """The stereo lifter of a stereo calibration (built once; it caches remap tables)."""
        lifter = self._lifters.get(id(calib))
        if lifter is None:
            lifter = self._lifters[id(calib)] = StereoLifter(calib, self.stereo_config)
        return lifter

    def noise(self, calib: Calibration | None) -> NoiseModel:
        """The noise model of the 3D points of frames with this calibration.

        The stereo lifter's own (rectified focal, its disparity noise) for stereo rigs, the
        calibration's for depth cameras, and a generic one for map points without a stereo or
        depth calibration, so that query and stored points always get the same model.
        """
        if calib is not None and calib.is_stereo:
            return self.lifter(calib).noise
        if calib is not None:
            try:
                return NoiseModel.for_calibration(calib)
            except ConfigError:
                pass
        focal = calib.left.fx if calib is not None else _MAP_POINT_FOCAL
        return NoiseModel(_MAP_POINT_DEPTH_NOISE, focal)

    def verifier(self, calib: Calibration | None) -> Verifier:
        """The verifier for frames of this calibration (built once).

        Raises:
            ConfigError: verification is off, or PnP verification without a calibration.
        """
        cfg = self.config.verification
        if cfg is None:
            raise ConfigError("verification is off in this configuration")
        verifier = self._verifiers.get(id(calib))
        if verifier is None:
            if calib is None:
                if cfg.method == "pnp":
                    raise ConfigError("PnP verification needs a calibration (the query camera)")
                verifier = Verifier(merge(cfg, {"min_pnp_inliers": 0}), noise=self.noise(None))
            else:
                verifier = Verifier(cfg, calib.left, self.noise(calib))
            self._verifiers[id(calib)] = verifier
        return verifier

    # ------------------------------------------------------------------ the path
    def prepare(self, frame: Frame, features: FeaturesLike | None = None) -> PreparedFrame:
        """Features, semantic selection, BoW vector and direct index, 3D points of one frame.

        Args:
            frame: the frame.
            features: the SLAM system's own features (in the order of ``frame.points3d``):
                Features or a ``(keypoints, descriptors)`` pair (see
                :meth:`~stablecues.types.Features.coerce`); else ``frame.features``; extracted
                here when both are None.

        Raises:
            InputError: map points without the features they belong to, features given both
                here and in the frame, features that are not Features or a well-formed pair,
                descriptors of another kind than the vocabulary's, a frame without the label
                image that ``semantic_source="labels"`` needs, or malformed 3D input.
        """
        laps = _Laps()
        self._frame_certainty = None
        calib = self.calibration_of(frame)
        self._check_frame_against(frame, calib)
        features = self._given_features(frame, features)
        if features is None:
            if frame.points3d is not None:
                raise InputError(f"frame {frame.index}: map points need the SLAM system's own "
                                 "features (process(frame, features=...)) to pair with")
            features = self.extractor.extract(to_grey(frame.image, f"frame {frame.index} image"))
        laps("extract")
        n_features = len(features)
        seg: SegmentationResult | None = None
        features, keep, fallback, seg = self._select(frame, features, laps)
        weights = None
        if self.config.weighting is not None and len(features):
            seg = seg if seg is not None else self.segment(frame)
            weights = feature_weights(features, seg, self.config.weighting, self.domain_certainty())
            laps("segment")
        if weights is None:
            bow, fvec = self.vocabulary.transform(features.descriptors)
        else:
            bow, fvec = self.vocabulary.transform(features.descriptors, weights=weights)
        laps("transform")
        points, source = None, None
        if self.config.verification is not None:
            if frame.points3d is not None and keep is not None:
                frame = dataclasses.replace(frame, points3d=np.asarray(frame.points3d)[keep])
            points, source = self._lift(frame, features, calib)
            if points is None and self.config.monocular is not None:
                points, source, calib = self._triangulate(features, fvec, calib)
            self.remember(features, fvec)
            laps("lift")  # 3D from whichever source: map points, stereo, depth or triangulation
        kept = None if weights is None else weights.astype(np.float32)  # as the entry keeps them
        return PreparedFrame(features, bow, fvec, points, calib, n_features, fallback, source,
                             laps.timings, laps.start, self._frame_certainty, kept)

    def _given_features(self, frame: Frame, features: FeaturesLike | None) -> Features | None:
        """The SLAM system's features of a frame, as Features of the vocabulary's kind, or None."""
        if features is not None and frame.features is not None and features is not frame.features:
            raise InputError(f"frame {frame.index}: features given twice (in the Frame and to the "
                             "detector): give them once")
        given = features if features is not None else frame.features
        if given is None:
            return None
        kind = self.vocabulary.descriptor_kind
        if isinstance(given, Features):
            out = given
        else:
            try:
                out = Features.coerce(given, frame_image_size(frame), kind=kind)
            except InputError as exc:
                raise InputError(f"frame {frame.index} ({frame.name}): {exc}") from None
        if out.descriptor_kind != kind:
            raise InputError(f"frame {frame.index} ({frame.name}): the features have {out.descriptor_kind} "
                             f"descriptors but the vocabulary holds {kind} words")
        return out

    def _select(
        self, frame: Frame, features: Features, laps: _Laps
    ) -> tuple[Features, np.ndarray | None, bool, SegmentationResult | None]:
        """Semantic selection: (kept features, indices kept or None for all, fell back, the
        segmentation when it was computed)."""
        masking = self.config.masking
        if masking is None or masking.mode == "none" or not len(features):
            return features, None, False, None
        seg = self.segment(frame)
        laps("segment")
        kept, report = select_features(features, seg, masking, self.domain_certainty())
        laps("mask")
        fallback = bool(report.fallback)
        return kept, (None if fallback else np.flatnonzero(report.passed)), fallback, seg

    def segment(self, frame: Frame) -> SegmentationResult:
        """The frame's segmentation: its label image (``semantic_source="labels"``) or the network."""
        if self.config.semantic_source == "labels":
            if frame.labels is None:
                raise InputError(f"frame {frame.index} ({frame.name}): semantic_source='labels' but "
                                 "the frame has no label image")
            lab = np.asarray(frame.labels, np.uint8)
            h, w = lab.shape
            return SegmentationResult(lab, np.ones((h, w), np.float32), np.zeros((h, w), np.float32),
                                      0, np.zeros((NUM_CLASSES, 1, 1), np.float32))
        if self._segmenter is None:
            model = SegmentationModel.load(precision=self.config.segmentation_precision)
            samples = self.config.segmentation_samples
            self._segmenter = lambda image: model.predict(image, samples)
        seg = self._segmenter(frame.image)
        self._frame_certainty = seg.frame_certainty()
        self._certainties.append(self._frame_certainty)
        return seg

    def restore_certainties(self, certainties: list[float]) -> None:
        """Start the domain window from the certainties of a reopened map's latest frames (oldest
        first), so a resumed stream gates as an uninterrupted one would."""
        self._certainties.clear()
        self._certainties.extend(float(c) for c in certainties[-self.config.domain_window:])

    def domain_certainty(self) -> float | None:
        """The median frame certainty of the last ``domain_window`` segmented frames (None
        before the first): how sure the network is of this stream (``DetectorConfig.domain_window``)."""
        return float(np.median(self._certainties)) if self._certainties else None

    def _lift(
        self, frame: Frame, features: Features, calib: Calibration | None
    ) -> tuple[Points3D | None, str | None]:
        """3D points of the features in the frame's camera and their source, or (None, None)."""
        try:
            if frame.points3d is not None:
                pts = np.asarray(frame.points3d)
                if pts.shape != (len(features), 3):
                    raise InputError(f"points3d has shape {pts.shape}, expected ({len(features)}, 3), "
                                     "one per feature")
                return lift_map_points(pts, self.noise(calib), octaves=features.octaves), "map"
            if calib is None:
                return None, None
            if frame.right is not None and calib.is_stereo:
                return self.lifter(calib).lift(features, frame.image, frame.right), "stereo"
            if frame.depth is not None:
                raw = np.issubdtype(np.asarray(frame.depth).dtype, np.integer)  # a 16-bit PNG as read
                points = lift_depth(features, frame.depth, calib.left,
                                    depth_scale=calib.depth_scale if raw else None, config=self.depth_config)
                return points, "depth"
        except InputError as exc:
            raise InputError(f"frame {frame.index} ({frame.name}): {exc}") from None
        return None, None

    # ------------------------------------------------------------------ monocular 3D
    def remember(self, features: Features, fvec: FeatureVector) -> None:
        """Keep a frame as a possible neighbour of the next ones (the detector refills this
        from the map's latest entries when it reopens one)."""
        self._recent.appendleft((features, fvec))

    def camera_for(self, calib: Calibration | None, image_size: tuple[int, int]) -> tuple[Calibration, bool]:
        """The calibration for monocular triangulation: the frame's own, else one with a focal
        guessed from the image size (cached per size); and whether it was guessed."""
        if calib is not None:
            return calib, False
        guessed = self._guessed.get(image_size)
        if guessed is None:
            guessed = self._guessed[image_size] = Calibration(left=guess_camera(*image_size),
                                                             source="focal guessed from the image size")
        return guessed, True

    def _triangulate(
        self, features: Features, fvec: FeatureVector, calib: Calibration | None
    ) -> tuple[Points3D | None, str | None, Calibration | None]:
        """Points of the features from the newest neighbour with enough parallax, or None.

        Neighbours are tried newest first while the newer ones fail for too little baseline;
        a neighbour with too few matches, or whose matches hold no one motion, ends the search
        (on the CamVid revisit sets, CamVid train and val, the corridor, the desk loop and KITTI,
        no older neighbour ever triangulated after either)."""
        mono = self.config.monocular
        if mono is None or not len(features) or not self._recent:
            return None, None, calib
        cam_calib, guessed = self.camera_for(calib, features.image_size)
        settings = TwoViewConfig(threshold_px=mono.threshold_px, min_inliers=mono.min_inliers,
                                 min_median_angle_deg=mono.min_median_angle_deg)
        for nb_features, nb_fvec in self._recent:
            matches = match_features(features, nb_features, fvec, nb_fvec, ratio=mono.ratio)
            if len(matches) < mono.min_inliers:
                break  # an older neighbour shares fewer features still
            two = triangulate_two_view(
                features.keypoints[matches.query], nb_features.keypoints[matches.candidate],
                cam_calib.left, settings, octaves=features.octaves[matches.query],
            )
            if not two.ok:
                if two.baseline_limited:
                    continue  # too little baseline: an older neighbour has more
                break  # the matches hold no one motion: an older neighbour's would hold fewer
            points = Points3D.empty(len(features))
            xyz, sd, sl = points.xyz.copy(), points.sigma_depth.copy(), points.sigma_lateral.copy()
            xyz[matches.query], sd[matches.query], sl[matches.query] = (
                two.points.xyz, two.points.sigma_depth, two.points.sigma_lateral)
            return Points3D(xyz, sd, sl, metric=False), "mono-guessed-focal" if guessed else "mono", cam_calib
        return None, None, calib
