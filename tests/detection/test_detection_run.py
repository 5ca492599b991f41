"""stablecues run: a run killed at any instant resumes to what an uninterrupted run writes.

Each kill runs ``stablecues run`` in a child process that SIGKILLs itself at one point of one
frame's write sequence (similarity row, journal, the map's commit, the CSV row); ``--resume``
then finishes the run in this process. Decisions (all but the timing columns), extras and the
similarity matrix must equal an uninterrupted run's, and meta.json must say complete.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import write_wall_drive
from stablecues.cli.main import main
from stablecues.runs import load_run

FRAMES = 16
KILL_AT = 11  # a frame of the revisit, after loops were accepted
OPTIONS = [
    "--preset", "bow", "--no-progress", "--pictures", "0",
    "--set", "query.exclude_recent=3", "--set", "query.temporal_k=1", "--set", "features.n_features=300",
]  # fmt: skip

# child: patch one step of the write sequence to SIGKILL the process at frame KILL_AT, then run
CHILD = r"""
import os, signal, sys
from stablecues.cli.main import main
from stablecues.detection import run as run_mod
from stablecues.runs import store

point, kill_at = sys.argv[1], int(sys.argv[2])
argv = sys.argv[3:]

def die():
    os.kill(os.getpid(), signal.SIGKILL)

if point == "after-similarity-row":
    orig = store.RunWriter._append_similarity
    def patched(self, frame, row):
        orig(self, frame, row)
        if frame == kill_at:
            die()
    store.RunWriter._append_similarity = patched
elif point in ("after-journal", "after-commit"):
    orig = run_mod._DeferredCommit.commit
    def patched(self):
        if len(self._db) == kill_at and point == "after-journal":
            die()
        out = orig(self)
        if len(self._db) == kill_at + 1 and point == "after-commit":
            die()
        return out
    run_mod._DeferredCommit.commit = patched
elif point in ("mid-row", "after-row"):
    orig = store.RunWriter._write_row
    def patched(self, frame, row, times, extra):
        if frame == kill_at and point == "mid-row":
            self._csv.write(",".join(row)[:7])
            self._csv.flush()
            die()
        orig(self, frame, row, times, extra)
        if frame == kill_at and point == "after-row":
            die()
    store.RunWriter._write_row = patched
