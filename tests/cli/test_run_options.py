"""``stablecues run``'s options (issue 14.5): ``--vocab`` (own binary or ORB-SLAM text), the help
text listing the presets, and the hint when the exclusion window leaves nothing to query."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path, write_wall_drive
from stablecues.cli.main import main
from stablecues.cli.run import exclusion_hint
from stablecues.detection import describe_preset, preset, preset_names
from stablecues.detection.run import RunSummary
from stablecues.runs import load_run
from stablecues.vocabulary import load_vocabulary
from stablecues.vocabulary.textformat import write_text

FRAMES = 16
OPTIONS = [
    "--preset", "bow", "--no-progress", "--pictures", "0",
    "--set", "query.exclude_recent=3", "--set", "query.temporal_k=1", "--set", "features.n_features=300",
]  # fmt: skip


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """16 frames driving along a wall, the last 7 revisiting the first ones."""
    return write_wall_drive(tmp_path_factory.mktemp("drive"), FRAMES)


@pytest.fixture(scope="module")
def vocab_files(drive: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A small vocabulary trained on the drive (own binary) and the same in ORB-SLAM's text layout."""
    tmp = tmp_path_factory.mktemp("voc")
    binary = tmp / "small.scv"
    argv = ["vocab", "train", str(drive), "--k", "6", "--levels", "3", "--out", str(binary)]
    assert main([*argv, "--features", "300"]) == 0
    text = tmp / "ORBvoc_small.txt"
    write_text(load_vocabulary(binary), text)
    return binary, text


def _decisions(run_dir: Path) -> dict[str, np.ndarray]:
    run = load_run(run_dir)
    return {name: getattr(run, name) for name in ("frames", "candidates", "accepted", "status", "scores")}


def test_vocab_own_binary_and_orbslam_text(
    drive: Path, vocab_files: tuple[Path, Path], tmp_path: Path
) -> None:
    binary, text = vocab_files
    voc = load_vocabulary(binary)
    runs = {}
    for name, path in (("binary", binary), ("text", text)):
        out = tmp_path / name
        assert main(["run", str(drive), "--out", str(out), *OPTIONS, "--vocab", str(path)]) == 0
        meta = json.loads((out / "meta.json").read_text())
        assert meta["vocabulary"] == str(path)
        assert meta["vocabulary_fingerprint"] == voc.info().fingerprint
        runs[name] = _decisions(out)
    # the same tree from either file: the same decisions and scores
    for key in runs["binary"]:
        np.testing.assert_array_equal(runs["binary"][key], runs["text"][key], err_msg=key)
    # and not the shipped vocabulary's
    assert main(["run", str(drive), "--out", str(tmp_path / "shipped"), *OPTIONS]) == 0
    shipped = _decisions(tmp_path / "shipped")
    assert not np.array_equal(shipped["scores"], runs["binary"]["scores"], equal_nan=True)


