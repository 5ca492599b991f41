"""Evaluation plots. Every function draws on a Matplotlib ``ax`` it is given (Agg backend, no
``plt.show()``); :func:`figure_png` turns a figure into PNG bytes for reports."""

from __future__ import annotations

import io
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure


def new_figure(width: float = 6.0, height: float = 4.5, ncols: int = 1) -> tuple[Figure, list[Axes]]:
    """A figure with ``ncols`` axes on the Agg canvas (no GUI, no global pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, ncols, squeeze=False)[0]
    return fig, list(axes)


def figure_png(fig: Figure, dpi: int = 100) -> bytes:
    """Render a figure to PNG bytes."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def plot_pr_curves(ax: Axes, curves: Sequence[tuple[str, np.ndarray, np.ndarray]]) -> None:
    """Precision-recall curves of several runs on one plot.

    Args:
        ax: the axes to draw on.
        curves: (label, (K,) recall, (K,) precision) per run, thresholds decreasing; the
            curve starts at (0, 1), the "accept nothing" point.
    """
    for label, recall, precision in curves:
        r = np.r_[0.0, np.asarray(recall, dtype=np.float64)]
        p = np.r_[1.0, np.asarray(precision, dtype=np.float64)]
        ax.step(r, p, where="post", label=label, linewidth=1.6)
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.02)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.grid(True, alpha=0.3)
    if curves:
        ax.legend(loc="lower left", fontsize=8)


def downsample_max(matrix: np.ndarray, max_size: int = 800) -> tuple[np.ndarray, int]:
    """Shrink an (N, N) matrix to at most ``max_size`` cells a side by max-pooling blocks.

    Returns:
        (the (M, M) float32 pooled matrix, the block size in frames).
    """
    m = np.asarray(matrix)
    n = m.shape[0]
    block = max(1, int(np.ceil(n / max_size)))
    if block == 1:
        return m.astype(np.float32), 1
    size = int(np.ceil(n / block))
    out = np.zeros((size, size), dtype=np.float32)
    for bi in range(size):  # row blocks: bounded memory even for 26k x 26k matrices
        rows = np.asarray(m[bi * block : (bi + 1) * block], dtype=np.float32)
        pad = size * block - n
        if pad:
            rows = np.pad(rows, ((0, 0), (0, pad)))
        out[bi] = rows.reshape(rows.shape[0], size, block).max(axis=(0, 2))
    return out, block


def plot_matrix(
    ax: Axes,
    matrix: np.ndarray,
    title: str,
    *,
    cmap: str = "viridis",
    points: Sequence[tuple[np.ndarray, np.ndarray, str, str]] = (),
    max_size: int = 800,
    colorbar: bool = False,
) -> None:
    """A loop or similarity matrix as a heatmap, row = query frame, column = earlier frame.

    Args:
        ax: the axes.
        matrix: (N, N) bool or float matrix (large ones are max-pooled for display).
        title: the axes title.
        cmap: Matplotlib colour map name.
        points: overlays (query frames, candidate frames, colour, label), e.g. detections.
        max_size: largest displayed side in cells.
        colorbar: draw a colour bar.
    """
    shown, block = downsample_max(matrix, max_size)
    n = matrix.shape[0]
    image = ax.imshow(
        shown, cmap=cmap, origin="upper", interpolation="nearest", extent=(0, n, n, 0), aspect="equal"
    )
    for rows, cols, colour, label in points:
        if len(rows):
            ax.scatter(
                np.asarray(cols) + 0.5, np.asarray(rows) + 0.5, s=9, c=colour, label=label, linewidths=0
            )
    if any(len(p[0]) for p in points):
        ax.legend(loc="upper right", fontsize=7, markerscale=1.5)
    ax.set_title(title + (f" (max over {block}x{block} blocks)" if block > 1 else ""), fontsize=9)
    ax.set_xlabel("earlier frame j")
    ax.set_ylabel("query frame i")
    if colorbar:
        ax.figure.colorbar(image, ax=ax, shrink=0.8)


def plot_status_counts(ax: Axes, counts: dict[str, int]) -> None:
    """Horizontal bars: how many frames ended with each status."""
    names = list(counts)
    ax.barh(names, [counts[k] for k in names], color="#4c72b0")
    ax.invert_yaxis()
    ax.set_xlabel("frames")
    for y, k in enumerate(names):
        ax.text(counts[k], y, f" {counts[k]}", va="center", fontsize=8)


def plot_timing(ax: Axes, table: dict[str, dict[str, Any]]) -> None:
    """Mean time per stage with a bar from min to max (ms)."""
    names = [k for k, v in table.items() if v.get("mean") is not None]
    means = np.array([table[k]["mean"] for k in names], dtype=np.float64)
    lo = means - np.array([table[k]["min"] for k in names], dtype=np.float64)
    hi = np.array([table[k]["max"] for k in names], dtype=np.float64) - means
    ax.barh(names, means, xerr=np.vstack([lo, hi]) if names else None, color="#dd8452", capsize=3)
    ax.invert_yaxis()
    ax.set_xlabel("ms per frame (mean, min to max)")
