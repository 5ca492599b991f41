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
    t = run.timings()  # the first frame (its warm-up) apart
    assert t["features"]["mean"] == pytest.approx(np.mean([2, 3, 4, 2, 6]))
    assert t["features"]["first"] == 1 and t["features"]["count"] == 5
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
    assert "resumed" in run.meta and run.timings()["features"]["count"] == 5  # 6, the first apart
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


def test_a_new_run_refuses_a_directory_that_is_not_empty(tmp_path: Path) -> None:
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match="exists and is not empty"):
        RunWriter(tmp_path / "run", {}, {})
    with pytest.raises(DatasetError, match="holds no run .* refusing to overwrite it"):
        RunWriter(tmp_path / "run", {}, {}, mode="overwrite")
    assert (tmp_path / "run" / "notes.txt").read_text() == "mine"


def test_overwrite_deletes_only_the_runs_own_files(tmp_path: Path) -> None:
    w = _write(tmp_path / "run", n=4, close=False)
    w.add_match_picture("loop_0003_0000", np.zeros((4, 6, 3), np.uint8))
    w.close()
    (tmp_path / "run" / "notes.txt").write_text("mine")
    (tmp_path / "run" / "matches" / "README.md").write_text("mine")
    (tmp_path / "run" / "eval_exact.json").write_text("{}")
    RunWriter(tmp_path / "run", {}, {}, mode="overwrite").close()
    left = sorted(p.relative_to(tmp_path / "run").as_posix() for p in (tmp_path / "run").rglob("*"))
    assert left == ["config.json", "matches", "matches/README.md", "meta.json", "notes.txt", "timings.json",
                    "writer.lock"]  # the lock is never deleted (a new one would not exclude its holder)


def test_nothing_outside_the_run_is_read_or_written_through_a_link(tmp_path: Path) -> None:
    _write(tmp_path / "run", n=4, close=False)
    outside = tmp_path / "outside.jsonl"
    outside.write_text("theirs\n")
    (tmp_path / "run" / "extra.jsonl").unlink(missing_ok=True)
    (tmp_path / "run" / "extra.jsonl").symlink_to(outside)
    with pytest.raises(DatasetError, match=r"extra\.jsonl: run file is a symbolic link"):
        RunWriter(tmp_path / "run", {}, {}, mode="resume")
    with pytest.raises(DatasetError, match=r"extra\.jsonl: per-frame extras is a symbolic link"):
        load_run(tmp_path / "run").extra()
    assert outside.read_text() == "theirs\n"
    (tmp_path / "run" / "extra.jsonl").unlink()
    secret = tmp_path / "secret.png"
    secret.write_bytes(b"secret")
    (tmp_path / "run" / "matches").mkdir()
    (tmp_path / "run" / "matches" / "loop_0001_0000.png").symlink_to(secret)
    assert load_run(tmp_path / "run").matches == []
    (tmp_path / "run" / "meta.json").rename(tmp_path / "meta.json")
    (tmp_path / "run" / "meta.json").symlink_to(tmp_path / "meta.json")
    with pytest.raises(DatasetError, match=r"meta\.json: run metadata is a symbolic link"):
        load_run(tmp_path / "run")


def test_a_planted_temporary_file_is_not_written_through(tmp_path: Path) -> None:
    _write(tmp_path / "run", n=2)
    outside = tmp_path / "outside.txt"
    outside.write_text("theirs")
    (tmp_path / "run" / "meta.json.tmp").symlink_to(outside)
    RunWriter(tmp_path / "run", {}, {}, mode="resume").close()
    assert outside.read_text() == "theirs" and load_run(tmp_path / "run").complete


