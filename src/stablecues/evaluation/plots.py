"""Evaluation plots. Every function draws on a Matplotlib ``ax`` it is given (Agg backend, no
``plt.show()``); :func:`figure_png` turns a figure into PNG bytes for reports."""

from __future__ import annotations

import io
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, NamedTuple

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


#: Matplotlib settings of report figures: fonts that stay legible at the size a page shows them
REPORT_STYLE: dict[str, Any] = {
    "font.size": 11,
    "axes.titlesize": 12,
    "axes.labelsize": 11,
    "xtick.labelsize": 10,
    "ytick.labelsize": 10,
    "legend.fontsize": 10,
}

# line styles and markers that tell runs apart where their curves coincide
_LINESTYLES = ("-", "--", "-.", ":")
_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")


@contextmanager
def report_style() -> Iterator[None]:
    """Draw and render inside this block to get :data:`REPORT_STYLE` (restored afterwards)."""
    from matplotlib import rc_context

    with rc_context(REPORT_STYLE):  # type: ignore[arg-type]
        yield


def full_precision_point(recall: np.ndarray, precision: np.ndarray) -> float:
    """The largest recall of a PR curve with no false positive (precision 1), 0 when none."""
    r = np.asarray(recall, dtype=np.float64)
    p = np.asarray(precision, dtype=np.float64)
    ok = p >= 1.0
    return float(r[ok].max()) if ok.any() else 0.0


def pr_zoom_limits(curves: Sequence[tuple[str, np.ndarray, np.ndarray]]) -> tuple[float, float]:
    """Axis limits that show where the curves differ: (largest recall shown, lowest precision shown).

    The recall axis ends a little past the largest recall reached; the precision axis starts
    a little under the lowest precision reached (never above 0.9, so that a curve at 1 still
    has room under it).
    """
    recalls = [float(np.max(r)) for _, r, _ in curves if len(r)]
    precisions = [float(np.min(p)) for _, _, p in curves if len(p)]
    r_max = max(recalls, default=0.0)
    p_min = min(precisions, default=1.0)
    x_hi = min(1.0, max(0.05, 1.1 * r_max))
    y_lo = max(0.0, min(0.9, p_min - 0.1 * (1.0 - p_min) - 0.01))
    return x_hi, y_lo


def plot_pr_curves(
    ax: Axes, curves: Sequence[tuple[str, np.ndarray, np.ndarray]], *, zoom: bool = False
) -> None:
    """Precision-recall curves of several runs on one plot.

    Curves that coincide stay apart: the first is drawn widest and each later one narrower on
    top of it (a shared stretch shows every run's colour as nested bands), each run has its
    own dash pattern, and a marker shows where each reaches its recall at 100 % precision.

    Args:
        ax: the axes to draw on.
        curves: (label, (K,) recall, (K,) precision) per run, thresholds decreasing; the
            curve starts at (0, 1), the "accept nothing" point.
        zoom: limit the axes to where the curves are (:func:`pr_zoom_limits`) instead of the
            unit square.
    """
    from matplotlib.colors import to_hex

    k = len(curves)
    ends: list[tuple[str, float, str]] = []
    for n, (label, recall, precision) in enumerate(curves):
        r = np.r_[0.0, np.asarray(recall, dtype=np.float64)]
        p = np.r_[1.0, np.asarray(precision, dtype=np.float64)]
        width = 1.8 + 2.2 * (k - 1 - n)
        (line,) = ax.step(r, p, where="post", label=label, linewidth=width,
                          linestyle=_LINESTYLES[n % len(_LINESTYLES)], zorder=2 + n, alpha=0.9)
        r100 = full_precision_point(r, p)
        ax.plot([r100], [1.0], marker=_MARKERS[n % len(_MARKERS)], markersize=9, color=line.get_color(),
                markeredgecolor="black", linestyle="none", zorder=10 + n, clip_on=False)
        ends.append((label.split(" (")[0], r100, to_hex(line.get_color())))
    if zoom:
        x_hi, y_lo = pr_zoom_limits(curves)
        ax.set_xlim(0.0, x_hi)
        ax.set_ylim(y_lo, 1.0 + 0.03 * (1.0 - y_lo))
        ax.set_title(f"zoom: recall 0 to {x_hi:.2g}, precision {y_lo:.2g} to 1")
        _label_ends(ax, ends, x_hi, y_lo)
    else:
        ax.set_xlim(0.0, 1.0)
        ax.set_ylim(0.0, 1.03)
        ax.set_title("whole curve")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.grid(True, alpha=0.3)
    if curves and not zoom:
        ax.legend(loc="lower left")


class Overlay(NamedTuple):
    """Points drawn over a matrix: (rows[k], cols[k]) for each k, e.g. accepted detections."""

    rows: np.ndarray
    cols: np.ndarray
    colour: str
    label: str
    marker: str = "o"


