"""Flight plots from a synthetic log (BRAKE / DRIFT modes), loop figure, and the mav CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymavlink")
pytest.importorskip("pymap3d")

from matplotlib.colors import to_rgb  # noqa: E402
from test_mav_dataflash_synth import make_log  # noqa: E402

from stablecues.cli.main import main  # noqa: E402
from stablecues.mav import ModeChange, geo, mode_spans, read_log, run_ekf, sync  # noqa: E402  # noqa: E402
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


def test_mode_spans_merge_repeats() -> None:
    changes = [
        ModeChange(0.0, "A", 1),
        ModeChange(0.0, "A", 1),
        ModeChange(5.0, "B", 2),
        ModeChange(7.0, "A", 1),
    ]
    spans = mode_spans(changes, 10.0)
    assert [(s.name, s.start, s.end) for s in spans] == [("A", 0.0, 5.0), ("B", 5.0, 7.0), ("A", 7.0, 10.0)]
    assert mode_spans([], 10.0) == ()


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
    red = [line for line in ax_traj.get_lines() if line.get_color() == "tab:red"]
    assert len(red) == 1 and list(red[0].get_xdata()) == [0.0, 0.0]


def test_cli_plot_poses_gt(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log_path = tmp_path / "synth.bin"
    log_path.write_bytes(make_log())
    assert main(["mav", "info", str(log_path), "--ekf"]) == 0
    out = capsys.readouterr().out
    assert "LOITER 0.0-4.0 s, BRAKE 4.0-7.0 s, RTL 7.0-10.0 s" in out and "EKF vs XKF1[0]" in out

    assert main(["mav", "plot", str(log_path), "--out", str(tmp_path / "plots"), "--dpi", "50"]) == 0
    for name in ("trajectory", "altitude", "position", "attitude"):
        assert (tmp_path / "plots" / f"{name}.png").stat().st_size > 2000

    # poses at 5 Hz without frames, then loop ground truth from them
    poses_txt = tmp_path / "poses.txt"
    assert main(["mav", "poses", str(log_path), "--out", str(poses_txt), "--rate", "5"]) == 0
    t, p, q = sync.read_tum(poses_txt)
    assert len(t) == 50 and np.isfinite(p).all()
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    assert main(["mav", "gt", str(poses_txt), "--out", str(tmp_path / "gt.png"), "--max-distance", "10",
                 "--min-gap-s", "3"]) == 0  # fmt: skip
    gt = np.load(tmp_path / "gt.npy")
    assert gt.shape == (50, 50) and gt.dtype == bool and not np.triu(gt).any()
    # north at 2 m/s from 1 s on: frame 20 (4 s) is 6 m from frame 0, frame 45 (9 s) 16 m
    assert gt[20, 0] and not gt[45, 0] and not gt[10, 0]  # frame 10 is only 2 s later
    assert (tmp_path / "gt.png").stat().st_size > 2000

    # frames with a times CSV, image-folder dataset
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(4):
        (frames / f"f{k}.png").write_bytes(b"png")
    utc0 = 315964800 + 2269 * 604800 + 300_000 - 18
    (tmp_path / "t.csv").write_text(
        "image,utc\n" + "".join(f"f{k}.png,{utc0 + 2.0 * k + 0.5}\n" for k in range(4))
    )
    framed = ["mav", "poses", str(log_path), "--frames", str(frames), "--times", str(tmp_path / "t.csv")]
    assert (
        main(
            [
                *framed,
                "--out",
                str(tmp_path / "fp.txt"),
                "--source",
                "onboard",
                "--dataset",
                str(tmp_path / "ds"),
            ]
        )
        == 0
    )
    t, p, _ = sync.read_tum(tmp_path / "fp.txt")
    np.testing.assert_allclose(p[:, 1], [0.0, 3.0, 7.0, 11.0], atol=0.2)  # 2 m/s north from 1 s on
    assert sorted(x.name for x in (tmp_path / "ds" / "images").iterdir())[0] == "000000_f0.png"
    assert np.load(tmp_path / "ds" / "loops.npy").shape == (4, 4)

    assert main(["mav", "info", str(tmp_path / "t.csv")]) == 1  # a CSV without lat/lon: not a log
    assert "not a flight log" in capsys.readouterr().err
    assert main(["mav", "poses", str(log_path), "--out", str(tmp_path / "x.txt"), "--offset", "soon",
                 "--frames", str(frames), "--times", str(tmp_path / "t.csv")]) == 1  # fmt: skip


def test_geo_round_trips() -> None:
    rng = np.random.default_rng(5)
    rpy = rng.uniform([-1, -1.2, -3], [1, 1.2, 3], size=(20, 3))
    q = geo.euler_to_quat(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    np.testing.assert_allclose(geo.quat_to_euler(q), rpy, atol=1e-9)
    q_enu = geo.ned_to_enu_quat(q)
    np.testing.assert_allclose(geo.quat_to_matrix(q_enu), geo.R_ENU_NED @ geo.quat_to_matrix(q), atol=1e-12)
    np.testing.assert_allclose(geo.quat_to_euler(geo.enu_to_ned_quat(q_enu)), rpy, atol=1e-9)
    enu = rng.normal(0, 100, (10, 3))
    llh = geo.enu_to_geodetic(enu, (52.8, -4.1, 20.0))
    np.testing.assert_allclose(
        geo.geodetic_to_enu(llh[:, 0], llh[:, 1], llh[:, 2], (52.8, -4.1, 20.0)), enu, atol=1e-6
    )
    # slerp half-way between identity and 90 deg about z is 45 deg about z
    qz = geo.quat_from_rotvec(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, np.pi / 2]]))
    mid = geo.quat_slerp(np.array([0.0, 1.0]), qz, np.array([0.5]))
    np.testing.assert_allclose(mid[0], geo.quat_from_rotvec(np.array([0.0, 0.0, np.pi / 4])), atol=1e-12)
