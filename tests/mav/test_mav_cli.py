"""The ``stablecues mav`` command on a synthetic log: info, plot, poses (with and without frames), gt.

It tests :mod:`stablecues.cli.mav`; it lives here, beside the mav tests whose helpers it uses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymavlink")
pytest.importorskip("pymap3d")

from flight_synth import make_log  # noqa: E402

from stablecues.cli.main import main  # noqa: E402
from stablecues.geometry.rotations import matrix_to_quat  # noqa: E402
from stablecues.trajectory import read_tum  # noqa: E402


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
    t, poses = read_tum(poses_txt)
    p, q = poses[:, :3, 3], matrix_to_quat(poses[:, :3, :3])
    assert len(t) == 50 and np.isfinite(p).all()
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    # the file holds qx qy qz qw (TUM order): a level body facing north (the compass says so) is
    # FRD -> ENU, 180 degrees about (1, 1, 0) / sqrt(2): qx = qy = sqrt(1/2), qz = qw = 0 (about)
    rows = np.loadtxt(poses_txt)
    np.testing.assert_allclose(rows[:, 4:8], q, atol=1e-6)
    np.testing.assert_allclose(np.abs(rows[:, 4:6]), np.sqrt(0.5), atol=0.01)
    assert np.abs(rows[:, 6:8]).max() < 0.1  # within ~10 degrees
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
    t, poses = read_tum(tmp_path / "fp.txt")
    p = poses[:, :3, 3]
    np.testing.assert_allclose(p[:, 1], [0.0, 3.0, 7.0, 11.0], atol=0.2)  # 2 m/s north from 1 s on
    assert sorted(x.name for x in (tmp_path / "ds" / "images").iterdir())[0] == "000000_f0.png"
    assert np.load(tmp_path / "ds" / "loops.npy").shape == (4, 4)

    assert main(["mav", "info", str(tmp_path / "t.csv")]) == 1  # a CSV without lat/lon: not a log
    assert "not a flight log" in capsys.readouterr().err
    assert main(["mav", "poses", str(log_path), "--out", str(tmp_path / "x.txt"), "--offset", "soon",
                 "--frames", str(frames), "--times", str(tmp_path / "t.csv")]) == 1  # fmt: skip
