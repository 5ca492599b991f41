"""Segmentation metrics with void ignored: confusion matrix, accuracies, IoU, calibration."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .classes import CLASS_NAMES, NUM_CLASSES


def confusion(pred: np.ndarray, label: np.ndarray, num_classes: int = NUM_CLASSES) -> np.ndarray:
    """(C, C) int64 confusion matrix, rows = ground truth, columns = prediction.

    Args:
        pred: (H, W) integer predicted ids.
        label: (H, W) integer ground-truth ids; ids >= ``num_classes`` (void) are ignored.
    """
    if pred.shape != label.shape:
        raise InputError(f"prediction {pred.shape} and label {label.shape}: expected equal shapes")
    valid = label < num_classes
    idx = label[valid].astype(np.int64) * num_classes + pred[valid].astype(np.int64)
    return np.bincount(idx, minlength=num_classes * num_classes).reshape(num_classes, num_classes)


@dataclass(frozen=True)
class SegMetrics:
    """Summary of a confusion matrix (fractions in [0, 1]).

    Attributes:
        global_acc: correctly labelled pixels / labelled pixels.
        class_acc: mean over classes of per-class recall.
        miou: mean over classes of intersection over union.
        iou: per-class IoU by class name.
        acc: per-class accuracy (recall) by class name.
    """

    global_acc: float
    class_acc: float
    miou: float
    iou: dict[str, float] = field(default_factory=dict)
    acc: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        return {
            "global_acc": self.global_acc,
            "class_acc": self.class_acc,
            "miou": self.miou,
            "iou": dict(self.iou),
            "acc": dict(self.acc),
        }


def summarize(conf: np.ndarray) -> SegMetrics:
    """Metrics of a (C, C) confusion matrix; classes absent from the ground truth are skipped."""
    conf = conf.astype(np.float64)
    tp = np.diag(conf)
    gt = conf.sum(axis=1)
    pr = conf.sum(axis=0)
    present = gt > 0
    acc = np.divide(tp, gt, out=np.zeros_like(tp), where=gt > 0)
    union = gt + pr - tp
    iou = np.divide(tp, union, out=np.zeros_like(tp), where=union > 0)
    total = gt.sum()
    names = CLASS_NAMES[: conf.shape[0]]
    return SegMetrics(
        global_acc=float(tp.sum() / total) if total > 0 else 0.0,
        class_acc=float(acc[present].mean()) if present.any() else 0.0,
        miou=float(iou[present].mean()) if present.any() else 0.0,
        iou={n: float(v) for n, v, p in zip(names, iou, present, strict=True) if p},
        acc={n: float(v) for n, v, p in zip(names, acc, present, strict=True) if p},
    )


class CalibrationTable:
    """Accuracy per uncertainty bin, accumulated over many frames.

    Args:
        edges: (B + 1,) increasing bin edges of the uncertainty; values beyond the last edge fall in
            the last bin.
    """

    def __init__(self, edges: np.ndarray) -> None:
        self.edges = np.asarray(edges, np.float64)
        n = self.edges.size - 1
        self.count = np.zeros(n, np.int64)
        self.correct = np.zeros(n, np.int64)

    def add(
        self, uncertainty: np.ndarray, pred: np.ndarray, label: np.ndarray, num_classes: int = NUM_CLASSES
    ) -> None:
        """Add one frame: (H, W) float uncertainty, predicted and ground-truth ids (void ignored)."""
        valid = label < num_classes
        u = uncertainty[valid]
        ok = (pred[valid] == label[valid]).astype(np.int64)
        b = np.clip(np.searchsorted(self.edges, u, side="right") - 1, 0, self.count.size - 1)
        self.count += np.bincount(b, minlength=self.count.size)
        self.correct += np.bincount(b, weights=ok, minlength=self.count.size).astype(np.int64)

    def rows(self) -> list[dict[str, float | None]]:
        """One dict per bin: lo, hi, pixel fraction, accuracy (None for empty bins)."""
        total = max(int(self.count.sum()), 1)
        out: list[dict[str, float | None]] = []
        for i in range(self.count.size):
            n = int(self.count[i])
            out.append(
                {
                    "lo": float(self.edges[i]),
                    "hi": float(self.edges[i + 1]),
                    "fraction": n / total,
                    "accuracy": float(self.correct[i] / n) if n else None,
                }
            )
        return out
