"""``scripts/make_revisit_set.py``, the builder of the held-out revisit set: on CamVid ``val`` with
a 7-pixel still threshold it rebuilds the layout and most of the ground truth of the shipped
``val_drive`` development set."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import shared_path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "make_revisit_set.py"


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, check=False)


def test_missing_camvid_is_one_line(tmp_path: Path) -> None:
    done = _run("--split", "test", "--out", str(tmp_path / "out"), "--camvid", str(tmp_path / "absent"))
    assert done.returncode == 1
    assert "Traceback" not in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert str(tmp_path / "absent") in done.stderr
    assert not (tmp_path / "out").exists()


def test_val_rebuilds_the_val_drive_layout(tmp_path: Path) -> None:
    camvid, dev = shared_path("camvid"), shared_path("camvid_revisit_dev", "val_drive")
    if not (camvid / "val").is_dir() or not (dev / "gt.png").is_file():
        pytest.skip("../shared/data/camvid and camvid_revisit_dev are not here")
    out = tmp_path / "val"
    done = _run("--split", "val", "--out", str(out), "--still-px", "7", "--camvid", str(camvid))
    assert done.returncode == 0, done.stderr
    ours = cv2.imread(str(out / "gt.png"), cv2.IMREAD_GRAYSCALE) > 0
    theirs = cv2.imread(str(dev / "gt.png"), cv2.IMREAD_GRAYSCALE) > 0
    assert ours.shape == theirs.shape == (49, 49)
    # the same rows hold loops (the second traversal), and loops point back to earlier frames
    np.testing.assert_array_equal(ours.any(axis=1), theirs.any(axis=1))
    assert not np.triu(ours).any()
    # about as many loop cells, most of them in the same places (the 7-pixel rule keeps 16 of the
    # shipped set's 49 source frames exactly, the others a frame or two beside them)
    assert abs(int(ours.sum()) - int(theirs.sum())) <= 0.25 * theirs.sum()
    assert np.count_nonzero(ours & theirs) >= 0.75 * theirs.sum()
    with open(out / "sources.csv", newline="") as fh:
        ours_src = [r["source"] for r in csv.DictReader(fh)]
    with open(dev / "sources.csv", newline="") as fh:
        theirs_src = [r["source"] for r in csv.DictReader(fh)]
    assert [s[:6] for s in ours_src] == [s[:6] for s in theirs_src]  # the same drives in the same order
    assert len(list((out / "frames").glob("*.jpg"))) == len(list((out / "labels").glob("*.png"))) == 49
