"""Turn a training checkpoint into shipped weights: ONNX graph, metadata JSON, training log.

Needs torch (export); the evaluation that fills the metadata runs the exported graph.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from .data import CamVidSplit, load_split, median_frequency_weights, to_input
from .evaluate import evaluate_model
from .inference import DEFAULT_T, SegmentationModel
from .metrics import confusion, summarize

log = logging.getLogger(__name__)

#: Candidate strengths of the prior correction, chosen on the validation split.
ALPHA_GRID = (0.0, 0.25, 0.5, 0.75, 1.0)


def tune_prior_alpha(
    net: Any,
    split: CamVidSplit,
    log_weights: np.ndarray,
    input_size: tuple[int, int],
    grid: tuple[float, ...],
) -> tuple[float, dict[str, float]]:
    """Strength ``alpha`` of the logit offset ``-alpha * log(w_c)`` that maximises mIoU on ``split``.

    Training with class weights w_c (median-frequency balancing) shifts the optimum of the
    softmax towards ``w_c p(c | x)``: rare classes are over-predicted, which raises class-average
    accuracy but costs IoU. Subtracting ``alpha * log(w_c)`` from the logits undoes a fraction
    of that shift; it is a per-class bias, folded into the classifier at export.

    Returns:
        (best alpha, {alpha: mIoU}) with deterministic (T = 1) predictions as inference makes them.
    """
    import cv2
    import torch

    logits = []
    with torch.no_grad():
        for image in split.images:
            logits.append(net(torch.from_numpy(to_input(image, input_size)))[0].numpy())
    scores: dict[str, float] = {}
    for alpha in grid:
        conf = np.zeros((log_weights.size, log_weights.size), np.int64)
        for z, label in zip(logits, split.labels, strict=True):
            z = z - alpha * log_weights[:, None, None]
            p = np.exp(z - z.max(axis=0))
            p /= p.sum(axis=0)
            up = cv2.resize(np.ascontiguousarray(p.transpose(1, 2, 0)), (label.shape[1], label.shape[0]))
            conf += confusion(up.argmax(axis=2), label)
        scores[str(alpha)] = summarize(conf).miou
        log.info("prior alpha %.2f: val mIoU %.4f", alpha, scores[str(alpha)])
    best = max(grid, key=lambda a: scores[str(a)])
    return float(best), scores


def apply_prior(net: Any, alpha: float, log_weights: np.ndarray) -> None:
    """Fold the logit offset ``-alpha * log(w_c)`` into the classifier's bias (in place)."""
    import torch

    with torch.no_grad():
        net.classifier.bias -= torch.from_numpy((alpha * log_weights).astype(np.float32))


