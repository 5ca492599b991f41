"""Writing a synthetic sequence to the image-folder format, reading it back, and ``stablecues synth``."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.cli.main import main
from stablecues.datasets.synthetic import SyntheticTown, SyntheticTownConfig, write_sequence
from stablecues.errors import DatasetError

CFG = SyntheticTownConfig(frames=6, width=96, height=72, loops=1, seed=11, noise=0.0)


def _settings(path: Path) -> dict[str, str]:
    out = {}
    for line in path.read_text().splitlines()[1:]:
        if ":" in line and not line.startswith("#"):
            k, v = line.split(":", 1)
            out[k.strip()] = v.strip()
    return out


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_sequence(CFG, tmp_path_factory.mktemp("synth") / "seq", progress=False)


def test_written_folder_round_trips(written: Path) -> None:
    out = written
    town = SyntheticTown(CFG)
    names = sorted(p.name for p in (out / "images").iterdir())
    assert names == [f"{i:06d}.png" for i in range(CFG.frames)]
    for sub in ("right", "depth", "labels"):
        assert sorted(p.name for p in (out / sub).iterdir()) == names
    img = cv2.imread(str(out / "images" / names[2]), cv2.IMREAD_UNCHANGED)
    right = cv2.imread(str(out / "right" / names[2]), cv2.IMREAD_UNCHANGED)
    depth = cv2.imread(str(out / "depth" / names[2]), cv2.IMREAD_UNCHANGED)
    labels = cv2.imread(str(out / "labels" / names[2]), cv2.IMREAD_UNCHANGED)
    assert img.shape == right.shape == (72, 96, 3) and img.dtype == np.uint8
    assert depth.shape == (72, 96) and depth.dtype == np.uint16
    assert labels.shape == (72, 96) and labels.dtype == np.uint8 and labels.max() <= 11
    # the files hold what the generator renders
    f = town.frame(2)
    np.testing.assert_array_equal(img, f.image)
    np.testing.assert_array_equal(labels, f.labels)
    assert f.depth is not None
    factor = CFG.depth_map_factor
    np.testing.assert_allclose(depth / factor, f.depth, atol=0.5 / factor + 1e-6)
    # calibration
    s = _settings(out / "calib.yaml")
    assert (out / "calib.yaml").read_text().startswith("%YAML:1.0")
    assert float(s["Camera.fx"]) == pytest.approx(town.intrinsics.fx)
    assert float(s["Camera.bf"]) == pytest.approx(town.intrinsics.fx * CFG.baseline)
    assert float(s["DepthMapFactor"]) == factor
    assert int(s["Camera.width"]) == 96 and int(s["Camera.height"]) == 72
    # times and poses
    times = np.loadtxt(out / "times.txt")
    np.testing.assert_allclose(times, town.times, atol=1e-6)
    rows = np.loadtxt(out / "poses.txt")
    assert rows.shape == (CFG.frames, 8)
    np.testing.assert_allclose(rows[:, 1:4], town.poses[:, :3, 3], atol=1e-6)
    from scipy.spatial.transform import Rotation

    R = Rotation.from_quat(rows[:, 4:8]).as_matrix()
    np.testing.assert_allclose(R, town.poses[:, :3, :3], atol=1e-6)
    # loops
    gt = np.load(out / "loops.npy")
    assert gt.shape == (CFG.frames, CFG.frames) and gt.dtype == bool and not np.triu(gt).any()
    np.testing.assert_array_equal(gt, town.ground_truth())
    meta = json.loads((out / "synthetic.json").read_text())
    assert meta["frames"] == CFG.frames and meta["lap_of_frame"] == town.lap_of.tolist()


def test_folder_loader_reads_it(written: Path) -> None:
    from stablecues.datasets.folder import open_folder

    out = written
    ds = open_folder(out)
    assert len(ds) == CFG.frames
    assert ds.depth_factor == CFG.depth_map_factor
    assert ds.gt_path == out / "loops.npy"
    rec = ds.records[3]
    assert rec.right is not None and rec.depth is not None and rec.labels is not None
    assert rec.pose is not None
    np.testing.assert_allclose(rec.pose, SyntheticTown(CFG).poses[3], atol=1e-6)


def test_refuses_to_overwrite(tmp_path: Path) -> None:
    small = SyntheticTownConfig(frames=2, width=48, height=36, loops=0, clutter=0.0)
    write_sequence(small, tmp_path, progress=False, right=False, depth=False, labels=False)
    assert not (tmp_path / "right").exists()
    with pytest.raises(DatasetError, match="already holds"):
        write_sequence(small, tmp_path, progress=False)
    write_sequence(small, tmp_path, progress=False, overwrite=True)
    assert (tmp_path / "right").is_dir()


def test_cli_synth(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "town"
    rc = main(
        [
            "synth",
            "--out",
            str(out),
            "--frames",
            "4",
            "--width",
            "64",
            "--height",
            "48",
            "--loops",
            "1",
            "--seed",
            "3",
            "-q",
        ]
    )
    assert rc == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith("stablecues synth: 4 frames 64x48") and str(out) in line
    assert len(list((out / "images").iterdir())) == 4
    assert np.load(out / "loops.npy").shape == (4, 4)
    # a second run into the same folder is refused with one line, exit 1
    rc = main(["synth", "--out", str(out), "--frames", "4", "--width", "64", "--height", "48", "-q"])
    assert rc == 1
    assert "already holds" in capsys.readouterr().err
    # bad settings are one-line errors too
    assert main(["synth", "--out", str(tmp_path / "x"), "--frames", "0", "-q"]) == 1