def test_reconcile_replays_a_committed_frame_and_drops_an_uncommitted_one(tmp_path: Path) -> None:
    """The journal of a frame killed after its commit is written as its row; one killed before
    the commit is dropped, and so are extras and similarity rows past the last row."""
    w = RunWriter(tmp_path / "run", {}, {}, stages=["total"])
    for i in range(3):
        w.add(i, float(i), "no_db_results", -1, math.nan, math.nan, False, {"total": 1.0},
              {"n": i}, similarity=np.full(i, 0.5, np.float32))

    def killed() -> dict[str, float]:
        raise KeyboardInterrupt  # the process dies here, between journal and row

    with pytest.raises(KeyboardInterrupt):
        w.add(3, 3.0, "loop_detected", 1, 0.9, 0.2, True, {"total": 1.0}, {"n": 3},
              similarity=np.full(3, 0.25, np.float32), commit=killed)
    assert (tmp_path / "run" / "pending.json").exists()
    w.release()  # the process died: its lock went with it
    replay = RunWriter(tmp_path / "run", {}, {}, mode="resume")
    assert replay.reconcile(4) == 4  # the map committed frame 3: its row is written
    replay.close()
    run = load_run(tmp_path / "run")
    assert len(run) == 4 and run.candidates[3] == 1 and run.accepted[3]
    assert run.extra()[-1] == {"frame": 3, "n": 3}
    assert run.similarity is not None and np.allclose(run.similarity[3, :3], 0.25)
    assert math.isnan(run.stage_ms["total"][3])  # the commit's time was not recorded
    assert not (tmp_path / "run" / "pending.json").exists()

    with pytest.raises(KeyboardInterrupt):
        w2 = RunWriter(tmp_path / "run2", {}, {}, stages=["total"])
        for i in range(2):
            w2.add(i, float(i), "no_db_results", -1, math.nan, math.nan, False, {"total": 1.0},
                   similarity=np.zeros(i, np.float32))
        w2.add(2, 2.0, "no_db_results", -1, math.nan, math.nan, False, {"total": 1.0},
               similarity=np.zeros(2, np.float32), commit=killed)
    w2.release()  # the process died
    dropped = RunWriter(tmp_path / "run2", {}, {}, mode="resume")
    assert dropped.reconcile(2) == 2  # not committed: frame 2 is done again
    dropped.release()
    with pytest.raises(DatasetError, match="the map holds 5 frames but decisions.csv has 2"):
        RunWriter(tmp_path / "run2", {}, {}, mode="resume").reconcile(5)


def test_similarity_rows_make_the_matrix(tmp_path: Path) -> None:
    w = RunWriter(tmp_path / "run", {}, {}, stages=["total"])
    for i in range(4):
        w.add(i, float(i), "x", -1, math.nan, math.nan, False, {"total": 1.0},
              similarity=np.arange(i, dtype=np.float32) + 1)
    assert load_run(tmp_path / "run").similarity[3].tolist() == [1.0, 2.0, 3.0, 0.0]  # before close
    w.close()
    sim = np.load(tmp_path / "run" / "similarity.npy")
    assert sim.shape == (4, 4) and sim[3].tolist() == [1.0, 2.0, 3.0, 0.0] and np.all(np.triu(sim) == 0)
    with pytest.raises(InputError, match="similarity rows need frames 0, 1, 2"):
        RunWriter(tmp_path / "r2", {}, {}).add(5, 0.0, "x", -1, 0, 0, False, {}, similarity=np.zeros(5))


def test_a_second_writer_of_one_run_is_refused_before_it_writes(tmp_path: Path) -> None:
    """Two ``--resume`` of one run at once: the second is refused in one line and writes
    nothing (it had appended a similarity row and pending.json, issue 34); once the first
    lets go (closed, failed or dropped), the run resumes."""
    first = _write(tmp_path / "run", n=4, close=False)
    before = {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir() if p.is_file()}
    for mode in ("resume", "overwrite"):
        with pytest.raises(DatasetError, match="another stablecues process is writing this run") as err:
            RunWriter(tmp_path / "run", {"preset": "bow"}, {"dataset": "/data/x"}, stages=STAGES, mode=mode)
        assert "\n" not in str(err.value)
    assert {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir() if p.is_file()} == before
    first.release()  # a failed run lets go at once
    second = RunWriter(tmp_path / "run", {"preset": "bow"}, {"dataset": "/data/x"}, mode="resume")
    assert second.next_frame == 4
    del second  # dropped without close, as a killed process
    third = RunWriter(tmp_path / "run", {"preset": "bow"}, {"dataset": "/data/x"}, mode="resume")
    third.close()
    assert load_run(tmp_path / "run").complete and (tmp_path / "run" / "writer.lock").exists()


