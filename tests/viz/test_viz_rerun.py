"""The Rerun logger through the library API: a LoopDetector user logs their own frames, and the
recording, read back with Rerun's reader, holds what the detector decided (issue 14.2)."""

from __future__ import annotations

import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from stablecues.detection import LoopDecision, LoopDetector, Status, preset
from stablecues.errors import ConfigError, InputError, MissingDependencyError
from stablecues.semantics.classes import NUM_CLASSES
from stablecues.semantics.inference import SegmentationResult
from stablecues.types import Frame
from stablecues.viz import RerunLogger, find_viewer, keypoint_classes
from stablecues.viz.rerun import BLOCK

pytest.importorskip("rerun")


def read_rrd(path: Path) -> dict[str, list[dict[str, Any]]]:
    """entity path -> rows (timelines as integer nanoseconds / sequence numbers), in frame order."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    rows: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        columns = {}
        for name, column in zip(batch.schema.names, batch.columns, strict=True):
            columns[name] = column.cast(pa.int64()) if pa.types.is_temporal(column.type) else column
        rows[chunk.entity_path] += pa.table(columns).to_pylist()
    for items in rows.values():
        items.sort(key=lambda r: r.get("frame") or 0)
    return rows


def _frames(n: int = 12) -> list[Frame]:
    """A drive along a textured wall that comes back to its start (frames n-4.. revisit 0..)."""
    rng = np.random.default_rng(5)
    pano = np.full((240, 1100), 110, np.uint8)
    for _ in range(1300):
        x, y = int(rng.integers(0, 1100)), int(rng.integers(0, 240))
        w, h = int(rng.integers(3, 25)), int(rng.integers(3, 25))
        cv2.rectangle(pano, (x, y), (x + w, y + h), int(rng.integers(0, 256)), -1)
    pano = cv2.GaussianBlur(pano, (3, 3), 0)
    out = []
    for i in range(n):
        x = 60 * i if i < n - 4 else 60 * (i - (n - 4)) + 5
        out.append(Frame(index=i, name=f"{i:03d}", timestamp=0.5 * i, image=pano[:, x : x + 320].copy()))
    return out


def _segment(image: np.ndarray) -> SegmentationResult:
    """A segmentation that is a function of the pixel (bright: Building, dark: Tree, else Road)."""
    grey = np.asarray(image, np.uint8)
    labels = np.where(grey > 150, 1, np.where(grey < 70, 5, 3)).astype(np.uint8)
    h, w = labels.shape
    return SegmentationResult(labels, np.ones((h, w), np.float32), np.zeros((h, w), np.float32), 1,
                              np.zeros((NUM_CLASSES, 1, 1), np.float32))


def test_a_detector_user_logs_their_frames(tmp_path: Path) -> None:
    frames = _frames()
    config = preset("dynamic", {"query": {"exclude_recent": 3, "temporal_k": 1},
                                "features": {"n_features": 300}})
    rrd = tmp_path / "mine.rrd"
    seen: list[SegmentationResult] = []

    def segment(image: np.ndarray) -> SegmentationResult:
        seen.append(_segment(image))
        return seen[-1]

    decisions = []
    with RerunLogger(rrd, image_of=lambda i: frames[i].image, jpeg_quality=None) as logger:
        detector = LoopDetector(config, segmenter=logger.watch_segmenter(segment))
        for frame in frames:
            d = detector.process(frame)
            logger.observe(frame, d, detector)
            decisions.append((d, detector.db.entry(d.entry_id).features.keypoints.copy()))
        detector.close()
    assert logger.frames_logged == len(frames) and len(seen) == len(frames)
    rec = read_rrd(rrd)
    images = rec["/camera/image"]
    assert [r["frame"] for r in images] == list(range(len(frames)))
    assert [r["time"] for r in images] == [int(0.5e9 * i) for i in range(len(frames))]
    np.testing.assert_array_equal(
        np.frombuffer(bytes(images[3]["Image:buffer"][0]), np.uint8).reshape(240, 320), frames[3].image)
    keypoints = rec["/camera/image/keypoints"]
    for row, (d, kp), seg in zip(keypoints, decisions, seen, strict=True):
        np.testing.assert_allclose(np.array(row["Points2D:positions"]), kp)
        assert len(kp) == d.n_kept
        # coloured by the class the detector's segmentation gave each keypoint
        np.testing.assert_array_equal(row["Points2D:class_ids"], keypoint_classes(kp, seg.labels))
    top = [r["BarChart:values"] for r in rec["/scores/top"]]
    for values, (d, _) in zip(top, decisions, strict=True):
        np.testing.assert_allclose(np.array(values[0]["buffer"] if values else []),
                                   [s for _, s in d.results[:10]], rtol=1e-6)
    accepted = [d for d, _ in decisions if d.accepted]
    assert accepted, "the drive comes back: loops must be accepted"
    loops = rec["/loops/accepted"]
    assert [r["candidate_frame"][0] for r in loops] == [d.candidate_frame for d in accepted]
    assert [r["inliers"][0] for r in loops] == [d.verification.n_inliers for d in accepted if d.verification]
    assert [r["frame"] for r in rec["/loops/pair"]] == [d.frame_index for d in accepted]
    assert "/world/camera" not in rec  # these frames carry no pose


def _decision(i: int, status: Status = Status.CLOSE_MATCHES_ONLY, **kw: Any) -> LoopDecision:
    return LoopDecision(frame_index=i, entry_id=-1, status=status, **kw)


def test_trajectory_blocks_and_loop_edges(tmp_path: Path) -> None:
    """Poses make a line strip per block of BLOCK frames, each block starting where the last ended,
    and accepted loops edges between the two positions; without a stamp the time timeline is left out."""
    n = BLOCK + 20
    image = np.zeros((8, 8), np.uint8)
    rrd = tmp_path / "track.rrd"
    with RerunLogger(rrd, jpeg_quality=None) as logger:
        for i in range(n):
            pose = np.eye(4)
            pose[:3, 3] = (i, 0.5 * i, 0)
            stamp = float("nan") if i == 5 else 1.6e9 + i  # Unix time: a date timeline
            d = _decision(i, Status.LOOP_DETECTED, candidate=0, candidate_frame=i - 100) if i in (150, 270) \
                else _decision(i)
            logger.log_frame(Frame(index=i, name=str(i), timestamp=stamp, image=image, pose=pose), d)
    rec = read_rrd(rrd)
    first, second = rec["/world/trajectory/0000"], rec["/world/trajectory/0001"]
    assert len(first) == BLOCK and len(second) == n - BLOCK
    assert len(first[-1]["LineStrips3D:strips"][0]) == BLOCK
    last = second[-1]["LineStrips3D:strips"][0]
    assert len(last) == n - BLOCK + 1  # starts at the previous block's last point
    np.testing.assert_allclose(last[0], (BLOCK - 1, 0.5 * (BLOCK - 1), 0))
    np.testing.assert_allclose(last[-1], (n - 1, 0.5 * (n - 1), 0))
    edges = rec["/world/loops/0000"]
    assert [r["frame"] for r in edges] == [150, 270]
    np.testing.assert_allclose(edges[-1]["LineStrips3D:strips"], [[[150, 75, 0], [50, 25, 0]],
                                                                  [[270, 135, 0], [170, 85, 0]]])
    loops = rec["/loops/accepted"]
    assert [(r["query_frame"][0], r["candidate_frame"][0], r["inliers"][0]) for r in loops] == [
        (150, 50, 0), (270, 170, 0)]
    times = {r["frame"]: r.get("time") for r in rec["/camera/image"]}
    assert times[5] is None and times[6] == int((1.6e9 + 6) * 1e9)


def test_timings_and_scores_are_logged(tmp_path: Path) -> None:
    rrd = tmp_path / "t.rrd"
    d = _decision(0, Status.LOW_SCORES, candidate=3, candidate_frame=3, score=0.25, raw_score=0.05,
                  results=((3, 0.25), (1, 0.2), (2, 0.1)), timings={"extract": 4.5, "query": 0.25,
                                                                    "verify": float("nan")})
    with RerunLogger(rrd, top_scores=2) as logger:
        logger.log_frame(Frame(index=0, name="0", timestamp=2.0, image=np.zeros((16, 16, 3), np.uint8)), d,
                         keypoints=np.array([[1.0, 2.0], [3.0, 4.0]], np.float32))
    rec = read_rrd(rrd)
    assert rec["/timing/extract"][0]["Scalars:scalars"] == [4.5]
    assert rec["/timing/query"][0]["Scalars:scalars"] == [0.25]
    assert "/timing/verify" not in rec  # the stage did not run
    assert rec["/scores/best"][0]["Scalars:scalars"] == [0.25]
    assert rec["/scores/raw"][0]["Scalars:scalars"] == [0.05]
    np.testing.assert_allclose(rec["/scores/top"][0]["BarChart:values"][0]["buffer"], [0.25, 0.2])
    assert rec["/camera/image/keypoints"][0]["Points2D:positions"] == [[1.0, 2.0], [3.0, 4.0]]
    assert "Points2D:class_ids" not in rec["/camera/image/keypoints"][0]
    text = rec["/detection/decisions"][0]["TextLog:text"][0]
    assert text == "frame 0: low_scores, candidate frame 3 (score 0.250)"
    assert rec["/detection/kept"][0]["Scalars:scalars"] == [2.0]


def test_keypoint_classes() -> None:
    labels = np.array([[0, 1, 2], [3, 4, 5]], np.uint8)
    kp = np.array([[0, 0], [2.4, 1.2], [1.6, 0.4], [-5, 9], [10, -1]], np.float32)
    np.testing.assert_array_equal(keypoint_classes(kp, labels), [0, 5, 2, 3, 2])
    assert keypoint_classes(np.zeros((0, 2), np.float32), labels).shape == (0,)
    with pytest.raises(InputError, match="keypoints"):
        keypoint_classes(np.zeros((3, 3)), labels)
    with pytest.raises(InputError, match="labels"):
        keypoint_classes(kp, np.zeros((2, 2, 3)))


def test_find_viewer(tmp_path: Path) -> None:
    with pytest.raises(MissingDependencyError, match="no Rerun viewer found"):
        find_viewer(str(tmp_path))
    viewer = tmp_path / "rerun"
    viewer.write_text("#!/bin/sh\n")
    viewer.chmod(0o755)
    assert find_viewer(str(tmp_path)) == viewer


def test_bad_settings_are_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(ConfigError, match="give a .rrd file"):
        RerunLogger()
    with pytest.raises(ConfigError, match="does not exist"):
        RerunLogger(tmp_path / "no" / "x.rrd")
    with pytest.raises(ConfigError, match="top_scores"):
        RerunLogger(tmp_path / "x.rrd", top_scores=0)
    with pytest.raises(ConfigError, match="jpeg_quality"):
        RerunLogger(tmp_path / "x.rrd", jpeg_quality=101)
    if sys.platform.startswith("linux"):  # elsewhere a viewer would really open
        monkeypatch.delenv("DISPLAY", raising=False)
        monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
        with pytest.raises((ConfigError, MissingDependencyError), match="display|viewer"):
            RerunLogger(spawn=True)
