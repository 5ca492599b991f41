"""Training of the segmentation network on CamVid (needs the ``train`` extra: torch).

Resumable: a checkpoint (model, optimiser, epoch, best score) is written to ``out_dir/last.pt``
after every epoch and ``out_dir/best.pt`` whenever the validation mIoU improves; ``resume=True``
continues from ``last.pt``. Every random choice derives from ``seed`` and the epoch number, so a
resumed run repeats what an uninterrupted one would have done. The loss is cross-entropy with
median-frequency-balanced class weights, void ignored. One JSON line per epoch goes to
``out_dir/log.jsonl`` (loss, validation mIoU / global / class accuracy, time).
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError
from .classes import NUM_CLASSES, VOID_ID
from .data import AugmentConfig, CamVidSplit, augment, load_split, median_frequency_weights
from .metrics import SegMetrics, confusion, summarize

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainConfig:
    """Settings of one training run.

    Attributes:
        data: CamVid folder (SegNet layout).
        out_dir: where checkpoints, the cache and the log go.
        epochs: total epochs of the schedule (the cosine decay ends there).
        batch_size: frames per step.
        lr: peak learning rate of AdamW.
        weight_decay: AdamW weight decay.
        warmup_epochs: linear warm-up length.
        widths: channel widths of the network at 1/2, 1/4, 1/8, 1/16.
        input_size: (height, width) the network sees at inference and validation.
        augment: training augmentation.
        seed: the seed every random choice derives from.
        threads: torch intra-op threads.
        max_weight: clip of the median-frequency weights.
        limit: use only the first ``limit`` frames of each split (smoke tests).
        steps_per_epoch: cap on steps per epoch (smoke tests); None = the whole split.
        val_every: validate every n epochs (and at the last one).
    """

    data: str = "../shared/data/camvid"
    out_dir: str = "runs/segnet"
    epochs: int = 120
    batch_size: int = 8
    lr: float = 3e-3
    weight_decay: float = 1e-4
    warmup_epochs: int = 2
    widths: tuple[int, int, int, int] = (16, 32, 64, 128)
    input_size: tuple[int, int] = (288, 384)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    seed: int = 0
    threads: int = 1
    max_weight: float = 20.0
    limit: int | None = None
    steps_per_epoch: int | None = None
    val_every: int = 1


def _require_torch() -> Any:
    try:
        import torch
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError('training needs PyTorch: pip install "stablecues[train]"') from exc
    return torch


def lr_at(config: TrainConfig, step: int, steps_per_epoch: int) -> float:
    """Learning rate at global ``step``: linear warm-up, then cosine decay to 1 % of the peak."""
    total = max(1, config.epochs * steps_per_epoch)
    warm = max(1, config.warmup_epochs * steps_per_epoch)
    if step < warm:
        return config.lr * (step + 1) / warm
    t = min(1.0, (step - warm) / max(1, total - warm))
    return config.lr * (0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * t)))


def evaluate_torch(net: Any, split: CamVidSplit, input_size: tuple[int, int]) -> SegMetrics:
    """Deterministic (dropout off) evaluation at the labels' full resolution."""
    torch = _require_torch()
    import torch.nn.functional as F

    from .data import to_input

    net.eval()
    conf = np.zeros((NUM_CLASSES, NUM_CLASSES), np.int64)
    with torch.no_grad():
        for image, label in zip(split.images, split.labels, strict=True):
            x = torch.from_numpy(to_input(image, input_size))
            logits = net(x)
            logits = F.interpolate(logits, size=label.shape, mode="bilinear", align_corners=False)
            pred = logits[0].argmax(0).numpy()
            conf += confusion(pred, label)
    return summarize(conf)


def _resume(last: Path, net: Any, opt: Any, config: TrainConfig) -> tuple[int, float, int]:
    """Load ``last.pt`` into the network and optimiser: (next epoch, best mIoU, best epoch).

    Raises:
        ConfigError: the checkpoint's widths differ from the config's.
    """
    ckpt = read_checkpoint(last)
    if tuple(ckpt["config"]["widths"]) != tuple(config.widths):
        raise ConfigError(f"{last}: checkpoint widths {ckpt['config']['widths']}, asked {config.widths}")
    net.load_state_dict(ckpt["model"])
    opt.load_state_dict(ckpt["optimizer"])
    start_epoch, best_miou, best_epoch = ckpt["epoch"] + 1, ckpt["best_miou"], ckpt["best_epoch"]
    log.info("resumed from %s at epoch %d (best val mIoU %.4f)", last, start_epoch, best_miou)
    return start_epoch, best_miou, best_epoch


