"""The network's domain gate: the median certainty of the stream's recent frames, kept with the
entries so that a reopened map gates its next frames as an uninterrupted stream would."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from test_api_detector import textured

from stablecues import Frame, LoopDetector, preset
from stablecues.semantics.classes import CLASS_NAMES, NUM_CLASSES
from stablecues.semantics.inference import SegmentationResult

CAR = CLASS_NAMES.index("Car")


def _image(seed: int) -> np.ndarray:
    return textured(seed % 5)  # five places, revisited


def _segmenter(image: np.ndarray) -> SegmentationResult:
    """A posterior whose certainty follows the image (so it varies along the stream): a car on
    the right third, buildings elsewhere."""
    sure = 0.55 + 0.4 * float(image.mean() % 7) / 7
    prob = np.full((NUM_CLASSES, 60, 80), (1 - sure) / (NUM_CLASSES - 1), np.float32)
    prob[CLASS_NAMES.index("Building")] = sure
    prob[:, :, 55:] = (1 - sure) / (NUM_CLASSES - 1)
    prob[CAR, :, 55:] = sure
    labels = prob.argmax(0).astype(np.uint8).repeat(4, 0).repeat(4, 1)
    return SegmentationResult(labels, np.ones((240, 320), np.float32), np.zeros((240, 320), np.float32),
                              1, prob)


def _decisions(det: LoopDetector, frames: list[Frame]) -> list[tuple[object, ...]]:
    out = []
    for f in frames:
        d = det.process(f)
        out.append((d.status, d.candidate_frame, round(d.raw_score, 12), d.n_kept))
    return out


def test_a_reopened_map_gates_as_the_uninterrupted_stream(tmp_path: Path) -> None:
    cfg = preset("default", {"domain_window": 4, "query": {"exclude_recent": 2}})
    frames = [Frame(i, f"{i}.png", float(i), _image(i)) for i in range(14)]
    with LoopDetector(cfg, database=tmp_path / "whole.sqlite", segmenter=_segmenter) as det:
        whole = _decisions(det, frames)
        certainty = det.preparer.domain_certainty()
    with LoopDetector(cfg, database=tmp_path / "split.sqlite", segmenter=_segmenter) as det:
        first = _decisions(det, frames[:7])
    with LoopDetector(cfg, database=tmp_path / "split.sqlite", segmenter=_segmenter) as det:
        assert det.preparer.domain_certainty() is not None  # restored from the entries
        second = _decisions(det, frames[7:])
        assert det.preparer.domain_certainty() == certainty
    assert first + second == whole
    # the gate is live in this stream: some frames drop the car, others keep it
    kept = {n for *_, n in whole}
    assert len(kept) > 1


def test_the_window_decides_not_the_frame_alone() -> None:
    """With the median of several frames, one unsure frame in a sure stream still drops its cars."""
    sure = [0.95] * 5
    det = LoopDetector(preset("default", {"domain_window": 5}))
    det.preparer.restore_certainties([(s - 1 / NUM_CLASSES) / (1 - 1 / NUM_CLASSES) for s in sure])
    assert det.preparer.domain_certainty() > 0.9
    alone = LoopDetector(preset("default", {"domain_window": 1}))
    alone.preparer.restore_certainties([0.5, 0.6, 0.95])
    assert alone.preparer.domain_certainty() == 0.95  # only the latest counts
    det.close()
    alone.close()