def test_resume_with_another_vocabulary_is_refused(
    drive: Path, vocab_files: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    argv = ["run", str(drive), "--out", str(out), *OPTIONS]
    assert main([*argv, "--vocab", str(vocab_files[1]), "--max-frames", "5"]) == 0
    capsys.readouterr()
    assert main([*argv, "--resume"]) == 1  # the map was built with the small vocabulary
    err = capsys.readouterr().err.strip()
    assert err.startswith("stablecues run: error: ") and "\n" not in err
    assert main([*argv, "--resume", "--vocab", str(vocab_files[0])]) == 0
    assert len(load_run(out)) == FRAMES


@pytest.mark.parametrize("content", [b"", b"10 6  0 0\n0 1 2 3\n", b"SCVOCAB\x00\x01\x00"])
def test_a_bad_vocab_file_is_one_line(
    content: bytes, drive: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.txt"
    bad.write_bytes(content)
    out = tmp_path / "run"
    assert main(["run", str(drive), "--out", str(out), *OPTIONS, "--vocab", str(bad)]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(bad) in err
    assert not out.exists()
    assert main(["run", str(drive), "--out", str(out), *OPTIONS, "--vocab", str(tmp_path / "none.scv")]) == 1
    assert "vocabulary file not found" in capsys.readouterr().err


def test_help_lists_every_preset_on_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["run", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("presets (--preset NAME"))
    listed = lines[start + 1 : start + 1 + len(preset_names())]
    for name, line in zip(preset_names(), listed, strict=True):
        assert line.split()[0] == name and line.endswith(describe_preset(name)), line
    flat = " ".join(text.split())
    assert "--no-progress do not draw the progress bar" in flat
    assert "--vocab FILE" in flat and "ORB-SLAM text" in flat
    assert "--rerun FILE.rrd" in flat and "--rerun-spawn" in flat


def test_hint_when_the_exclusion_window_covers_the_sequence(
    drive: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = ["--preset", "fast", "--no-progress", "--pictures", "0", "--max-frames", "10"]
    assert main(["run", str(drive), "--out", str(tmp_path / "a"), *base]) == 0
    printed = capsys.readouterr().out
    assert "10 frames, 0 loops accepted" in printed and "close_matches_only 10" in printed
    hint = next(line for line in printed.splitlines() if line.startswith("hint: "))
    assert "none of the 10 frames" in hint and "query.exclude_recent = 20 frames" in hint
    assert "--set query.exclude_recent=2" in hint
    # following it, the frames are queried and the revisit is found
    argv = ["run", str(drive), "--out", str(tmp_path / "b"), *base, "--set", "query.exclude_recent=2"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "hint:" not in printed
    assert load_run(tmp_path / "b").accepted.any()


def test_hint_on_the_real_ten_frame_desk_loop(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = shared_path("desk_loop10")
    assert main(["run", str(data), "--format", "folder", "--out", str(tmp_path / "run"), "--preset", "fast",
                 "--no-progress", "--pictures", "0"]) == 0
    printed = capsys.readouterr().out
    assert "10 frames, 0 loops accepted" in printed
    assert "hint: none of the 10 frames" in printed


def test_hint_counts_a_mostly_excluded_run() -> None:
    config = preset("fast", {"query": {"exclude_recent": 12, "exclude_recent_s": 3.0}})
    summary = RunSummary(Path("run"), 20, 0, {"close_matches_only": 12, "low_scores": 8}, 1.0, 0)
    hint = exclusion_hint(summary, config)
    assert hint is not None and "12 of the 20 frames" in hint
    assert "query.exclude_recent = 12 frames, query.exclude_recent_s = 3 s" in hint
    assert exclusion_hint(RunSummary(Path("run"), 20, 1, {"close_matches_only": 12}, 1.0, 0), config) is None
    assert exclusion_hint(RunSummary(Path("run"), 20, 0, {"close_matches_only": 9}, 1.0, 0), config) is None
    assert exclusion_hint(RunSummary(Path("run"), 0, 0, {}, float("nan"), 0), config) is None


def test_non_finite_settings_and_huge_sweeps_are_refused_in_one_line(
    drive: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--set query.alpha=NaN`` (JSON reads it as a float) is refused before anything runs, and a
    sweep whose --vary lists multiply past MAX_SWEEP_CELLS is refused before the grid is built."""
    from stablecues.cli.sweep import override_sets
    from stablecues.errors import ConfigError
    from stablecues.limits import MAX_SWEEP_CELLS

    for value in ("NaN", "Infinity", "-Infinity", "[0.1, NaN]"):
        out = tmp_path / f"run_{len(value)}"
        assert main(["run", str(drive), "--out", str(out), "--set", f"query.alpha={value}"]) == 1
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "not a finite number" in err and value in err
        assert not out.exists()
    with pytest.raises(ConfigError, match=f"1048576 configurations; a sweep plans at most {MAX_SWEEP_CELLS}"):
        override_sets([], [f"query.alpha=[0.1, 0.2, 0.3, {k}]" for k in range(10)])
    grid = override_sets(["query.refine=0"], ["query.alpha=[0.1, 0.2]", "query.island_gap=[2, 3, 4]"])
    assert len(grid) == 6


def test_run_calib_gives_the_decisions_of_calib_yaml(tmp_path: Path) -> None:
    """`run --calib FILE` (issue 35): a folder whose calibration lies elsewhere gives the same
    decisions, with the same 3D points from its depth images (the file's DepthMapFactor
    included), as the same folder with the file as its calib.yaml; the run records the file."""
    from stablecues.synthetic import SyntheticTownConfig, write_sequence

    config = SyntheticTownConfig(frames=16, width=256, height=192, seed=3)
    seq = write_sequence(config, tmp_path / "seq", labels=False, progress=False)
    cam = tmp_path / "elsewhere" / "cam.yaml"
    cam.parent.mkdir()
    (seq / "calib.yaml").rename(cam)
    options = ["--preset", "fast", "--no-progress", "--pictures", "0", "--set", "query.exclude_recent=3"]
    assert main(["run", str(seq), "--out", str(tmp_path / "given"), "--calib", str(cam), *options]) == 0
    (seq / "calib.yaml").write_bytes(cam.read_bytes())
    assert main(["run", str(seq), "--out", str(tmp_path / "own"), *options]) == 0
    given, own = _decisions(tmp_path / "given"), _decisions(tmp_path / "own")
    for name in given:
        np.testing.assert_array_equal(given[name], own[name], err_msg=name)
    run = load_run(tmp_path / "given")
    assert run.meta["calibration"] == str(cam)
    assert {e.get("points") for e in run.extra()} == {"depth"}
    assert main(["run", str(seq), "--out", str(tmp_path / "bad"), "--calib", str(tmp_path / "none.yaml"),
                 *options]) == 1
    (tmp_path / "wrong.txt").write_text("1 2 3\n")  # not a calibration: refused before anything is written
    assert main(["run", str(seq), "--out", str(tmp_path / "bad"), "--calib", str(tmp_path / "wrong.txt"),
                 *options]) == 1
    assert not (tmp_path / "bad").exists()