def _label_ends(ax: Axes, ends: Sequence[tuple[str, float, str]], x_hi: float, y_lo: float) -> None:
    """Name each run beside the point where it leaves precision 1 (labels stacked downwards,
    so that runs whose curves coincide are still told apart); at most eight."""
    step = 0.085 * (1.0 - y_lo)
    for n, (name, r100, colour) in enumerate(ends[:8]):
        right = r100 > 0.6 * x_hi
        ax.annotate(
            f"{name}: {100 * r100:.1f} %",
            xy=(r100, 1.0),
            xytext=(r100 + (-0.03 if right else 0.03) * x_hi, 1.0 - (n + 1) * step),
            ha="right" if right else "left",
            va="center",
            color=colour,
            fontweight="bold",
            arrowprops={"arrowstyle": "-", "color": colour, "linewidth": 1.0},
            bbox={"boxstyle": "round,pad=0.2", "facecolor": "white", "edgecolor": colour, "alpha": 0.9},
            zorder=20,
        )


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
    points: Sequence[Overlay] = (),
    max_size: int = 800,
    colorbar: bool = False,
    colorbar_label: str = "",
) -> None:
    """A loop or similarity matrix as a heatmap, row = query frame, column = earlier frame.

    Args:
        ax: the axes.
        matrix: (N, N) bool or float matrix (large ones are max-pooled for display).
        title: the axes title.
        cmap: Matplotlib colour map name.
        points: overlays (query frames, candidate frames, colour, label, marker), e.g. detections.
        max_size: largest displayed side in cells.
        colorbar: draw a colour bar.
        colorbar_label: its label.
    """
    shown, block = downsample_max(matrix, max_size)
    n = matrix.shape[0]
    image = ax.imshow(
        shown, cmap=cmap, origin="upper", interpolation="nearest", extent=(0, n, n, 0), aspect="equal"
    )
    for rows, cols, colour, label, marker in points:
        if len(rows):
            line_marker = marker in ("x", "+", "1", "2", "3", "4", "|", "_")
            ax.scatter(np.asarray(cols) + 0.5, np.asarray(rows) + 0.5, s=42, c=colour, label=label,
                       marker=marker, linewidths=1.8 if line_marker else 0.6,
                       edgecolors=None if line_marker else "white", zorder=3)
    if any(len(p[0]) for p in points):
        ax.legend(loc="upper right")
    ax.set_title(title + (f"\n(max over {block}x{block} blocks)" if block > 1 else ""))
    ax.set_xlabel("earlier frame j")
    ax.set_ylabel("query frame i")
    if colorbar:
        bar = ax.figure.colorbar(image, ax=ax, shrink=0.85, pad=0.02)
        if colorbar_label:
            bar.set_label(colorbar_label)


def plot_status_counts(ax: Axes, counts: dict[str, int]) -> None:
    """Horizontal bars: how many frames ended with each status."""
    names = list(counts)
    ax.barh(names, [counts[k] for k in names], color="#4c72b0")
    ax.invert_yaxis()
    ax.set_xlabel("frames")
    for y, k in enumerate(names):
        ax.text(counts[k], y, f" {counts[k]}", va="center")
    ax.margins(x=0.12)


#: colours of the loss funnel's stages: losses red to orange, the accepted ones blue and green
FUNNEL_COLOURS = {
    "excluded": "#9e9e9e", "not_retrieved": "#b2182b", "below_alpha": "#d6604d", "wrong_island": "#f4a582",
    "temporal": "#fdae61", "geometry": "#e08214", "wrong_accepted": "#762a83", "below_threshold": "#4393c3",
    "found": "#1a9850", "unknown": "#bdbdbd",
}


def plot_funnel(ax: Axes, counts: dict[str, int]) -> None:
    """Horizontal bars in pipeline order: how many positive queries each stage lost (and found).

    Args:
        ax: the axes.
        counts: stage -> queries, in pipeline order (:attr:`stablecues.evaluation.funnel.Funnel.counts`).
    """
    names = list(counts)
    total = sum(counts.values())
    values = [counts[k] for k in names]
    ax.barh(names, values, color=[FUNNEL_COLOURS.get(k, "#4c72b0") for k in names])
    ax.invert_yaxis()
    ax.set_xlabel("positive queries")
    for y, k in enumerate(names):
        share = counts[k] / total if total else 0.0
        ax.text(counts[k], y, f" {counts[k]} ({share:.0%})", va="center")
    ax.margins(x=0.18)


def plot_timing(ax: Axes, table: dict[str, dict[str, Any]]) -> None:
    """Mean time per stage with a bar from min to max (ms)."""
    names = [k for k, v in table.items() if v.get("mean") is not None]
    means = np.array([table[k]["mean"] for k in names], dtype=np.float64)
    lo = means - np.array([table[k]["min"] for k in names], dtype=np.float64)
    hi = np.array([table[k]["max"] for k in names], dtype=np.float64) - means
    ax.barh(names, means, xerr=np.vstack([lo, hi]) if names else None, color="#dd8452", capsize=3)
    ax.invert_yaxis()
    ax.set_xlabel("ms per frame (mean, min to max)")
