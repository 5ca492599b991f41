"""Logging each frame's detection to a Rerun recording (``stablecues run --rerun FILE.rrd``).

Entities, all on the sequence timeline ``frame`` (the frame's index) and, where the frame has a
timestamp, the time timeline ``time`` (a date for Unix-epoch stamps, a duration otherwise)::

    camera/image                the frame's image (JPEG unless ``jpeg_quality=None``)
    camera/image/keypoints      Points2D: the kept keypoints; class ids of the segmentation (the
                                CamVid palette and names, from the static annotation context on
                                ``camera``) when the frame was segmented or carries labels
    scores/top                  BarChart: the query's normalised scores, best first (top ``top_scores``)
    scores/best, scores/raw     Scalars: the candidate's normalised and raw BoW scores
    detection/decisions         TextLog: the stage that decided, and the candidate
    detection/kept              Scalars: keypoints kept (after semantic selection)
    loops/accepted              AnyValues (query_frame, candidate_frame, inliers, score) per accepted loop
    loops/pair                  the query and candidate images side by side (needs ``image_of``)
    loops/pair/matches          LineStrips2D: the loop's inlier matches across the pair
    world/trajectory/NNNN       LineStrips3D: camera positions from the frames' poses (blocks of
                                :data:`BLOCK` frames, so the recording grows linearly)
    world/camera                Points3D: the current camera position
    world/loops/NNNN            LineStrips3D: accepted loops as edges between camera positions
    timing/STAGE                Scalars: milliseconds of each stage (extract, segment, ..., total)

``rerun`` (the ``rerun`` extra) is imported when a logger is made, never before.
"""

from __future__ import annotations

import math
import os
import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ConfigError, InputError, MissingDependencyError
from ..semantics.classes import CLASS_NAMES, PALETTE, VOID_ID, VOID_NAME

if TYPE_CHECKING:
    from ..detection.decision import LoopDecision
    from ..detection.detector import LoopDetector
    from ..detection.prepare import Segmenter
    from ..semantics.inference import SegmentationResult
    from ..types import Frame

__all__ = ["BLOCK", "RerunLogger", "find_viewer", "keypoint_classes"]

#: frames per trajectory (and loop-edge) block entity: each frame re-logs only its own block
BLOCK = 256
#: stamps at or above this are read as Unix time (after 2001-09-09), below as durations
_EPOCH_FROM = 1e9
_KEYPOINT_COLOUR = (255, 200, 0)
_INLIER_COLOUR = (40, 220, 60)
_TRAJECTORY_COLOUR = (80, 160, 255)
_LOOP_COLOUR = (255, 60, 60)
_INSTALL = 'pip install "stablecues[rerun]"'


def find_viewer(path: str | None = None) -> Path:
    """The Rerun viewer executable: ``rerun`` on ``path`` (default: ``$PATH``), else the one the
    ``rerun-sdk`` wheel bundles.

    Raises:
        MissingDependencyError: there is none.
    """
    found = shutil.which("rerun", path=path)
    if found:
        return Path(found)
    if path is None:
        import importlib.util

        spec = importlib.util.find_spec("rerun_cli")
        if spec is not None and spec.origin is not None:
            bundled = Path(spec.origin).parent / "rerun"
            if bundled.is_file() and os.access(bundled, os.X_OK):
                return bundled
    raise MissingDependencyError(
        f"no Rerun viewer found (no 'rerun' executable on PATH nor bundled with rerun-sdk): {_INSTALL}, "
        "or write a recording with --rerun FILE.rrd and open it where a viewer is"
    )


def _check_display() -> None:
    """A viewer opens a window: on Linux that needs X11 or Wayland.

    Raises:
        ConfigError: no display.
    """
    shown = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    if sys.platform.startswith("linux") and not shown:
        raise ConfigError(
            "the Rerun viewer needs a display and neither DISPLAY nor WAYLAND_DISPLAY is set: write a "
            "recording with --rerun FILE.rrd and open it with `rerun FILE.rrd` where there is one"
        )


