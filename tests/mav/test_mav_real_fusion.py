"""Real data: EKF against the onboard EKF3, camera poses and loop ground truth, flight plots."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path

pytest.importorskip("pymavlink")
pytest.importorskip("pymap3d")

from stablecues.mav import (  # noqa: E402
    compare_solutions,
    read_log,
    run_ekf,
    sync,  # noqa: E402
)
from stablecues.mav.plots import flight_figures, mode_bands_of, mode_colour  # noqa: E402


def _read(path: Path):  # type: ignore[no-untyped-def]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_log(path)


@pytest.mark.parametrize("name", ["2023-07-06_10-12-18.bin", "2023-07-06_10-18-44.bin"])
def test_ekf_matches_onboard_ekf3_on_uob_flights(name: str) -> None:
    log = _read(shared_path("mav", "uob_ardupilot_copter_2023", name))
    solution, report = run_ekf(log)  # one configuration, the defaults, for both flights
    assert log.onboard is not None
    cmp = compare_solutions(solution, log.onboard)
    # acceptance: within 0.5 m horizontal and 0.3 m vertical RMS after removing a constant offset
    assert cmp.h_rmse_m < 0.5
    assert cmp.v_rmse_m < 0.3
    assert cmp.n > 900  # the whole flight is compared (XKF1 at 10 Hz)
    assert np.linalg.norm(cmp.offset_enu) < 0.5  # same origin conventions: no big hidden offset
    assert cmp.roll_rmse_deg < 5 and cmp.pitch_rmse_deg < 5
    assert np.isfinite(solution.position).all() and np.isfinite(solution.quaternion).all()
    assert report.gnss_lag_s == pytest.approx(0.12)  # GPS_DELAY_MS = 0 in these logs: driver default
    assert report.declination_deg == pytest.approx(np.degrees(log.params["COMPASS_DEC"]))
    assert sum(report.rejected.values()) == 0 and report.resets == 0


def test_zr10_poses_and_revisit_ground_truth(tmp_path: Path) -> None:
    folder = shared_path("mav", "zr10_aerial_camera_gnss")
    log = _read(folder / "gps.csv")
    assert log.kind == "gnss_csv" and len(log.gnss) == 5155
    assert log.duration == pytest.approx(652, abs=1)
    frames = sync.read_frames(folder / "images", folder / "image_metadata.csv")
    assert len(frames) == 17 and frames.is_utc
    solution = sync.log_solution(log)  # no IMU: the GNSS track
    assert solution.name == "gnss"
    poses = sync.poses_for_frames(frames, log, solution)
    assert poses.valid.all() and not poses.has_attitude
    # the frames' own geotags were assigned from this track: the interpolated poses agree
    tags = sync.geo.geodetic_to_enu(
        frames.geotags[:, 0], frames.geotags[:, 1], frames.geotags[:, 2], poses.origin
    )
    assert np.abs(tags - poses.positions).max() < 0.1
    # 70 m above ground: the frames fly about 60-70 m above the first fix
    assert 50 < np.median(poses.positions[:, 2]) < 80
    # the clock offset estimated from the geotags is ~0
    est = sync.poses_for_frames(frames, log, solution, offset="estimate")
    assert abs(est.offset) < 0.05

    gt = sync.loops_from_trajectory(
        poses.positions, max_distance=8.0, times=poses.frame_times, min_gap_s=20.0
    )
    assert gt.shape == (17, 17) and not np.triu(gt).any()
    ids = [int(n[4:8]) for n in poses.names]
    pairs = {(ids[i], ids[j]) for i, j in zip(*np.nonzero(gt), strict=True)}
    for query, earlier in ((67, 15), (33, 18), (196, 104), (191, 127)):
        assert (query, earlier) in pairs
    # consecutive frames of the first lane are 3 s apart: never loops with a 20 s gap
    assert not any(q <= 18 for q, _ in pairs)

    out = sync.write_image_folder(tmp_path / "ds", frames, poses, loops=gt)
    assert len(list((out / "images").iterdir())) == 17
    assert np.array_equal(np.load(out / "loops.npy"), gt)
    t, p, _ = sync.read_tum(out / "poses.txt")
    np.testing.assert_allclose(p, poses.positions, atol=1e-3)
    np.testing.assert_allclose(np.loadtxt(out / "times.txt"), t, atol=1e-6)


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
