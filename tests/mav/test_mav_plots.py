"""Flight figures: mode bands and colours, the synthetic BRAKE flight, the real 118 flight, loops."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from matplotlib.collections import LineCollection

from conftest import shared_path

pytest.importorskip("pymavlink")
pytest.importorskip("pymap3d")

from flight_synth import make_log  # noqa: E402
from matplotlib.colors import to_rgb  # noqa: E402

from stablecues.mav import FlightLog, read_log, run_ekf  # noqa: E402
from stablecues.mav.plots import (  # noqa: E402
    MODE_COLOURS,
    flight_figures,
    gapped,
    loop_figure,
    mode_bands_of,
    mode_colour,
    mode_label,
    yaw_window,
)


def test_mode_labels_and_colours() -> None:
    assert [mode_label(n) for n in ("STABILIZE", "ALT_HOLD", "LOITER", "RTL", "BRAKE", "DRIFT", "LAND")] == [
        "Stabilize", "AltHold", "Loiter", "RTL", "Brake", "Drift", "Land",
    ]  # fmt: skip
    assert mode_label("AUTO_RTL") == "AutoRTL" and mode_label("SMART_RTL") == "SmartRTL"
    assert len(set(MODE_COLOURS.values())) == len(MODE_COLOURS)  # every known mode is distinct
    assert mode_colour("AUTO_LOITER") == mode_colour("LOITER")  # PX4 names share the colour
    assert mode_colour("SOMETHING_NEW") == mode_colour("SOMETHING_NEW")  # stable for unknown names


def test_yaw_window_centres_the_headings() -> None:
    assert yaw_window(np.array([350.0, 5.0, 20.0])) == -180.0  # heading north: [-180, 180)
    assert yaw_window(np.array([170.0, 190.0])) == 0.0  # heading south: [0, 360)
    assert yaw_window(np.array([85.0, 95.0])) == -90.0
    assert yaw_window(np.array([])) == 0.0


def test_gapped_breaks_lines() -> None:
    t, v = gapped(np.array([0.0, 1.0, 10.0, 11.0]), np.array([1.0, 2.0, 3.0, 4.0]))
    assert np.isnan(v[2]) and np.isnan(t[2]) and len(v) == 5


def test_figures_of_a_synthetic_flight_with_brake(tmp_path: Path) -> None:
    path = tmp_path / "synth.bin"
    path.write_bytes(make_log())
    log = read_log(path)
    solution, _ = run_ekf(log)
    figs = flight_figures(log, solution=solution)
    ax = figs["altitude"].axes[0]
    assert [(n, round(a, 2), round(b, 2)) for n, a, b in mode_bands_of(ax)] == [
        ("LOITER", 0.0, 4.0), ("BRAKE", 4.0, 7.0), ("RTL", 7.0, 9.98),
    ]  # fmt: skip
    brake = next(p for p in ax.patches if p.get_gid() == "mode:BRAKE")
    np.testing.assert_allclose(brake.get_facecolor()[:3], to_rgb(MODE_COLOURS["BRAKE"]))
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["GNSS", "barometer", "stablecues-ekf", "Loiter", "Brake", "RTL"]
    # trajectory: one point per fix, coloured by time, with a colour bar
    traj = figs["trajectory"]
    scatter = traj.axes[0].collections[0]
    np.testing.assert_allclose(scatter.get_array(), log.gnss.t)
    assert len(traj.axes) == 2
    # attitude panels: roll, pitch, yaw (deg) of the autopilot and of the EKF
    att = figs["attitude"].axes
    assert [a.get_ylabel() for a in att] == ["roll [deg]", "pitch [deg]", "yaw [deg]"]
    assert len(att[0].get_lines()) == 2
    # position panels: latitude, longitude, altitude
    assert [a.get_ylabel() for a in figs["position"].axes] == [
        "latitude [deg]",
        "longitude [deg]",
        "altitude [m MSL]",
    ]


def test_loop_figure() -> None:
    gt = np.zeros((4, 4), bool)
    gt[3, 0] = True
    fig = loop_figure(np.array([[0, 0, 0], [5, 0, 0], [5, 5, 0], [0, 1, 0]], float), gt)
    ax_matrix, ax_traj = fig.axes[:2]
    assert "1 pairs" in ax_matrix.get_title()
    (pairs,) = [c for c in ax_traj.collections if isinstance(c, LineCollection)]  # one collection
    (segment,) = pairs.get_segments()
    np.testing.assert_allclose(segment, [[0.0, 1.0], [0.0, 0.0]])  # frame 3 -> frame 0


def test_loop_figure_of_a_long_trajectory_draws_a_sample() -> None:
    """10^4 poses on a circle, all close: 5 x 10^7 pairs; the picture pools the matrix and draws
    at most MAX_PLOTTED_LOOP_PAIRS of them, and says so."""
    from stablecues.limits import MAX_PLOTTED_LOOP_PAIRS
    from stablecues.mav.plots import loop_pairs_sample

    n = 10_000
    gt = np.tril(np.ones((n, n), bool), -200)
    rows, cols, total = loop_pairs_sample(gt)
    assert total == int(gt.sum()) and 0 < rows.size <= MAX_PLOTTED_LOOP_PAIRS
    assert np.all(gt[rows, cols]) and rows.min() < 300 and rows.max() > n - 100  # spread over all
    angle = np.linspace(0, 20 * np.pi, n)
    fig = loop_figure(np.c_[np.cos(angle), np.sin(angle), np.zeros(n)], gt)
    ax_matrix, ax_traj = fig.axes[:2]
    assert ax_matrix.get_images()[0].get_array().shape[0] <= 1024
    assert f"of {total} drawn" in ax_traj.get_title()


def _read(path: Path) -> FlightLog:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_log(path)


def test_118_altitude_figure_has_the_mode_bands(tmp_path: Path) -> None:
    log = _read(shared_path("mav", "erlerobot_ardupilot_copter_2014", "118.BIN"))
    figs = flight_figures(log)
    assert set(figs) == {"trajectory", "altitude", "position", "attitude"}
    ax = figs["altitude"].axes[0]
    bands = mode_bands_of(ax)
    spans = log.mode_spans()
    assert [b[0] for b in bands] == [s.name for s in spans] and len(bands) == 12
    for (_, x0, x1), s in zip(bands, spans, strict=True):
        assert x0 == pytest.approx(s.start) and x1 == pytest.approx(s.end)
    # each band has its mode's colour, and the legend names every mode once
    for patch in ax.patches:
        if (patch.get_gid() or "").startswith("mode:"):
            want = mode_colour(patch.get_gid()[5:])
            np.testing.assert_allclose(patch.get_facecolor()[:3], _rgb(want), atol=1e-6)
    legend = ax.get_legend()
    assert legend is not None
    labels = [t.get_text() for t in legend.get_texts()]
    assert {"AltHold", "Loiter", "RTL", "Stabilize"} <= set(labels)
    assert labels.count("Loiter") == 1
    # the GNSS altitude line is drawn, broken at the two logging pauses (NaN separators)
    gnss_line = next(line for line in ax.get_lines() if line.get_label() == "GNSS")
    assert np.isnan(np.asarray(gnss_line.get_ydata(), dtype=float)).sum() == 2
    # the position panels carry the bands too; the files render
    assert len(mode_bands_of(figs["position"].axes[2])) == 12
    for name, fig in figs.items():
        path = tmp_path / f"{name}.png"
        fig.savefig(path, dpi=60)
        assert path.stat().st_size > 5000


def _rgb(colour: str) -> tuple[float, float, float]:
    from matplotlib.colors import to_rgb

    return to_rgb(colour)
