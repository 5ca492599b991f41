"""``stablecues synth``: writes a sequence, refuses to overwrite, one-line errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stablecues.cli.main import main


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


def test_a_stereo_only_town_is_read_as_stereo(tmp_path: Path) -> None:
    """`synth --no-depth` wrote DepthMapFactor into calib.yaml, which makes the settings an RGB-D
    camera's: the folder's right images were never used for 3D and loops had no pose. Without
    depth images the file has no DepthMapFactor and the frames are lifted from the stereo pair."""
    from stablecues.datasets import open_dataset
    from stablecues.detection import LoopDetector, preset

    out = tmp_path / "town"
    assert main(["synth", "--out", str(out), "--frames", "3", "--width", "96", "--height", "72",
                 "--no-depth", "-q"]) == 0
    assert "DepthMapFactor" not in (out / "calib.yaml").read_text()
    ds = open_dataset(out)
    assert ds.records[0].right is not None and ds.records[0].depth is None
    calib = ds.calibration
    assert calib is not None and calib.baseline is not None and calib.baseline > 0
    with LoopDetector(preset("fast"), calibration=calib) as det:
        assert det.process(ds[0]).points_source == "stereo"