def _train_epoch(
    net: Any, opt: Any, train_set: CamVidSplit, class_w: Any, config: TrainConfig, epoch: int, steps: int
) -> list[float]:
    """One epoch of ``steps`` optimiser steps; the loss of each step.

    The shuffle, the augmentation and torch's dropout are seeded from ``config.seed`` and
    ``epoch``, so a resumed run repeats the epoch exactly.
    """
    torch = _require_torch()
    import torch.nn.functional as F

    n = len(train_set)
    rng = np.random.default_rng([config.seed, epoch])
    torch.manual_seed(config.seed * 100003 + epoch)
    order = rng.permutation(n)
    net.train()
    losses = []
    for s in range(steps):
        idx = order[(s * config.batch_size) % n : (s * config.batch_size) % n + config.batch_size]
        if idx.size < config.batch_size:
            idx = np.concatenate([idx, order[: config.batch_size - idx.size]])
        pairs = [augment(train_set.images[i], train_set.labels[i], rng, config.augment) for i in idx]
        x = torch.from_numpy(np.stack([p[0] for p in pairs]))
        y = torch.from_numpy(np.stack([p[1] for p in pairs]))
        for g in opt.param_groups:
            g["lr"] = lr_at(config, epoch * steps + s, steps)
        logits = net(x)
        logits = F.interpolate(logits, size=y.shape[-2:], mode="bilinear", align_corners=False)
        loss = F.cross_entropy(logits, y, weight=class_w, ignore_index=VOID_ID)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(float(loss.item()))
    return losses


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The dictionary of a checkpoint written by :func:`train`, read without unpickling code.

    ``torch.load(weights_only=True)`` admits tensors, containers and plain values only, so a
    hostile ``.pt`` file cannot run anything; anything else is a one-line :class:`ModelError`.
    """
    torch = _require_torch()
    from ..errors import ModelError

    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: checkpoint not found")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises UnpicklingError, RuntimeError, EOFError ...
        first = " ".join(str(exc).split())[:200]
        raise ModelError(f"{path}: not a stablecues training checkpoint "
                         f"({type(exc).__name__}: {first})") from exc
    if not isinstance(ckpt, dict) or not {"config", "model"} <= set(ckpt):
        raise ModelError(f"{path}: not a stablecues training checkpoint "
                         "(expected a dict with config and model)")
    return ckpt


def _save_atomic(checkpoint: dict[str, Any], path: Path) -> None:
    """``torch.save`` to ``path`` through a ``.tmp`` file, so a killed run never leaves half a file."""
    torch = _require_torch()
    tmp = path.with_name(path.name + ".tmp")
    torch.save(checkpoint, tmp)
    tmp.replace(path)


def _log_epoch(
    out: Path, record: dict[str, Any], config: TrainConfig, best_miou: float, best_epoch: int
) -> None:
    """Append the epoch's record to ``log.jsonl`` and log one line."""
    with open(out / "log.jsonl", "a") as f:
        f.write(json.dumps(record) + "\n")
    log.info(
        "epoch %d/%d loss %.4f val mIoU %s (best %.4f @ %d) %.0fs",
        record["epoch"] + 1,
        config.epochs,
        record["loss"],
        f"{record['val_miou']:.4f}" if "val_miou" in record else "-",
        best_miou,
        best_epoch + 1,
        record["time_s"],
    )


def train(config: TrainConfig, *, resume: bool = False) -> dict[str, Any]:
    """Train (or continue training) and return the best validation metrics.

    Args:
        config: the run's settings.
        resume: continue from ``out_dir/last.pt`` when it exists.

    Returns:
        {"best_miou", "best_epoch", "epochs_done", "out_dir"}.
    """
    torch = _require_torch()
    from .model import BayesLiteSeg, count_parameters

    if config.epochs < 1 or config.batch_size < 1:
        raise ConfigError(f"epochs and batch_size must be >= 1, got {config.epochs}, {config.batch_size}")
    torch.set_num_threads(config.threads)
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cache = out / "cache"
    train_set = load_split(config.data, "train", cache_dir=cache, limit=config.limit)
    val_set = load_split(config.data, "val", cache_dir=cache, limit=config.limit)
    weights = np.minimum(median_frequency_weights(train_set.labels), config.max_weight)
    log.info("class weights %s", np.round(weights, 3).tolist())

    torch.manual_seed(config.seed)
    net = BayesLiteSeg(config.widths)
    opt = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    start_epoch, best_miou, best_epoch = 0, -1.0, -1
    last = out / "last.pt"
    if resume and last.is_file():
        start_epoch, best_miou, best_epoch = _resume(last, net, opt, config)
    log.info("network: %d parameters, widths %s", count_parameters(net), config.widths)

    steps = max(1, len(train_set) // config.batch_size)
    if config.steps_per_epoch is not None:
        steps = min(steps, config.steps_per_epoch)
    class_w = torch.from_numpy(weights)
    cfg_dict = asdict(config)
    for epoch in range(start_epoch, config.epochs):
        t0 = time.time()
        losses = _train_epoch(net, opt, train_set, class_w, config, epoch, steps)
        record: dict[str, Any] = {
            "epoch": epoch,
            "loss": float(np.mean(losses)),
            "lr": lr_at(config, (epoch + 1) * steps - 1, steps),
            "train_s": round(time.time() - t0, 1),
        }
        if (epoch + 1) % config.val_every == 0 or epoch + 1 == config.epochs:
            m = evaluate_torch(net, val_set, config.input_size)
            record.update(val_miou=m.miou, val_global=m.global_acc, val_class=m.class_acc)
            if m.miou > best_miou:
                best_miou, best_epoch = m.miou, epoch
                _save_atomic(
                    {"model": net.state_dict(), "config": cfg_dict, "epoch": epoch, "val": m.as_dict()},
                    out / "best.pt",
                )
        record["time_s"] = round(time.time() - t0, 1)
        ckpt = {
            "model": net.state_dict(),
            "optimizer": opt.state_dict(),
            "epoch": epoch,
            "best_miou": best_miou,
            "best_epoch": best_epoch,
            "config": cfg_dict,
        }
        _save_atomic(ckpt, last)
        _log_epoch(out, record, config, best_miou, best_epoch)
    return {
        "best_miou": best_miou,
        "best_epoch": best_epoch,
        "epochs_done": config.epochs,
        "out_dir": str(out),
    }


def load_checkpoint(path: str | Path) -> Any:
    """The network of a checkpoint (``best.pt`` or ``last.pt``), in evaluation mode."""
    from .model import BayesLiteSeg

    ckpt = read_checkpoint(path)
    net = BayesLiteSeg(tuple(ckpt["config"]["widths"]))
    net.load_state_dict(ckpt["model"])
    net.eval()
    return net
