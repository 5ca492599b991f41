"""Evaluation of the ONNX segmentation model on a CamVid split (no torch needed)."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from .classes import NUM_CLASSES
from .data import load_split
from .inference import SegmentationModel
from .metrics import CalibrationTable, confusion, summarize

log = logging.getLogger(__name__)

#: Bin edges of the calibration table for the winning-class variance (range [0, 0.25]).
VARIANCE_BINS = np.array([0.0, 0.001, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25], np.float64)


def evaluate_model(
    model: SegmentationModel,
    data: str | Path,
    split: str = "test",
    t: int | None = None,
    *,
    cache_dir: str | Path | None = None,
    limit: int | None = None,
    bins: np.ndarray = VARIANCE_BINS,
    progress: bool = False,
) -> dict[str, Any]:
    """Segment every frame of a split and score it at the labels' resolution, void ignored.

    Args:
        model: the loaded ONNX model.
        data: the CamVid folder.
        split: "train", "val" or "test".
        t: Monte-Carlo samples (None: the model's default).
        cache_dir: optional folder of the decoded-split cache.
        limit: evaluate only the first ``limit`` frames.
        bins: uncertainty bin edges of the calibration table.
        progress: show a progress bar.

    Returns:
        {"split", "frames", "T", "global_acc", "class_acc", "miou", "iou", "acc",
        "calibration": [{"lo", "hi", "fraction", "accuracy"}], "ms_per_frame"}.
    """
    frames = load_split(data, split, cache_dir=cache_dir, limit=limit)
    t = model.default_t if t is None else t
    conf = np.zeros((NUM_CLASSES, NUM_CLASSES), np.int64)
    calib = CalibrationTable(bins)
    seconds = 0.0
    for image, label in tqdm(
        zip(frames.images, frames.labels, strict=True), total=len(frames), disable=not progress, desc=split
    ):
        start = time.perf_counter()
        result = model.predict(image, t, bgr=False)
        seconds += time.perf_counter() - start
        conf += confusion(result.labels, label)
        calib.add(result.uncertainty, result.labels, label)
    metrics = summarize(conf)
    out: dict[str, Any] = {"split": split, "frames": len(frames), "T": t}
    out.update(metrics.as_dict())
    out["calibration"] = calib.rows()
    out["ms_per_frame"] = 1000.0 * seconds / max(len(frames), 1)
    return out


def format_report(result: dict[str, Any]) -> str:
    """Human-readable table of :func:`evaluate_model`'s result."""
    lines = [
        f"CamVid {result['split']} ({result['frames']} frames, T={result['T']}): "
        f"mIoU {100 * result['miou']:.1f} %, global accuracy {100 * result['global_acc']:.1f} %, "
        f"class-average accuracy {100 * result['class_acc']:.1f} %",
        f"{'class':<12} {'IoU %':>7} {'acc %':>7}",
    ]
    for name, iou in result["iou"].items():
        lines.append(f"{name:<12} {100 * iou:7.1f} {100 * result['acc'][name]:7.1f}")
    lines.append("uncertainty calibration (accuracy per bin):")
    lines.append(f"{'bin':<20} {'pixels %':>9} {'acc %':>7}")
    for row in result["calibration"]:
        acc = "-" if row["accuracy"] is None else f"{100 * row['accuracy']:.1f}"
        lines.append(f"[{row['lo']:.3f}, {row['hi']:.3f}){'':<4} {100 * row['fraction']:9.2f} {acc:>7}")
    return "\n".join(lines)
