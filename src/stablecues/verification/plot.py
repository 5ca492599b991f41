"""Match pictures: two frames side by side, matches coloured by confidence, and the triangles.

As the paper's Fig. 8: strong matches green, weak ones blue, with a colour bar.
"""

from __future__ import annotations

import numpy as np
from matplotlib.axes import Axes
from matplotlib.cm import ScalarMappable
from matplotlib.collections import LineCollection
from matplotlib.colors import LinearSegmentedColormap, Normalize
from matplotlib.lines import Line2D
from matplotlib.patches import Polygon

from ..errors import InputError
from .result import Verification

__all__ = ["CONFIDENCE_CMAP", "draw_verification", "plot_verification", "side_by_side"]

#: weak (blue) to strong (green), as in the paper's match figures
CONFIDENCE_CMAP = LinearSegmentedColormap.from_list("weak_strong", ["#1a2cff", "#00a0e0", "#00d000"])


def _rgb(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8:
        lo, hi = float(np.nanmin(img)), float(np.nanmax(img))
        img = np.clip((img.astype(np.float64) - lo) / max(hi - lo, 1e-9) * 255.0, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 1:
        return np.repeat(img, 3, axis=2)
    return img[:, :, 2::-1]  # BGR(A) -> RGB


def side_by_side(left: np.ndarray, right: np.ndarray, gap: int = 8) -> tuple[np.ndarray, int]:
    """(H, W1 + gap + W2, 3) uint8 RGB canvas of two images, and the x offset of the second."""
    a, b = _rgb(left), _rgb(right)
    h = max(a.shape[0], b.shape[0])
    canvas = np.full((h, a.shape[1] + gap + b.shape[1], 3), 255, np.uint8)
    canvas[: a.shape[0], : a.shape[1]] = a
    offset = a.shape[1] + gap
    canvas[: b.shape[0], offset:] = b
    return canvas, offset


def plot_verification(
    ax: Axes,
    image_query: np.ndarray,
    image_candidate: np.ndarray,
    result: Verification,
    *,
    max_matches: int = 150,
    colorbar: bool = True,
    title: str | None = None,
) -> None:
    """Draw a verification: query left, candidate right, matches and triangles.

    Matches are coloured by confidence (``Matches.confidence``: 1 - Hamming / 128); matches
    that support the decision (``result.inliers``) are drawn solid, the others thin and faint.
    Agreeing triangles are outlined in yellow, disagreeing ones in red (dashed).

    Args:
        ax: the axes to draw in (nothing is shown or saved here).
        image_query: the query image the keypoints refer to (grey or BGR).
        image_candidate: the candidate image.
        result: the verification of the pair (as a Verifier returns it: with the matches' pixels).
        max_matches: draw at most this many matches (the best ranked).
        colorbar: add a confidence colour bar to the axes' figure.
        title: title; default states the decision.
    """
    if result.pixels_query is None or result.pixels_candidate is None:
        raise InputError("plot_verification: the result carries no match pixels (make it with a Verifier)")
    canvas, offset = side_by_side(image_query, image_candidate)
    ax.imshow(canvas)
    ax.set_axis_off()
    m = result.matches
    k = min(len(m), max_matches)
    conf_all = m.confidence[:k]
    # colour range: the drawn matches' confidences (a Hamming ceiling of 64 puts them in [0.5, 1])
    lo = float(np.floor(conf_all.min() * 20) / 20) if k else 0.0
    hi = float(np.ceil(conf_all.max() * 20) / 20) if k else 1.0
    norm = Normalize(lo, max(hi, lo + 0.05))
    if k:
        pq = result.pixels_query[:k].astype(np.float64)
        pc = result.pixels_candidate[:k].astype(np.float64)
        pc[:, 0] += offset
        conf = m.confidence[:k]
        colours = CONFIDENCE_CMAP(norm(conf))
        inl = result.inliers[:k]
        segs = np.stack((pq, pc), axis=1)
        if (~inl).any():
            faint = colours[~inl].copy()
            faint[:, 3] = 0.35
            ax.add_collection(LineCollection(list(segs[~inl]), colors=faint, linewidths=0.5, zorder=2))
        if inl.any():
            ax.add_collection(LineCollection(list(segs[inl]), colors=colours[inl], linewidths=0.9, zorder=3))
        ax.scatter(pq[:, 0], pq[:, 1], s=5, c=colours, linewidths=0, zorder=4)
        ax.scatter(pc[:, 0], pc[:, 1], s=5, c=colours, linewidths=0, zorder=4)
    for tri in result.triangles:
        idx = np.asarray(tri.matches)
        colour = "#ffd600" if tri.agree else "#ff1744"
        style = "-" if tri.agree else "--"
        for pixels, dx in ((result.pixels_query, 0.0), (result.pixels_candidate, float(offset))):
            pts = pixels[idx].astype(np.float64) + [dx, 0.0]
            ax.add_patch(
                Polygon(
                    pts, closed=True, fill=False, edgecolor=colour, linestyle=style, linewidth=2.2, zorder=5
                )
            )
    if result.triangles:
        ax.legend(
            handles=[
                Line2D([], [], color="#ffd600", lw=1.6, label="triangle agrees"),
                Line2D([], [], color="#ff1744", lw=1.6, ls="--", label="triangle disagrees"),
            ],
            loc="lower right",
            fontsize=7,
            framealpha=0.7,
        )
    if title is None:
        decision = "ACCEPTED" if result.accepted else f"REJECTED ({result.status.value})"
        plural = "match" if len(m) == 1 else "matches"
        title = f"{decision} by {result.method.value}: {len(m)} {plural}, {result.n_inliers} inliers"
        if result.triangles:
            title += f", {result.n_triangles_agree}/{len(result.triangles)} triangles agree"
    ax.set_title(title, fontsize=9)
    if colorbar and ax.figure is not None:
        sm = ScalarMappable(norm=norm, cmap=CONFIDENCE_CMAP)
        sm.set_array(np.array([]))
        cb = ax.figure.colorbar(sm, ax=ax, fraction=0.025, pad=0.01)
        cb.set_label("match confidence (1 - Hamming/128): blue weak, green strong", fontsize=7)
        cb.ax.tick_params(labelsize=7)


def draw_verification(
    image_query: np.ndarray, image_candidate: np.ndarray, result: Verification, *, dpi: int = 100
) -> np.ndarray:
    """Render :func:`plot_verification` off-screen to an image.

    Args:
        image_query: the query image the keypoints refer to (grey or BGR).
        image_candidate: the candidate image.
        result: the verification of the pair.
        dpi: resolution of the rendering.

    Returns:
        (H, W, 3) uint8 BGR picture (ready for ``cv2.imwrite``).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    h = max(image_query.shape[0], image_candidate.shape[0])
    w = image_query.shape[1] + image_candidate.shape[1]
    fig = Figure(figsize=(w / dpi + 1.5, h / dpi + 0.6), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.01, 0.02, 0.88, 0.9))
    plot_verification(ax, image_query, image_candidate, result)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    return np.ascontiguousarray(rgba[:, :, 2::-1])