sys.exit(main(argv))
"""


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """16 frames driving along a wall, the last 7 revisiting the first ones."""
    return write_wall_drive(tmp_path_factory.mktemp("drive"), FRAMES)


@pytest.fixture(scope="module")
def reference(dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ref") / "run"
    assert main(["run", str(dataset), "--out", str(out), *OPTIONS]) == 0
    return out


def _same_run(a: Path, b: Path) -> None:
    ra, rb = load_run(a), load_run(b)
    assert ra.complete and rb.complete
    for name in ("frames", "candidates", "accepted", "status"):
        np.testing.assert_array_equal(getattr(ra, name), getattr(rb, name), err_msg=name)
    for name in ("scores", "raw_scores", "timestamps"):
        np.testing.assert_array_equal(getattr(ra, name), getattr(rb, name), err_msg=name)
    assert ra.extra() == rb.extra()
    sa, sb = ra.similarity, rb.similarity
    assert sa is not None and sb is not None
    np.testing.assert_array_equal(sa, sb)
    assert ra.meta["frames_written"] == FRAMES and not (b / "pending.json").exists()


@pytest.mark.parametrize(
    "point", ["after-similarity-row", "after-journal", "after-commit", "mid-row", "after-row"]
)
def test_killed_run_resumes_to_the_uninterrupted_run(
    point: str, dataset: Path, reference: Path, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    argv = ["run", str(dataset), "--out", str(out), *OPTIONS]
    child = subprocess.run(
        [sys.executable, "-c", CHILD, point, str(KILL_AT), *argv],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
        check=False,
    )
    assert child.returncode == -signal.SIGKILL, child.stderr
    killed = load_run(out)
    assert not killed.complete and len(killed) in (KILL_AT, KILL_AT + 1)
    # killed between journalling the frame and finishing its row: the journal is there to replay
    assert (out / "pending.json").exists() == (point != "after-similarity-row")
    assert main([*argv, "--resume"]) == 0
    _same_run(reference, out)
    assert load_run(reference).accepted.any(), "the drive should close loops"


def test_resume_of_a_finished_run_changes_nothing(
    reference: Path, dataset: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = {p.name: p.read_bytes() for p in reference.iterdir() if p.is_file()}
    assert main(["run", str(dataset), "--out", str(reference), *OPTIONS, "--resume"]) == 0
    out = capsys.readouterr().out
    assert "already complete" in out and "nan" not in out
    after = {p.name: p.read_bytes() for p in reference.iterdir() if p.is_file()}
    assert after == before


def test_existing_out_is_refused_and_overwrite_keeps_user_files(dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["run", str(dataset), "--out", str(out), *OPTIONS, "--max-frames", "2"]) == 1
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert main(["run", str(dataset), "--out", str(out), *OPTIONS, "--max-frames", "2", "--overwrite"]) == 1
    (out / "notes.txt").unlink()
    assert main(["run", str(dataset), "--out", str(out), *OPTIONS, "--max-frames", "2"]) == 0
    (out / "notes.txt").write_text("mine")
    assert main(["run", str(dataset), "--out", str(out), *OPTIONS, "--max-frames", "3", "--overwrite"]) == 0
    assert (out / "notes.txt").read_text() == "mine" and len(load_run(out)) == 3
    meta = json.loads((out / "meta.json").read_text())
    assert meta["dataset_frames"] == FRAMES and meta["complete"]


def test_a_finished_run_extended_with_more_frames_equals_one_run(
    dataset: Path, reference: Path, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    argv = ["run", str(dataset), "--out", str(out), *OPTIONS]
    assert main([*argv, "--max-frames", "6"]) == 0
    assert not (out / "similarity.rows").exists()  # closed: the matrix holds the rows
    assert main([*argv, "--resume"]) == 0
    _same_run(reference, out)


def test_pictures_and_summary_cover_the_whole_resumed_run(
    dataset: Path, reference: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    options = [o for o in OPTIONS if o not in ("--pictures", "0")]
    argv = ["run", str(dataset), "--out", str(out), *options, "--pictures", "3"]
    assert main([*argv, "--max-frames", "13"]) == 0
    for p in (out / "matches").glob("*.png"):
        p.unlink()
    capsys.readouterr()
    assert main([*argv, "--resume"]) == 0
    printed = capsys.readouterr().out
    ref = load_run(reference)
    # the summary counts the whole run, not the resumed part
    n = int(ref.accepted.sum())
    assert f"{FRAMES} frames, {n} loop{'' if n == 1 else 's'} accepted" in printed
    loops = [int(f) for f in ref.frames[ref.accepted]]
    drawn = sorted(int(p.stem.split("_")[1]) for p in (out / "matches").glob("loop_*.png"))
    assert drawn and drawn[0] == loops[0] and drawn[0] < 13  # a loop of the first session is drawn


def test_the_first_frame_s_warm_up_is_reported_apart(
    dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 35: the first frame loads networks and compiles kernels; averaged into ms/frame it
    misled. The summary's ms/frame leaves it out and the run's line names it apart."""
    from stablecues.detection.run import _summary

    out = tmp_path / "run"
    assert main(["run", str(dataset), "--out", str(out), *OPTIONS, "--max-frames", "6"]) == 0
    printed = capsys.readouterr().out
    totals = load_run(out).stage_ms["total"]
    summary = _summary(out, [], 0)
    assert summary.first_frame_ms == pytest.approx(totals[0])
    assert summary.ms_per_frame == pytest.approx(float(np.mean(totals[1:])))
    assert f"{summary.ms_per_frame:.1f} ms/frame (the first, loading, {totals[0]:.0f} ms, apart)" in printed
