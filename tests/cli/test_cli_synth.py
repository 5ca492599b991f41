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
