"""stablecues.runs.store: writing a run directory, reading it back, interrupted runs, resuming."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from stablecues.errors import DatasetError, InputError
from stablecues.runs import RunWriter, load_run

STAGES = ["features", "bow", "verify"]


def _write(path: Path, n: int = 6, close: bool = True) -> RunWriter:
    w = RunWriter(path, {"preset": "bow", "k": 10}, {"dataset": "/data/x", "format": "folder"}, stages=STAGES)
    for i in range(n):
        cand = i - 3 if i >= 3 else -1
        w.add(
            i,
            0.1 * i,
            "accepted" if i % 2 else "low_score",
            cand,
            0.5 + 0.05 * i if cand >= 0 else math.nan,
            0.01 * i,
            bool(i % 2) and cand >= 0,
            {"features": 1.0 + i, "bow": 0.5} if i != 4 else {"features": 2.0},
            {"n_keypoints": 100 + i} if i == 2 else None,
        )
    w.set_similarity(np.tril(np.full((n, n), 0.25)))
    if close:
        w.close()
    return w


def test_write_and_read_back(tmp_path: Path) -> None:
    _write(tmp_path / "run")
    run = load_run(tmp_path / "run")
    assert len(run) == 6 and run.complete and not run.truncated
    np.testing.assert_array_equal(run.frames, np.arange(6))
    np.testing.assert_array_equal(run.candidates, [-1, -1, -1, 0, 1, 2])
    assert run.accepted.tolist() == [False, False, False, True, False, True]
    assert math.isnan(run.scores[0]) and run.scores[5] == pytest.approx(0.75)
    assert run.timestamps[3] == pytest.approx(0.3)
    assert list(run.stage_ms) == STAGES and math.isnan(run.stage_ms["bow"][4])
    assert np.isnan(run.stage_ms["verify"]).all()
    assert run.status_counts() == {"accepted": 3, "low_score": 3}
    assert run.config == {"preset": "bow", "k": 10}
    assert (
        run.meta["format"] == "folder" and run.meta["frames_written"] == 6 and "numpy" in run.meta["versions"]
    )
    t = run.timings()
    assert t["features"]["mean"] == pytest.approx(np.mean([1, 2, 3, 4, 2, 6]))
    assert t["verify"]["count"] == 0
    sim = run.similarity
    assert sim is not None and sim.dtype == np.float32 and sim.shape == (6, 6)
    assert run.extra() == [{"frame": 2, "n_keypoints": 102}]
    header = (tmp_path / "run" / "decisions.csv").read_text().splitlines()[0]
    assert (
        header
        == "frame,timestamp,status,candidate,score,raw_score,accepted,t_features_ms,t_bow_ms,t_verify_ms"
    )
    json.loads((tmp_path / "run" / "timings.json").read_text())  # strict JSON, no NaN


def test_killed_run_leaves_readable_prefix_and_resumes(tmp_path: Path) -> None:
    w = _write(tmp_path / "run", n=5, close=False)
    # the process dies mid-row: a partial line without its newline, no close()
    with (tmp_path / "run" / "decisions.csv").open("a") as fh:
        fh.write("5,0.5,acc")
    del w
    run = load_run(tmp_path / "run")
    assert len(run) == 5 and run.truncated and not run.complete
    with pytest.raises(DatasetError, match="already holds a run"):
        RunWriter(tmp_path / "run", {}, {})
    w2 = RunWriter(tmp_path / "run", {"preset": "bow"}, {"dataset": "/data/x"}, mode="resume")
    assert w2.next_frame == 5 and w2.stages == STAGES
    w2.add(5, 0.5, "accepted", 1, 0.9, 0.1, True, {"features": 1.0})
    w2.close()
    run = load_run(tmp_path / "run")
    assert len(run) == 6 and not run.truncated and run.complete and run.candidates[5] == 1
    assert "resumed" in run.meta and run.timings()["features"]["count"] == 6
    w3 = RunWriter(tmp_path / "run", {}, {}, mode="overwrite")
    w3.close()
    assert not (tmp_path / "run" / "similarity.npy").exists()


def test_writer_rejects_bad_rows(tmp_path: Path) -> None:
    w = RunWriter(tmp_path / "r", {}, {}, stages=["a"])
    w.add(0, 0.0, "no_results", -1, math.nan, math.nan, False, {"a": 1.0})
    with pytest.raises(InputError, match="after 0"):
        w.add(0, 0.0, "x", -1, 0, 0, False, {})
    with pytest.raises(InputError, match="earlier frame"):
        w.add(1, 0.0, "x", 1, 0, 0, False, {})
    with pytest.raises(InputError, match="status"):
        w.add(1, 0.0, "a,b", -1, 0, 0, False, {})
    with pytest.raises(InputError, match="declare every stage"):
        w.add(1, 0.0, "x", -1, 0, 0, False, {"b": 1.0})
    with pytest.raises(InputError, match="square"):
        w.set_similarity(np.zeros((2, 3)))
    with pytest.raises(InputError, match="name"):
        w.add_match_picture("../evil", np.zeros((2, 2), np.uint8))
    pic = w.add_match_picture("loop_0001_0000", np.zeros((4, 6, 3), np.uint8))
    assert pic.is_file()
    w.close()
    assert load_run(tmp_path / "r").matches == [pic]


def test_load_run_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="not found"):
        load_run(tmp_path / "absent")
    _write(tmp_path / "run")
    d = tmp_path / "run" / "decisions.csv"
    good = d.read_text()
    d.write_text(good.replace("frame,timestamp", "frm,timestamp"))
    with pytest.raises(DatasetError, match="header"):
        load_run(tmp_path / "run")
    lines = good.splitlines()
    d.write_text("\n".join([lines[0], lines[2], lines[1]]) + "\n")
    with pytest.raises(DatasetError, match="frames must increase"):
        load_run(tmp_path / "run")
    d.write_text("\n".join([lines[0], lines[1].replace(",0,", ",x,", 1)]) + "\n")
    with pytest.raises(DatasetError, match="line 2"):
        load_run(tmp_path / "run")
    d.write_text(good)
    np.save(tmp_path / "run" / "similarity.npy", np.zeros((2, 2), np.float32))
    sim = load_run(tmp_path / "run").similarity  # a prefix (killed between checkpoints) is kept
    assert sim is not None and sim.shape == (2, 2)
    np.save(tmp_path / "run" / "similarity.npy", np.zeros((2, 3), np.float32))
    with pytest.raises(DatasetError, match="square"):
        _ = load_run(tmp_path / "run").similarity
    (tmp_path / "run" / "meta.json").write_text("[1, 2]")
    with pytest.raises(DatasetError, match="JSON object"):
        load_run(tmp_path / "run")
