"""``stablecues segment``: train, evaluate, export and look at the segmentation network."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Any

from .commands import summary
from .options import add_extractor_options, extractor_from_args


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    from ..semantics.modes import MODES

    p: argparse.ArgumentParser = subparsers.add_parser(
        "segment", help=summary("segment")
    )
    sub = p.add_subparsers(dest="segment_command", metavar="ACTION")

    t = sub.add_parser("train", help="train the network on CamVid (needs torch: stablecues[train])")
    t.add_argument("--data", required=True, help="CamVid folder (train/, trainannot/, val/, ...)")
    t.add_argument("--out", default="runs/segnet", help="checkpoints and log (default runs/segnet)")
    t.add_argument("--epochs", type=int, default=None, help="epochs of the schedule (default 100)")
    t.add_argument("--batch-size", type=int, default=None)
    t.add_argument("--lr", type=float, default=None)
    t.add_argument("--threads", type=int, default=None, help="torch threads (default 1)")
    t.add_argument("--seed", type=int, default=None)
    t.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")

    e = sub.add_parser("eval", help="evaluate the ONNX weights on a CamVid split")
    e.add_argument("--data", required=True, help="CamVid folder")
    e.add_argument("--split", default="test", choices=("train", "val", "test"))
    e.add_argument("--weights", default=None, help="ONNX file (default: the shipped weights)")
    e.add_argument("--precision", default="float32", choices=("float32", "int8"),
                   help="which shipped weights without --weights (default float32; the detector's "
                        "default runs int8)")
    e.add_argument("-T", "--samples", type=int, default=None, help="MC-dropout samples (default: weights')")
    e.add_argument("--limit", type=int, default=None, help="only the first N frames")
    e.add_argument("--threads", type=int, default=2)
    e.add_argument("--json", default=None, help="write the result as JSON here")

    x = sub.add_parser("export", help="export a checkpoint to ONNX with metadata and evaluation")
    x.add_argument("--checkpoint", required=True, help="best.pt of a training run")
    x.add_argument("--out", required=True, help="the .onnx file to write")
    x.add_argument("--data", required=True, help="CamVid folder for the evaluation in the metadata")
    x.add_argument("--default-t", type=int, default=None)
    x.add_argument("--command", default="", help="the training command, recorded in the metadata")
    x.add_argument("--prior-alpha", type=float, default=None, help="prior correction (default: tuned on val)")
    x.add_argument("--cache", default=None, help="folder of the decoded-split cache (e.g. runs/segnet/cache)")

    i = sub.add_parser("image", help="segment one image and draw classes, uncertainty and keypoints")
    i.add_argument("image", help="image file")
    i.add_argument("--out", required=True, help="PNG to write")
    i.add_argument("--weights", default=None, help="ONNX file (default: the shipped weights)")
    i.add_argument("--precision", default="float32", choices=("float32", "int8"),
                   help="which shipped weights without --weights (default float32; the detector's "
                        "default runs int8)")
    i.add_argument("-T", "--samples", type=int, default=None)
    i.add_argument("--mode", default="dynamic", choices=list(MODES),
                   help="masking mode (default: dynamic, the library's default)")
    i.add_argument("--max-uncertainty", type=float, default=None)
    add_extractor_options(i, "to extract")
    return p


def run(args: argparse.Namespace) -> int:
    action = getattr(args, "segment_command", None)
    if action == "train":
        return _train(args)
    if action == "eval":
        return _eval(args)
    if action == "export":
        return _export(args)
    if action == "image":
        return _image(args)
    print("stablecues segment: choose an action: train, eval, export, image", file=sys.stderr)
    return 2


def _train(args: argparse.Namespace) -> int:
    try:
        from ..semantics.train import TrainConfig, train
    except ImportError as exc:  # pragma: no cover - depends on the environment
        from ..errors import MissingDependencyError

        raise MissingDependencyError('segment train needs PyTorch: pip install "stablecues[train]"') from exc
    from ..config import merge

    overrides: dict[str, Any] = {"data": args.data, "out_dir": args.out}
    for key, name in (
        ("epochs", "epochs"),
        ("batch_size", "batch_size"),
        ("lr", "lr"),
        ("threads", "threads"),
        ("seed", "seed"),
    ):
        value = getattr(args, name)
        if value is not None:
            overrides[key] = value
    result = train(merge(TrainConfig(), overrides), resume=args.resume)
    print(json.dumps(result))
    return 0


def _eval(args: argparse.Namespace) -> int:
    from ..outputs import check_output, write_output
    from ..semantics.evaluate import evaluate_model, format_report
    from ..semantics.inference import SegmentationModel

    if args.json:
        check_output(args.json, "evaluation", make_folder=True)  # before the evaluation runs
    model = SegmentationModel.load(args.weights, threads=args.threads, precision=args.precision)
    result = evaluate_model(model, args.data, args.split, args.samples, limit=args.limit, progress=True)
    result["weights"] = str(model.path)
    print(format_report(result))
    if args.json:
        write_output(args.json, json.dumps(result, indent=2) + "\n", "evaluation")
    return 0


def _export(args: argparse.Namespace) -> int:
    from ..semantics.inference import DEFAULT_T
    from ..semantics.release import release

    meta = release(
        args.checkpoint,
        args.out,
        args.data,
        default_t=args.default_t or DEFAULT_T,
        command=args.command or " ".join(shlex.quote(a) for a in sys.argv),
        prior_alpha=args.prior_alpha,
        cache_dir=args.cache,
    )
    print(json.dumps({k: meta[k] for k in ("onnx", "sha256", "input_size", "default_t")}))
    for key, m in meta["metrics"].items():
        figures = f"mIoU {100 * m['miou']:.2f} %, global {100 * m['global_acc']:.2f} %"
        print(f"{key}: {figures}, class {100 * m['class_acc']:.2f} %")
    return 0


def _image(args: argparse.Namespace) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import cv2
    import matplotlib.pyplot as plt

    from ..config import merge
    from ..features import make_extractor
    from ..imageio import read_image
    from ..outputs import check_output, output_file
    from ..semantics.inference import SegmentationModel
    from ..semantics.masking import MaskingConfig, select_features
    from ..semantics.viz import plot_keypoints, plot_overlay, plot_uncertainty

    check_output(args.out, "figure", make_folder=True)
    overrides: dict[str, Any] = {"mode": args.mode}
    if args.max_uncertainty is not None:
        overrides["max_uncertainty"] = args.max_uncertainty
    config = merge(MaskingConfig(), overrides)
    bgr = read_image(args.image)
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    model = SegmentationModel.load(args.weights, precision=args.precision)
    seg = model.predict(bgr, args.samples)
    features = make_extractor(extractor_from_args(args)).extract(bgr)
    _, report = select_features(features, seg, config)
    fig, axes = plt.subplots(2, 2, figsize=(12, 9))
    axes[0, 0].imshow(rgb)
    axes[0, 0].set_title(Path(args.image).name)
    axes[0, 0].axis("off")
    plot_overlay(axes[0, 1], rgb, seg)
    im = plot_uncertainty(axes[1, 0], seg)
    fig.colorbar(im, ax=axes[1, 0], fraction=0.035)
    plot_keypoints(axes[1, 1], rgb, features, report)
    axes[1, 1].set_title(f"{axes[1, 1].get_title()} - mode {config.mode}")
    fig.tight_layout()
    with output_file(args.out, "figure") as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    print(f"{args.out}: {report.kept}/{report.total} keypoints kept, fallback={report.fallback}")
    return 0