def training_log_markdown(log_jsonl: str | Path, command: str) -> str:
    """A Markdown table of a run's ``log.jsonl`` (one row per epoch)."""
    rows = [json.loads(line) for line in Path(log_jsonl).read_text().splitlines() if line.strip()]
    out = [
        "# Training log of the shipped segmentation weights",
        "",
        f"Command: `{command}`",
        "",
        "| epoch | loss | lr | val mIoU % | val global % | val class-avg % | seconds |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        if "val_miou" in r:
            val = f"{100 * r['val_miou']:.2f} | {100 * r['val_global']:.2f} | {100 * r['val_class']:.2f}"
        else:
            val = "- | - | -"
        out.append(f"| {r['epoch'] + 1} | {r['loss']:.4f} | {r['lr']:.2e} | {val} | {r['time_s']:.0f} |")
    return "\n".join(out) + "\n"


def release(
    checkpoint: str | Path,
    onnx_path: str | Path,
    data: str | Path,
    *,
    default_t: int = DEFAULT_T,
    splits: tuple[str, ...] = ("val", "test"),
    cache_dir: str | Path | None = None,
    command: str = "",
    prior_alpha: float | None = None,
) -> dict[str, Any]:
    """Export ``checkpoint`` to ``onnx_path``, evaluate it, and write ``<stem>.json`` and
    ``<stem>_training.md`` beside it.

    Args:
        checkpoint: ``best.pt`` of a training run (its folder's ``log.jsonl`` becomes the log).
        onnx_path: where the graph goes (e.g. ``src/stablecues/data/segnet_camvid.onnx``).
        data: CamVid folder for the evaluation.
        default_t: Monte-Carlo samples the weights default to.
        splits: splits to evaluate, each at T = 1 and T = default_t.
        cache_dir: decoded-split cache folder.
        command: the command that made the checkpoint, recorded in the metadata.
        prior_alpha: strength of the prior correction (see :func:`tune_prior_alpha`); None
            chooses it on the validation split.

    Returns:
        The metadata written.
    """
    from .export import export_onnx, write_metadata
    from .train import load_checkpoint, read_checkpoint

    checkpoint = Path(checkpoint)
    net = load_checkpoint(checkpoint)
    ckpt = read_checkpoint(checkpoint)
    size = ckpt["config"]["input_size"]
    input_size = (int(size[0]), int(size[1]))
    cfg = ckpt["config"]
    train_labels = load_split(data, "train", cache_dir=cache_dir).labels
    log_weights = np.log(np.minimum(median_frequency_weights(train_labels), float(cfg["max_weight"])))
    alpha_scores: dict[str, float] = {}
    if prior_alpha is None:
        val = load_split(data, "val", cache_dir=cache_dir)
        prior_alpha, alpha_scores = tune_prior_alpha(net, val, log_weights, input_size, ALPHA_GRID)
    apply_prior(net, prior_alpha, log_weights)
    onnx_path = Path(onnx_path)
    export_onnx(net, onnx_path, input_size)
    meta_path = onnx_path.with_suffix(".json")
    if meta_path.exists():
        meta_path.unlink()  # stale metadata must not describe the new graph
    model = SegmentationModel.load(onnx_path)
    model.default_t = default_t
    model.input_size = (int(input_size[0]), int(input_size[1]))  # no metadata file yet
    metrics: dict[str, Any] = {}
    for split in splits:
        for t in sorted({1, default_t}):
            r = evaluate_model(model, data, split, t, cache_dir=cache_dir)
            key = f"{split}_T{t}"
            metrics[key] = {k: r[k] for k in ("frames", "T", "miou", "global_acc", "class_acc", "iou", "acc")}
            if t == default_t:
                metrics[key]["calibration"] = r["calibration"]
            log.info("%s: mIoU %.4f global %.4f class %.4f", key, r["miou"], r["global_acc"], r["class_acc"])
    log_jsonl = checkpoint.parent / "log.jsonl"
    epochs_logged = 0
    train_seconds = 0.0
    if log_jsonl.is_file():
        lines = [json.loads(x) for x in log_jsonl.read_text().splitlines() if x.strip()]
        epochs_logged = len(lines)
        train_seconds = float(sum(x.get("time_s", 0.0) for x in lines))
        md = onnx_path.with_name(onnx_path.stem + "_training.md")
        md.write_text(training_log_markdown(log_jsonl, command))
    training = {
        "command": command,
        "checkpoint_epoch": int(ckpt["epoch"]) + 1,
        "schedule_epochs": int(ckpt["config"]["epochs"]),
        "epochs_logged": epochs_logged,
        "train_seconds": round(train_seconds, 1),
        "seed": int(ckpt["config"]["seed"]),
        "config": ckpt["config"],
        "hardware": "CPU, 1 thread (no GPU)",
        "prior_correction": {
            "alpha": prior_alpha,
            "log_class_weights": [round(float(v), 6) for v in log_weights],
            "val_miou_by_alpha": alpha_scores,
            "note": "logits - alpha * log(median-frequency weight), folded into the classifier bias",
        },
    }
    return write_metadata(
        onnx_path,
        meta_path,
        net=net,
        input_size=input_size,
        default_t=default_t,
        metrics=metrics,
        training=training,
    )
