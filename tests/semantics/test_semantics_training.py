"""Smoke training on two real CamVid frames, resuming, data loading and the metrics."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path
from stablecues.errors import DatasetError
from stablecues.semantics.data import (
    AugmentConfig,
    augment,
    list_split,
    load_split,
    median_frequency_weights,
)
from stablecues.semantics.metrics import CalibrationTable, confusion, summarize


def test_metrics_on_a_hand_made_case() -> None:
    label = np.array([[0, 0, 1, 11]], np.uint8)  # the void pixel is ignored
    pred = np.array([[0, 1, 1, 0]], np.uint8)
    conf = confusion(pred, label)
    assert conf[0, 0] == 1 and conf[0, 1] == 1 and conf[1, 1] == 1 and conf.sum() == 3
    m = summarize(conf)
    assert m.global_acc == pytest.approx(2 / 3)
    assert m.class_acc == pytest.approx((0.5 + 1.0) / 2)
    assert m.miou == pytest.approx((1 / 2 + 1 / 2) / 2)  # class 0: 1/(2+1-1); class 1: 1/(1+2-1)
    assert set(m.iou) == {"Sky", "Building"}
    table = CalibrationTable(np.array([0.0, 0.1, 0.25]))
    table.add(np.array([[0.0, 0.2, 0.05, 0.3]], np.float32), pred, label)
    rows = table.rows()
    assert rows[0]["accuracy"] == pytest.approx(1.0) and rows[1]["accuracy"] == pytest.approx(0.0)
    assert rows[0]["fraction"] == pytest.approx(2 / 3)


def test_median_frequency_weights() -> None:
    labels = np.zeros((2, 4, 4), np.uint8)
    labels[0, :, :2] = 1  # class 1 covers 8 of 16 pixels of the one image it is in; class 0: 24/32
    w = median_frequency_weights(labels)
    freq0, freq1 = 24 / 32, 8 / 16
    med = np.median([freq0, freq1])
    assert w[0] == pytest.approx(med / freq0) and w[1] == pytest.approx(med / freq1)
    assert w[5] == 1.0  # absent class


def test_augment_shapes_and_void_padding() -> None:
    rng = np.random.default_rng(0)
    image = np.full((20, 30, 3), 200, np.uint8)
    label = np.ones((20, 30), np.uint8)
    x, y = augment(image, label, rng, AugmentConfig(crop=(32, 40), scale=(1.0, 1.0)))
    assert x.shape == (3, 32, 40) and x.dtype == np.float32 and y.shape == (32, 40)
    assert float(x.min()) >= 0.0 and float(x.max()) <= 1.0
    assert set(np.unique(y).tolist()) == {1, 11}  # padding is void


def test_missing_dataset_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="trainannot"):
        list_split(tmp_path, "train")
    with pytest.raises(DatasetError, match="split"):
        list_split(tmp_path, "holdout")


def test_smoke_training_on_two_frames_and_resume(tmp_path: Path) -> None:
    pytest.importorskip("torch", reason="torch not installed (the train extra)")
    from stablecues.semantics.train import TrainConfig, load_checkpoint, train

    camvid = shared_path("camvid")
    frames = load_split(camvid, "train", limit=2)
    assert frames.images.shape == (2, 360, 480, 3) and frames.labels.shape == (2, 360, 480)
    cfg = TrainConfig(
        data=str(camvid),
        out_dir=str(tmp_path / "run"),
        epochs=2,
        batch_size=2,
        widths=(4, 8, 8, 16),
        input_size=(48, 64),
        augment=AugmentConfig(crop=(32, 48), scale=(0.1, 0.15)),
        limit=2,
        steps_per_epoch=1,
    )
    first = train(cfg)
    log = [json.loads(x) for x in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in log] == [0, 1] and all(np.isfinite(r["loss"]) for r in log)
    assert 0.0 <= first["best_miou"] <= 1.0
    # resuming a finished run with a longer schedule continues at epoch 3
    from stablecues.config import merge

    train(merge(cfg, {"epochs": 3}), resume=True)
    log = [json.loads(x) for x in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in log] == [0, 1, 2]
    net = load_checkpoint(tmp_path / "run" / "best.pt")
    assert net.widths == (4, 8, 8, 16)


def test_prior_correction_is_a_classifier_bias() -> None:
    torch = pytest.importorskip("torch", reason="torch not installed (the train extra)")
    from stablecues.semantics.model import BayesLiteSeg
    from stablecues.semantics.release import apply_prior

    torch.manual_seed(0)
    net = BayesLiteSeg((4, 8, 8, 16)).eval()
    x = torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        before = net(x)
    log_w = np.log(np.linspace(0.5, 4.0, 11))
    apply_prior(net, 0.5, log_w)
    with torch.no_grad():
        after = net(x)
    shift = torch.from_numpy((0.5 * log_w).astype(np.float32))[None, :, None, None]
    torch.testing.assert_close(after, before - shift, atol=1e-5, rtol=0)


class _Hostile:
    """A pickled object whose loading would run a shell command."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[object, tuple[str]]:
        import os

        return os.system, (f"touch {self.marker}",)


def test_hostile_checkpoint_is_refused_without_running_code(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch", reason="torch not installed (the train extra)")
    from stablecues.errors import ModelError
    from stablecues.semantics.train import load_checkpoint, read_checkpoint

    marker = tmp_path / "ran"
    path = tmp_path / "evil.pt"
    torch.save({"config": {"widths": [4, 8, 8, 16]}, "model": {}, "x": _Hostile(marker)}, path)
    for reader in (read_checkpoint, load_checkpoint):
        with pytest.raises(ModelError, match=r"evil\.pt: not a stablecues training checkpoint"):
            reader(path)
    assert not marker.exists()
    (tmp_path / "cut.pt").write_bytes(path.read_bytes()[:100])
    with pytest.raises(ModelError, match=r"cut\.pt: not a stablecues training checkpoint"):
        read_checkpoint(tmp_path / "cut.pt")
    with pytest.raises(ModelError, match="not found"):
        read_checkpoint(tmp_path / "none.pt")
