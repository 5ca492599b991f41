"""The ``stablecues segment`` command: eval, image, and its error line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import shared_path
from stablecues.cli.main import main


@pytest.fixture(scope="module")
def tiny_onnx(tmp_path_factory: pytest.TempPathFactory) -> Path:
    torch = pytest.importorskip("torch", reason="torch not installed (the train extra)")
    pytest.importorskip("onnx", reason="onnx not installed (the train extra)")
    from stablecues.semantics.export import export_onnx
    from stablecues.semantics.model import BayesLiteSeg

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("cli") / "tiny.onnx"
    export_onnx(BayesLiteSeg((4, 8, 8, 16)), path, (48, 64))
    path.with_suffix(".json").write_text('{"input_size": [48, 64], "default_t": 3}')
    return path


def test_eval_prints_and_writes_json(
    tiny_onnx: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    camvid = shared_path("camvid")
    out = tmp_path / "eval.json"
    argv = ["segment", "eval", "--data", str(camvid), "--split", "val", "--limit", "2"]
    code = main([*argv, "--weights", str(tiny_onnx), "--json", str(out), "-T", "2", "--threads", "1"])
    assert code == 0
    text = capsys.readouterr().out
    assert "mIoU" in text and "calibration" in text
    result = json.loads(out.read_text())
    assert result["frames"] == 2 and result["T"] == 2
    assert {"miou", "global_acc", "class_acc", "iou", "calibration"} <= set(result)
    assert 0.0 <= result["miou"] <= 1.0
    assert abs(sum(row["fraction"] for row in result["calibration"]) - 1.0) < 1e-9


@pytest.mark.parametrize(
    "features", [["--features", "200"], ["--features", "orb", "--n-features", "200"], ["--features", "sift"]]
)
def test_image_writes_a_picture(
    tiny_onnx: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], features: list[str]
) -> None:
    frame = sorted((shared_path("camvid") / "test").iterdir())[0]
    out = tmp_path / "seg.png"
    code = main(["segment", "image", str(frame), "--out", str(out), "--weights", str(tiny_onnx), *features])
    assert code == 0 and out.stat().st_size > 10_000
    kept, total = capsys.readouterr().out.split(": ")[1].split(" ")[0].split("/")
    assert 0 <= int(kept) <= int(total) <= (200 if "200" in features else 1000) and int(total) > 50


def test_missing_weights_is_one_clear_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["segment", "eval", "--data", str(tmp_path), "--weights", str(tmp_path / "gone.onnx")])
    assert code == 1
    err = capsys.readouterr().err
    assert "gone.onnx" in err and "not found" in err and "Traceback" not in err


def test_image_with_the_shipped_int8_weights(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    frame = sorted((shared_path("camvid") / "test").iterdir())[0]
    out = tmp_path / "seg.png"
    code = main(["segment", "image", str(frame), "--out", str(out), "--precision", "int8"])
    assert code == 0 and out.stat().st_size > 10_000
    assert "/" in capsys.readouterr().out