def test_malformed_run_folders_are_one_line_through_the_commands(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """extra.jsonl lines that are not records of ours, frames out of range in decisions.csv,
    and a meta.json whose "complete" is not true: `eval`, `report` and `results` answered with
    tracebacks (issue 34); each is one line naming the file and line."""
    from stablecues.cli.main import main
    from stablecues.groundtruth import save_ground_truth

    gt = save_ground_truth(tmp_path / "gt.npy", np.zeros((6, 6), bool))
    deep = "[" * 200_000 + "]" * 200_000
    extras = {
        "list": "[1, 2]", "string": '"frame"', "frame_text": '{"frame": "abc"}',
        "frame_nan": '{"frame": NaN}', "frame_huge": '{"frame": 1e999}',
        "results": '{"frame": 2, "results": [1, 2, 3]}',
        "scores": '{"frame": 2, "results": [[1, "x"]]}', "deep": '{"frame": 2, "results": ' + deep + "}",
    }
    for name, line in extras.items():
        run = tmp_path / name
        _write(run)
        (run / "extra.jsonl").write_text(line + "\n" + '{"frame": 3}\n')
        with pytest.raises(DatasetError, match=r"extra\.jsonl: line 1") as err:
            load_run(run).extra()
        assert "\n" not in str(err.value)
        for argv in (["eval", str(run), "--gt", str(gt)], ["report", str(run), "--out", str(tmp_path / "r")]):
            assert main(argv) == 1, (name, argv)
            out = capsys.readouterr().err.strip()
            assert out.count("\n") == 0 and "extra.jsonl" in out, (name, argv, out)
    for frame in ("1180591620717411303424", "-5"):  # 2**70, and below 0
        run = tmp_path / f"frame{frame}"
        _write(run)
        lines = (run / "decisions.csv").read_text().splitlines()
        lines[1] = frame + lines[1][lines[1].index(","):]
        (run / "decisions.csv").write_text("\n".join(lines) + "\n")
        for argv in (["eval", str(run), "--gt", str(gt)], ["results", str(run)]):
            assert main(argv) == 1
            out = capsys.readouterr().err.strip()
            assert out.count("\n") == 0 and "decisions.csv: line 2" in out, (frame, out)
    run = tmp_path / "unfinished"
    _write(run)
    meta = json.loads((run / "meta.json").read_text())
    for value in ("no", 1, "true"):
        (run / "meta.json").write_text(json.dumps({**meta, "complete": value}))
        assert not load_run(run).complete


def test_files_larger_than_the_run_are_refused_before_they_are_read(tmp_path: Path) -> None:
    """Issue 34's memory cases: a sparse 20000^2 similarity.npy under a 6-frame run, a
    decisions.csv with more rows than meta.json's frames, an extra.jsonl line of megabytes and
    more extra lines than frames: each one line, before the data is read."""
    path = tmp_path / "run"
    _write(path)
    sim = path / "similarity.npy"
    with sim.open("wb") as f:
        header = {"descr": "<f4", "fortran_order": False, "shape": (20000, 20000)}
        np.lib.format.write_array_header_1_0(f, header)
        f.truncate(f.tell() + 20000 * 20000 * 4)  # sparse: costs nothing on disk
    with pytest.raises(DatasetError, match=r"shape \(20000, 20000\) is larger than the 6 frames"):
        _ = load_run(path).similarity
    meta = json.loads((path / "meta.json").read_text())
    meta["frames"] = 4
    (path / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="decisions.csv: 6 rows, but .*meta.json gives the run 4 frames"):
        load_run(path)
    meta["frames"] = 6
    (path / "meta.json").write_text(json.dumps(meta))
    extra = path / "extra.jsonl"
    extra.write_text(json.dumps({"frame": 2, "results": [[1, 0.5]] * 200_000}) + "\n")
    with pytest.raises(DatasetError, match="line 1 is .* characters long, more than the 1048576"):
        load_run(path).extra()
    extra.write_text("".join(json.dumps({"frame": i}) + "\n" for i in range(6)) * 2)
    with pytest.raises(DatasetError, match="12 lines for the 6 frames"):
        load_run(path).extra()