def keypoint_classes(keypoints: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """The class id under each keypoint.

    Args:
        keypoints: (N, 2) float pixel coordinates (x, y) in the frame's image.
        labels: (H, W) integer class ids of the frame, at the image's size.

    Returns:
        (N,) uint16 class ids (nearest pixel, clipped to the image).

    Raises:
        InputError: ``keypoints`` is not (N, 2) or ``labels`` is not a 2-D image.
    """
    kp = np.asarray(keypoints, np.float64)
    lab = np.asarray(labels)
    if kp.ndim != 2 or kp.shape[1] != 2:
        raise InputError(f"keypoints: expected shape (N, 2), got {kp.shape}")
    if lab.ndim != 2 or lab.size == 0:
        raise InputError(f"labels: expected a (H, W) image, got shape {lab.shape}")
    h, w = lab.shape
    x = np.clip(np.rint(kp[:, 0]), 0, w - 1).astype(np.intp)
    y = np.clip(np.rint(kp[:, 1]), 0, h - 1).astype(np.intp)
    return lab[y, x].astype(np.uint16)


class RerunLogger:
    """Logs the detector's per-frame results to a Rerun recording.

    An observer for :func:`stablecues.detection.run.run_dataset` (``observers=[logger]``), or,
    around your own loop::

        with RerunLogger("run.rrd") as logger:
            for frame in frames:
                logger.observe(frame, detector.process(frame), detector)

    Args:
        path: ``.rrd`` file to write (its folder must exist), or None.
        spawn: also stream to a Rerun viewer started now (needs the viewer and a display).
        image_of: ``frame index -> image`` of earlier frames, to draw an accepted loop's image
            pair; without it a loop is logged as its frame ids, inlier count and matches.
        top_scores: how many of the query's best scores the bar chart shows.
        jpeg_quality: JPEG quality of the logged images (smaller recordings), or None for raw pixels.
        application_id: the recording's application id (the viewer groups recordings by it).
        recording_id: the recording's id (default: a new one).
        port: the spawned viewer's port.

    Raises:
        ConfigError: neither a file nor a viewer, a file whose folder does not exist, or
            ``spawn`` without a display.
        MissingDependencyError: ``spawn`` without a viewer executable.
        ImportError: the ``rerun`` extra is not installed.
    """

    def __init__(
        self,
        path: str | Path | None = None,
        *,
        spawn: bool = False,
        image_of: Callable[[int], np.ndarray] | None = None,
        top_scores: int = 10,
        jpeg_quality: int | None = 75,
        application_id: str = "stablecues",
        recording_id: str | None = None,
        port: int = 9876,
    ) -> None:
        if path is None and not spawn:
            raise ConfigError("RerunLogger: give a .rrd file to write, spawn a viewer, or both")
        if path is not None and not Path(path).parent.is_dir():
            raise ConfigError(f"{path}: the recording's folder {Path(path).parent} does not exist")
        if top_scores < 1 or (jpeg_quality is not None and not 1 <= jpeg_quality <= 100):
            raise ConfigError(f"RerunLogger: top_scores >= 1 and jpeg_quality in 1..100 are required, got "
                              f"{top_scores} and {jpeg_quality}")
        viewer = None
        if spawn:
            viewer = find_viewer()
            _check_display()
        import rerun as rr

        self._rr = rr
        self.path = None if path is None else Path(path)
        self.image_of = image_of
        self.top_scores = top_scores
        self.jpeg_quality = jpeg_quality
        self.frames_logged = 0
        self._rec = rr.RecordingStream(application_id, recording_id=recording_id)
        self._closed = False
        self._open_sinks(viewer, port)
        self._epoch: bool | None = None
        self._positions: dict[int, np.ndarray] = {}
        self._track: list[list[float]] = []
        self._n_posed = 0
        self._edges: list[list[list[float]]] = []
        self._n_loops = 0
        self._segmentation: tuple[int, SegmentationResult] | None = None
        self._rec.log("camera", rr.AnnotationContext(
            [rr.AnnotationInfo(id=i, label=name, color=tuple(int(c) for c in PALETTE[i]))
             for i, name in enumerate(CLASS_NAMES)]
            + [rr.AnnotationInfo(id=VOID_ID, label=VOID_NAME, color=tuple(int(c) for c in PALETTE[VOID_ID]))]
        ), static=True)

    def _open_sinks(self, viewer: Path | None, port: int) -> None:
        rr = self._rr
        sinks: list[Any] = []
        if self.path is not None:
            sinks.append(rr.FileSink(self.path))
        if viewer is not None:
            try:
                rr.spawn(port=port, connect=False, executable_path=str(viewer), recording=self._rec)
            except RuntimeError as exc:
                raise ConfigError(f"the Rerun viewer {viewer} did not start: {exc}") from None
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{port}/proxy"))
        self._rec.set_sinks(*sinks)

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Flush and close the recording (the ``.rrd`` file is complete afterwards)."""
        if not self._closed:
            self._closed = True
            self._rec.flush()
            self._rec.disconnect()

    def __enter__(self) -> RerunLogger:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # ------------------------------------------------------------------ inputs
    def watch_segmenter(self, segmenter: Segmenter) -> Segmenter:
        """``segmenter`` that also keeps its latest result, so the keypoints of the frame it
        segmented are coloured by the classes the detector saw (pass the result to
        :class:`~stablecues.detection.LoopDetector` or ``run_dataset(segmenter=...)``)."""

        def watched(image: np.ndarray) -> SegmentationResult:
            result = segmenter(image)
            self._segmentation = (id(image), result)
            return result

        return watched

    def observe(self, frame: Frame, decision: LoopDecision, detector: LoopDetector) -> None:
        """Log one frame the detector has just processed (and stored, for its keypoints).

        The keypoints are the stored entry's (those kept after semantic selection); their
        classes come from the segmentation :meth:`watch_segmenter` saw for this image, else from
        the frame's label image when the detector reads its classes from labels.
        """
        keypoints = None
        if 0 <= decision.entry_id < len(detector):
            keypoints = detector.db.entry(decision.entry_id).features.keypoints
        labels = None
        seg, self._segmentation = self._segmentation, None
        if seg is not None and seg[0] == id(frame.image):
            labels = seg[1].labels
        elif detector.config.semantic_source == "labels" and frame.labels is not None:
            labels = frame.labels
        self.log_frame(frame, decision, keypoints, labels)

    # ------------------------------------------------------------------ logging
    def log_frame(
        self,
        frame: Frame,
        decision: LoopDecision,
        keypoints: np.ndarray | None = None,
        labels: np.ndarray | None = None,
    ) -> None:
        """Log one frame's image, keypoints, scores, decision, loop, pose and stage times.

        Args:
            frame: the frame.
            decision: the detector's decision for it.
            keypoints: (N, 2) float32 kept keypoints (x, y), or None to log none.
            labels: (H, W) class ids of the frame, to colour the keypoints by class; or None.
        """
        rr = self._rr
        self._set_time(frame)
        self._rec.log("camera/image", self._image(frame.image))
        if keypoints is not None:
            # a fresh, aligned copy: stored keypoints can be unaligned views of a database blob,
            # which Arrow (in rerun) aborts the process on
            kp = np.array(keypoints, np.float32).reshape(-1, 2)
            if labels is not None:
                points = rr.Points2D(kp, class_ids=keypoint_classes(kp, labels))
            else:
                points = rr.Points2D(kp, colors=_KEYPOINT_COLOUR)
            self._rec.log("camera/image/keypoints", points)
            self._rec.log("detection/kept", rr.Scalars(float(len(kp))))
        self._log_scores(decision)
        self._log_pose(frame)
        if decision.accepted:
            self._log_loop(frame, decision)
        for stage, ms in decision.timings.items():
            if math.isfinite(ms):
                self._rec.log(f"timing/{stage}", rr.Scalars(float(ms)))
        self.frames_logged += 1

    def _set_time(self, frame: Frame) -> None:
        self._rec.set_time("frame", sequence=int(frame.index))
        t = float(frame.timestamp)
        if not math.isfinite(t):
            self._rec.disable_timeline("time")
            return
        if self._epoch is None:  # decided once: a timeline keeps one kind
            self._epoch = t >= _EPOCH_FROM
        if self._epoch:
            self._rec.set_time("time", timestamp=t)
        else:
            self._rec.set_time("time", duration=t)

    def _image(self, image: np.ndarray) -> Any:
        """An archetype for a grey or BGR image, JPEG-encoded when asked."""
        rr = self._rr
        img = np.ascontiguousarray(image)
        if self.jpeg_quality is not None:
            import cv2

            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
            if ok:
                return rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg")
        if img.ndim == 3 and img.shape[2] == 3:
            return rr.Image(img, color_model="BGR")
        return rr.Image(img)

    def _log_scores(self, d: LoopDecision) -> None:
        rr = self._rr
        top = np.array([s for _, s in d.results[: self.top_scores]], np.float32)
        self._rec.log("scores/top", rr.BarChart(top))
        if d.candidate >= 0:
            self._rec.log("scores/best", rr.Scalars(float(d.score)))
            self._rec.log("scores/raw", rr.Scalars(float(d.raw_score)))
        text = f"frame {d.frame_index}: {d.status.value}"
        if d.candidate_frame >= 0:
            text += f", candidate frame {d.candidate_frame} (score {d.score:.3f})"
        if d.verification is not None:
            text += f"; {d.verification.reason}"
        level = rr.TextLogLevel.INFO if d.accepted else rr.TextLogLevel.DEBUG
        self._rec.log("detection/decisions", rr.TextLog(text, level=level))

    def _log_pose(self, frame: Frame) -> None:
        if frame.pose is None:
            return
        pose = np.asarray(frame.pose, np.float64)
        if pose.shape != (4, 4) or not np.isfinite(pose[:3, 3]).all():
            return
        rr = self._rr
        p = pose[:3, 3]
        self._positions[int(frame.index)] = p
        if self._n_posed % BLOCK == 0:  # a new block starts at the previous block's last point
            self._track = self._track[-1:]
        self._track.append(p.tolist())
        block = self._n_posed // BLOCK
        self._n_posed += 1
        self._rec.log(f"world/trajectory/{block:04d}",
                      rr.LineStrips3D([self._track], colors=_TRAJECTORY_COLOUR))
        self._rec.log("world/camera", rr.Points3D([p], colors=_TRAJECTORY_COLOUR, radii=0.3))

    def _log_loop(self, frame: Frame, d: LoopDecision) -> None:
        rr = self._rr
        v = d.verification
        inliers = v.n_inliers if v is not None else 0
        self._rec.log("loops/accepted", rr.AnyValues(
            query_frame=int(d.frame_index), candidate_frame=int(d.candidate_frame), inliers=int(inliers),
            score=float(d.score)))
        a, b = self._positions.get(int(d.frame_index)), self._positions.get(int(d.candidate_frame))
        if a is not None and b is not None:
            if self._n_loops % BLOCK == 0:
                self._edges = []
            self._edges.append([a.tolist(), b.tolist()])
            self._rec.log(f"world/loops/{self._n_loops // BLOCK:04d}",
                          rr.LineStrips3D(self._edges, colors=_LOOP_COLOUR))
            self._n_loops += 1
        if self.image_of is not None and d.candidate_frame >= 0:
            self._log_pair(frame.image, self.image_of(d.candidate_frame), d)

    def _log_pair(self, query: np.ndarray, candidate: np.ndarray, d: LoopDecision) -> None:
        """The two images side by side (query left) and the inlier matches across them."""
        rr = self._rr
        left, right = _bgr(query), _bgr(candidate)
        h = max(left.shape[0], right.shape[0])
        pair = np.zeros((h, left.shape[1] + right.shape[1], 3), np.uint8)
        pair[: left.shape[0], : left.shape[1]] = left
        pair[: right.shape[0], left.shape[1]:] = right
        self._rec.log("loops/pair", self._image(pair))
        v = d.verification
        if v is None or v.pixels_query is None or v.pixels_candidate is None:
            self._rec.log("loops/pair/matches", rr.Clear(recursive=False))
            return
        keep = np.asarray(v.inliers, bool)
        q = np.asarray(v.pixels_query, np.float32)[keep]
        c = np.asarray(v.pixels_candidate, np.float32)[keep] + np.array([left.shape[1], 0], np.float32)
        strips = np.stack((q, c), axis=1)  # (M, 2 points, 2)
        self._rec.log("loops/pair/matches", rr.LineStrips2D(strips, colors=_INLIER_COLOUR))


def _bgr(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2).astype(np.uint8)
    return img[:, :, :3].astype(np.uint8)
