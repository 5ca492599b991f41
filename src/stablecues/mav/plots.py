"""The paper's flight figures (Figs. 5-7) and a loop ground-truth figure.

Every ``plot_*`` function draws into the matplotlib ``Axes`` it is given and returns what a caller
may need (a colour mappable, the band patches); nothing calls ``pyplot``. :func:`flight_figures`
and :func:`loop_figure` build whole :class:`~matplotlib.figure.Figure` objects (Agg canvas,
headless); :func:`save_flight_figures` writes them as PNG files.

Flight-mode bands are ``axvspan`` patches whose ``gid`` is ``"mode:<NAME>"`` so that a figure can
be checked by reading its patches back.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.cm import ScalarMappable
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle

from ..limits import MAX_PLOTTED_LOOP_PAIRS
from .flightlog import FlightLog, ModeSpan, NavSolution

# Fixed colours for the usual modes (ArduPilot names; PX4 names map onto the closest one).
MODE_COLOURS: dict[str, str] = {
    "STABILIZE": "#1f77b4",
    "ALT_HOLD": "#ff7f0e",
    "LOITER": "#2ca02c",
    "RTL": "#d62728",
    "BRAKE": "#9467bd",
    "DRIFT": "#8c564b",
    "LAND": "#e377c2",
    "AUTO": "#7f7f7f",
    "GUIDED": "#bcbd22",
    "POSHOLD": "#17becf",
    "ACRO": "#aec7e8",
    "CIRCLE": "#ffbb78",
    "SMART_RTL": "#ff9896",
    "SPORT": "#98df8a",
    "MANUAL": "#c5b0d5",
    "AUTOTUNE": "#c49c94",
    "TAKEOFF": "#f7b6d2",
}
_PX4_EQUIVALENT = {
    "STAB": "STABILIZE",
    "ALTCTL": "ALT_HOLD",
    "POSCTL": "POSHOLD",
    "AUTO_LOITER": "LOITER",
    "AUTO_RTL": "RTL",
    "AUTO_LAND": "LAND",
    "AUTO_MISSION": "AUTO",
    "AUTO_TAKEOFF": "TAKEOFF",
    "OFFBOARD": "GUIDED",
}
_LABELS = {
    "ALT_HOLD": "AltHold",
    "POSHOLD": "PosHold",
    "SMART_RTL": "SmartRTL",
    "AUTOTUNE": "AutoTune",
    "GUIDED_NOGPS": "GuidedNoGPS",
    "ALTCTL": "AltCtl",
    "POSCTL": "PosCtl",
}
_ACRONYMS = {"RTL", "QRTL", "FBWA", "FBWB", "ADSB", "GPS", "VTOL", "CRUISE_"}
_FALLBACK = (
    "#393b79", "#637939", "#8c6d31", "#843c39", "#7b4173", "#5254a3", "#8ca252", "#bd9e39",
    "#ad494a", "#a55194", "#6b6ecf", "#b5cf6b", "#e7ba52", "#d6616b", "#ce6dbd",
)  # fmt: skip


def gapped(t: np.ndarray, values: np.ndarray, max_gap: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Insert NaN rows where samples are more than ``max_gap`` seconds apart, so that lines
    break at logging pauses instead of bridging them.

    Args:
        t: (N,) times; values: (N,) or (N, K) samples.
    """
    t = np.asarray(t, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    gaps = np.flatnonzero(np.diff(t) > max_gap)
    if len(gaps) == 0:
        return t, values
    return np.insert(t, gaps + 1, np.nan), np.insert(values, gaps + 1, np.nan, axis=0)


def mode_label(name: str) -> str:
    """Readable label of a mode name: "ALT_HOLD" -> "AltHold", "AUTO_RTL" -> "AutoRTL"."""
    if name in _LABELS:
        return _LABELS[name]
    return "".join(w if w in _ACRONYMS else w.capitalize() for w in name.split("_"))


def mode_colour(name: str) -> str:
    """Background colour of a flight mode (fixed for known modes, stable for others)."""
    key = _PX4_EQUIVALENT.get(name, name)
    if key in MODE_COLOURS:
        return MODE_COLOURS[key]
    return _FALLBACK[zlib.crc32(name.encode()) % len(_FALLBACK)]


def add_mode_bands(ax: Axes, spans: Sequence[ModeSpan], *, alpha: float = 0.22) -> list[Any]:
    """Shade each flight-mode span behind the data.

    Returns:
        The band patches, in span order; each has ``gid`` ``"mode:<NAME>"``.
    """
    patches = []
    for s in spans:
        patch = ax.axvspan(s.start, s.end, color=mode_colour(s.name), alpha=alpha, lw=0, zorder=0)
        patch.set_gid(f"mode:{s.name}")
        patches.append(patch)
    return patches


def mode_legend_handles(spans: Sequence[ModeSpan], *, alpha: float = 0.35) -> list[Patch]:
    """One legend patch per distinct mode, in order of first appearance."""
    seen: list[str] = []
    for s in spans:
        if s.name not in seen:
            seen.append(s.name)
    return [Patch(facecolor=mode_colour(n), alpha=alpha, label=mode_label(n)) for n in seen]


def mode_bands_of(ax: Axes) -> list[tuple[str, float, float]]:
    """Read the flight-mode bands back from an axes: (mode name, start, end) per band."""
    out = []
    for patch in ax.patches:
        gid = patch.get_gid()
        if gid and gid.startswith("mode:"):
            if isinstance(patch, Rectangle):
                x0, x1 = patch.get_x(), patch.get_x() + patch.get_width()
            else:  # matplotlib < 3.9 drew axvspan as a Polygon
                xy = np.asarray(patch.get_path().vertices)
                x0, x1 = float(xy[:, 0].min()), float(xy[:, 0].max())
            out.append((gid[5:], float(x0), float(x1)))
    return out


def _legend(ax: Axes, handles: list[Any]) -> None:
    if handles:
        ax.legend(
            handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False
        )


def plot_trajectory(
    ax: Axes, log: FlightLog, *, solution: NavSolution | None = None
) -> ScalarMappable | None:
    """Latitude / longitude track coloured by time (paper Fig. 5).

    Draws the GNSS fixes (3D or better) as points coloured by log time, and ``solution`` as a
    thin line when given.

    Returns:
        The scatter (for a colour bar), or None when the log has no fix.
    """
    g = log.gnss.subset(log.gnss.fix >= 3)
    sc = None
    if len(g):
        sc = ax.scatter(g.lon, g.lat, c=g.t, cmap="viridis", s=6, lw=0, zorder=2)
        ax.plot(g.lon[0], g.lat[0], marker="^", color="k", ms=7, ls="none", label="start", zorder=3)
        ax.plot(g.lon[-1], g.lat[-1], marker="s", color="k", ms=6, ls="none", label="end", zorder=3)
        ax.set_aspect(1.0 / max(np.cos(np.radians(float(np.mean(g.lat)))), 1e-3), adjustable="datalim")
    if solution is not None and len(solution):
        llh = solution.geodetic()
        _, lonlat = gapped(solution.t, llh[:, [1, 0]])
        ax.plot(lonlat[:, 0], lonlat[:, 1], color="tab:red", lw=0.8, alpha=0.8, label=solution.name, zorder=1)
    ax.set_xlabel("longitude [deg]")
    ax.set_ylabel("latitude [deg]")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(axis="x", labelrotation=30)
    ax.set_title("trajectory")
    if len(g) or solution is not None:
        ax.legend(loc="best", fontsize="small")
    return sc


def _baro_on_gnss(log: FlightLog) -> np.ndarray | None:
    """Barometric altitude shifted onto the GNSS altitude (median difference), or None."""
    b, g = log.baro, log.gnss.subset(log.gnss.fix >= 3)
    if len(b) == 0:
        return None
    if len(g) == 0:
        return b.alt
    inside = (g.t >= b.t[0]) & (g.t <= b.t[-1])
    if not np.any(inside):
        return b.alt
    shift = float(np.median(g.alt[inside] - np.interp(g.t[inside], b.t, b.alt)))
    return b.alt + shift


def plot_altitude(
    ax: Axes, log: FlightLog, *, solution: NavSolution | None = None, modes: bool = True
) -> list[Any]:
    """Altitude over time with the flight-mode background (paper Fig. 6).

    GNSS altitude (MSL), barometric altitude shifted onto it, and ``solution``'s altitude.

    Returns:
        The mode band patches.
    """
    handles: list[Any] = []
    g = log.gnss.subset(log.gnss.fix >= 3)
    if len(g):
        handles += ax.plot(*gapped(g.t, g.alt), color="k", lw=1.0, label="GNSS")
    baro = _baro_on_gnss(log)
    if baro is not None:
        handles += ax.plot(*gapped(log.baro.t, baro), color="tab:blue", lw=0.8, ls="--", label="barometer")
    if solution is not None and len(solution):
        up = solution.position[:, 2] + solution.origin[2]
        handles += ax.plot(*gapped(solution.t, up), color="tab:red", lw=0.9, label=solution.name)
    spans = log.mode_spans() if modes else ()
    patches = add_mode_bands(ax, spans)
    ax.set_xlim(0.0, max(log.duration, 1e-3))
    ax.set_xlabel("time [s]")
    ax.set_ylabel("altitude [m MSL]" if len(g) else "barometric altitude [m]")
    ax.set_title("altitude and flight mode")
    _legend(ax, handles + mode_legend_handles(spans))
    return patches


def plot_position_panels(
    axes: Sequence[Axes], log: FlightLog, *, solution: NavSolution | None = None, modes: bool = True
) -> None:
    """Latitude, longitude and altitude over time, one panel each (three axes)."""
    if len(axes) != 3:
        raise ValueError(f"plot_position_panels needs 3 axes, got {len(axes)}")
    g = log.gnss.subset(log.gnss.fix >= 3)
    llh = solution.geodetic() if solution is not None and len(solution) else None
    spans = log.mode_spans() if modes else ()
    for k, (ax, label) in enumerate(
        zip(axes, ("latitude [deg]", "longitude [deg]", "altitude [m MSL]"), strict=True)
    ):
        handles: list[Any] = []
        if len(g):
            values = (g.lat, g.lon, g.alt)[k]
            handles += ax.plot(*gapped(g.t, values), color="k", lw=1.0, label="GNSS")
        if llh is not None and solution is not None:
            handles += ax.plot(*gapped(solution.t, llh[:, k]), color="tab:red", lw=0.8, label=solution.name)
        add_mode_bands(ax, spans)
        ax.set_ylabel(label)
        ax.ticklabel_format(axis="y", useOffset=False, style="plain")
        ax.set_xlim(0.0, max(log.duration, 1e-3))
        if k == 0:
            _legend(ax, handles + mode_legend_handles(spans))
    axes[-1].set_xlabel("time [s]")


def yaw_window(yaw_deg: np.ndarray) -> float:
    """Lower edge of the 360-degree window in which to show headings: centred on their circular
    mean and rounded to 90 degrees, so a flight heading north is not split between 0 and 360."""
    y = np.radians(np.asarray(yaw_deg, dtype=np.float64))
    y = y[np.isfinite(y)]
    if len(y) == 0:
        return 0.0
    mean = float(np.degrees(np.arctan2(np.mean(np.sin(y)), np.mean(np.cos(y)))))
    low = 90.0 * np.round((mean - 180.0) / 90.0)
    return float((low + 180.0) % 360.0 - 180.0)  # in [-180, 180)


def _break_wraps(t: np.ndarray, deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Insert NaN where a wrapped angle jumps by a full turn, so lines do not cross the plot."""
    jumps = np.flatnonzero(np.abs(np.diff(deg)) > 180.0)
    if len(jumps) == 0:
        return t, deg
    return np.insert(t, jumps + 1, np.nan), np.insert(deg, jumps + 1, np.nan)


def plot_attitude(
    axes: Sequence[Axes], log: FlightLog, *, solution: NavSolution | None = None, modes: bool = False
) -> None:
    """Roll, pitch and yaw over time, one panel each (paper Fig. 7), in degrees.

    Draws the autopilot's attitude and, when given, ``solution``'s. Yaw is shown in a 360-degree
    window centred on the flight's mean heading (:func:`yaw_window`), e.g. [-180, 180) for a
    flight heading north, [0, 360) for one heading south.
    """
    if len(axes) != 3:
        raise ValueError(f"plot_attitude needs 3 axes, got {len(axes)}")
    series: list[tuple[str, np.ndarray, np.ndarray, dict[str, Any]]] = []
    if len(log.attitude):
        series.append(("autopilot", log.attitude.t, np.degrees(log.attitude.rpy), {"color": "k", "lw": 0.9}))
    if solution is not None and solution.has_attitude:
        series.append((solution.name, solution.t, np.degrees(solution.rpy), {"color": "tab:red", "lw": 0.8}))
    spans = log.mode_spans() if modes else ()
    low = yaw_window(series[0][2][:, 2]) if series else 0.0
    for k, (ax, label) in enumerate(zip(axes, ("roll [deg]", "pitch [deg]", "yaw [deg]"), strict=True)):
        handles: list[Any] = []
        for name, t, rpy, style in series:
            tt, values = gapped(t, rpy[:, k])
            if k == 2:
                tt, values = _break_wraps(tt, low + np.mod(values - low, 360.0))
            handles += ax.plot(tt, values, label=name, **style)
        add_mode_bands(ax, spans)
        ax.set_ylabel(label)
        ax.set_xlim(0.0, max(log.duration, 1e-3))
        if k == 2:
            ax.set_ylim(low, low + 360.0)
            ax.set_yticks(low + np.arange(0.0, 361.0, 90.0))
        if k == 0:
            _legend(ax, handles + mode_legend_handles(spans))
    axes[-1].set_xlabel("time [s]")


def flight_figures(log: FlightLog, *, solution: NavSolution | None = None) -> dict[str, Figure]:
    """The four flight figures: "trajectory", "altitude", "position", "attitude"."""
    figs: dict[str, Figure] = {}
    fig = Figure(figsize=(6.4, 5.6), layout="constrained")
    ax = fig.add_subplot()
    sc = plot_trajectory(ax, log, solution=solution)
    if sc is not None:
        fig.colorbar(sc, ax=ax, label="time [s]")
    figs["trajectory"] = fig

    fig = Figure(figsize=(9.0, 3.8), layout="constrained")
    plot_altitude(fig.add_subplot(), log, solution=solution)
    figs["altitude"] = fig

    fig = Figure(figsize=(9.0, 7.0), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    plot_position_panels(list(axes), log, solution=solution)
    figs["position"] = fig

    fig = Figure(figsize=(9.0, 7.0), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    plot_attitude(list(axes), log, solution=solution)
    figs["attitude"] = fig
    return figs


def save_flight_figures(
    log: FlightLog, out_dir: str | Path, *, solution: NavSolution | None = None, dpi: int = 150
) -> dict[str, Path]:
    """Write the flight figures as ``<out_dir>/<name>.png``; returns name -> path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, fig in flight_figures(log, solution=solution).items():
        path = out / f"{name}.png"
        fig.savefig(path, dpi=dpi)
        paths[name] = path
    return paths


_MATRIX_PIXELS = 1024  # a loop matrix is drawn pooled to at most this many cells a side


def plot_loop_matrix(ax: Axes, gt: np.ndarray) -> None:
    """The loop ground-truth matrix: query frame i (rows) against earlier frame j (columns).

    A matrix of more than 1024 frames a side is drawn pooled (a cell is dark when any pair in
    it is a loop), so the picture costs the same memory whatever the trajectory's length.
    """
    n = gt.shape[0]
    ax.imshow(
        _pooled(gt, _MATRIX_PIXELS),
        cmap="Greys",
        interpolation="nearest",
        vmin=0,
        vmax=1,
        extent=(-0.5, n - 0.5, n - 0.5, -0.5),
    )
    ax.set_xlabel("earlier frame j")
    ax.set_ylabel("query frame i")
    ax.set_title(f"loop ground truth: {int(gt.sum())} pairs, {int(gt.any(axis=1).sum())} query frames")


def _pooled(gt: np.ndarray, cells: int) -> np.ndarray:
    """(m, m) bool ``any`` over square blocks of ``gt``, m <= ``cells``; ``gt`` itself if small."""
    n = gt.shape[0]
    if n <= cells:
        return gt
    f = -(-n // cells)
    starts = np.arange(0, n, f)
    out = np.zeros((starts.size, starts.size), dtype=bool)
    for k, a in enumerate(starts):
        out[k] = np.logical_or.reduceat(gt[a : a + f].any(axis=0), starts)
    return out


def loop_pairs_sample(
    gt: np.ndarray, limit: int = MAX_PLOTTED_LOOP_PAIRS
) -> tuple[np.ndarray, np.ndarray, int]:
    """At most ``limit`` loop pairs of ``gt``, evenly spread over all of them in row order.

    Works a block of rows at a time, so all pairs are never held at once.

    Returns:
        ((K,) int64 rows i, (K,) int64 columns j, the number of pairs in ``gt``).
    """
    n = gt.shape[0]
    total = int(np.count_nonzero(gt))
    step = max(1, -(-total // max(limit, 1)))
    block = max(1, (1 << 22) // max(n, 1))
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    seen = 0
    for start in range(0, n, block):
        r, c = np.nonzero(gt[start : start + block])
        keep = (np.arange(seen, seen + r.size) % step) == 0
        rows.append(r[keep] + start)
        cols.append(c[keep])
        seen += r.size
    if not rows:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), total
    return np.concatenate(rows).astype(np.int64), np.concatenate(cols).astype(np.int64), total


def plot_loops_on_trajectory(
    ax: Axes, positions: np.ndarray, gt: np.ndarray, *, names: Sequence[str] | None = None
) -> None:
    """Camera positions (east/north) with a line for every loop pair (one line collection; at
    most :data:`stablecues.limits.MAX_PLOTTED_LOOP_PAIRS` pairs, evenly spread, are drawn and the
    title says so)."""
    p = np.asarray(positions, dtype=np.float64)
    ax.plot(p[:, 0], p[:, 1], color="0.6", lw=0.8, zorder=1)
    ax.scatter(p[:, 0], p[:, 1], c=np.arange(len(p)), cmap="viridis", s=12, zorder=2)
    rows, cols, total = loop_pairs_sample(gt)
    if rows.size:
        segments = np.stack([p[rows, :2], p[cols, :2]], axis=1)
        ax.add_collection(LineCollection(list(segments), colors="tab:red", linewidths=1.2, zorder=3))
    if names is not None and len(names) == len(p) and len(p) <= 60:
        for k, name in enumerate(names):
            ax.annotate(name, (p[k, 0], p[k, 1]), fontsize=6, xytext=(2, 2), textcoords="offset points")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    drawn = f" ({rows.size} of {total} drawn)" if rows.size < total else ""
    ax.set_title(f"poses and loop pairs{drawn}")
    ax.legend(handles=[Line2D([], [], color="tab:red", label="loop pair")], loc="best", fontsize="small")


def loop_figure(positions: np.ndarray, gt: np.ndarray, *, names: Sequence[str] | None = None) -> Figure:
    """Loop matrix and trajectory side by side."""
    fig = Figure(figsize=(11.0, 5.0), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    plot_loop_matrix(ax1, gt)
    plot_loops_on_trajectory(ax2, positions, gt, names=names)
    return fig


__all__ = [
    "MODE_COLOURS",
    "add_mode_bands",
    "flight_figures",
    "loop_figure",
    "mode_bands_of",
    "mode_colour",
    "mode_label",
    "mode_legend_handles",
    "plot_altitude",
    "plot_attitude",
    "plot_loop_matrix",
    "loop_pairs_sample",
    "plot_loops_on_trajectory",
    "plot_position_panels",
    "plot_trajectory",
    "save_flight_figures",
    "yaw_window",
]
