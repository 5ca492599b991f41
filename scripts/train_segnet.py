#!/usr/bin/env python
"""Remake the shipped segmentation weights: train on CamVid, then export, evaluate and describe.

    python scripts/train_segnet.py --data ../shared/data/camvid --out runs/segnet --epochs 100 \
        --export src/stablecues/data/segnet_camvid.onnx
    # interrupted? the same command with --resume continues from runs/segnet/last.pt

Training alone is ``stablecues segment train``; the export step is ``stablecues segment export``.
Needs the ``train`` extra (torch).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from stablecues.config import merge  # noqa: E402
from stablecues.semantics.inference import DEFAULT_T  # noqa: E402
from stablecues.semantics.train import TrainConfig, train  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default=TrainConfig.data)
    p.add_argument("--out", default=TrainConfig.out_dir)
    p.add_argument("--epochs", type=int, default=TrainConfig.epochs)
    p.add_argument("--batch-size", type=int, default=TrainConfig.batch_size)
    p.add_argument("--lr", type=float, default=TrainConfig.lr)
    p.add_argument("--threads", type=int, default=TrainConfig.threads)
    p.add_argument("--seed", type=int, default=TrainConfig.seed)
    p.add_argument("--resume", action="store_true")
    p.add_argument("--export", default=None, help="after training, write the ONNX weights + metadata here")
    p.add_argument("--default-t", type=int, default=DEFAULT_T)
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    config = merge(
        TrainConfig(),
        {
            "data": args.data,
            "out_dir": args.out,
            "epochs": args.epochs,
            "batch_size": args.batch_size,
            "lr": args.lr,
            "threads": args.threads,
            "seed": args.seed,
        },
    )
    result = train(config, resume=args.resume)
    print(result)
    if args.export:
        from stablecues.semantics.release import release

        command = " ".join(a for a in sys.argv if a != "--resume")
        meta = release(
            Path(args.out) / "best.pt",
            args.export,
            args.data,
            default_t=args.default_t,
            cache_dir=Path(args.out) / "cache",
            command=f"python {command}",
        )
        for key, m in meta["metrics"].items():
            print(f"{key}: mIoU {100 * m['miou']:.2f} %, global {100 * m['global_acc']:.2f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
