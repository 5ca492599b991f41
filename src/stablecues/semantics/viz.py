"""Pictures of a segmentation: class overlay, uncertainty map, kept and dropped keypoints.

Every function draws on a Matplotlib ``ax`` handed in; nothing is shown.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..types import Features
from .classes import CLASS_NAMES, PALETTE
from .inference import SegmentationResult
from .masking import MaskReport


def colorize(labels: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB CamVid colours of an (H, W) label image (void black)."""
    return PALETTE[np.minimum(labels, PALETTE.shape[0] - 1)]


def overlay(rgb: np.ndarray, labels: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """(H, W, 3) uint8 blend of an RGB frame and its class colours."""
    blend = (1.0 - alpha) * rgb.astype(np.float32) + alpha * colorize(labels).astype(np.float32)
    return np.clip(blend, 0, 255).astype(np.uint8)


def plot_overlay(ax: Any, rgb: np.ndarray, seg: SegmentationResult, legend: bool = True) -> None:
    """Frame with the class colours blended in, and a legend of the classes present."""
    ax.imshow(overlay(rgb, seg.labels))
    ax.set_title(f"classes (T={seg.samples})")
    ax.axis("off")
    if legend:
        from matplotlib.patches import Patch

        present = np.unique(seg.labels)
        handles = [Patch(color=PALETTE[c] / 255.0, label=CLASS_NAMES[c]) for c in present]
        ax.legend(handles=handles, loc="lower left", fontsize=6, framealpha=0.7)


def plot_uncertainty(ax: Any, seg: SegmentationResult) -> Any:
    """Uncertainty map (variance of the winning class); returns the image artist for a colorbar."""
    im = ax.imshow(seg.uncertainty, cmap="magma", vmin=0.0, vmax=max(float(seg.uncertainty.max()), 1e-6))
    ax.set_title(f"uncertainty (max {float(seg.uncertainty.max()):.3f})")
    ax.axis("off")
    return im


def plot_keypoints(ax: Any, rgb: np.ndarray, features: Features, report: MaskReport) -> None:
    """Frame with kept keypoints in green and dropped ones in red."""
    ax.imshow(rgb)
    kp = features.keypoints
    passed = report.passed
    if kp.shape[0]:
        ax.scatter(kp[passed, 0], kp[passed, 1], s=6, c="lime", label=f"kept {int(passed.sum())}")
        ax.scatter(kp[~passed, 0], kp[~passed, 1], s=6, c="red", label=f"dropped {int((~passed).sum())}")
        ax.legend(loc="lower left", fontsize=6, framealpha=0.7)
    title = "keypoints" + (" (fallback: all kept)" if report.fallback else "")
    ax.set_title(title)
    ax.axis("off")
