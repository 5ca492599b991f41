"""``stablecues vocab`` end to end: train, info, convert, errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.cli.main import main


def write_images(folder: Path, n: int = 4) -> None:
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        img = np.full((160, 200), 120, np.uint8)
        for _ in range(80):
            x, y = int(rng.integers(0, 190)), int(rng.integers(0, 150))
            cv2.circle(img, (x, y), int(rng.integers(2, 12)), int(rng.integers(0, 256)), -1)
        cv2.imwrite(str(folder / f"{i:03d}.png"), img)


def test_train_info_convert(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_images(tmp_path / "imgs")
    out = tmp_path / "v.scv"
    assert main(["vocab", "train", str(tmp_path / "imgs"), "--k", "4", "--levels", "3",
                 "--out", str(out), "--features", "200"]) == 0
    assert main(["vocab", "info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "k:           4" in text and "levels:      3" in text and "weighting:   tf-idf" in text
    assert main(["vocab", "convert", str(out), str(tmp_path / "v.txt")]) == 0
    assert (tmp_path / "v.txt").read_text().startswith("4 3")


def test_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["vocab", "info", str(tmp_path / "missing.scv")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "missing.scv" in err and "not found" in err
    (tmp_path / "bad.txt").write_text("not a vocabulary\n")
    assert main(["vocab", "info", str(tmp_path / "bad.txt")]) == 1
    assert "bad.txt" in capsys.readouterr().err
    assert main(["vocab", "train", str(tmp_path / "nothing"), "--out", str(tmp_path / "x.scv")]) == 1


def test_features_by_name_and_the_old_number_form_agree(tmp_path: Path) -> None:
    write_images(tmp_path / "imgs")
    old, new = tmp_path / "old.scv", tmp_path / "new.scv"
    common = ["vocab", "train", str(tmp_path / "imgs"), "--k", "4", "--levels", "2"]
    assert main([*common, "--out", str(old), "--features", "150"]) == 0
    assert main([*common, "--out", str(new), "--features", "orb", "--n-features", "150"]) == 0
    assert old.read_bytes() == new.read_bytes()


def test_extractors_the_vocabulary_cannot_take_are_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    write_images(tmp_path / "imgs", n=1)
    out = tmp_path / "v.txt"  # SIFT vocabularies are made (issue 14), but have no DBoW2 text form
    assert main(["vocab", "train", str(tmp_path / "imgs"), "--out", str(out), "--features", "sift"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "128-dim float32" in err and "32-byte binary" in err
    assert not out.exists()
    out = tmp_path / "v.scv"
    assert main(["vocab", "train", str(tmp_path / "imgs"), "--out", str(out), "--features", "surf"]) == 1
    assert "unknown feature extractor 'surf'; known: orb, sift" in capsys.readouterr().err


def test_info_of_the_shipped_xfeat_vocabulary(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["vocab", "info", "default:xfeat"]) == 0
    out = capsys.readouterr().out
    assert "64-dim float32" in out and "10000" in out and "make_xfeat_vocabulary.py" in out
    assert "gardens" not in out.lower()  # trained on development data only
