#!/usr/bin/env python
"""Make the shipped network's int8 copy (issue 11: the network pass at about half the time).

onnxruntime's static quantisation (QDQ format, weights int8 per output channel, activations
uint8 with MinMax ranges) of ``src/stablecues/data/segnet_camvid.onnx``, calibrated on every
10th frame of CamVid ``train`` (the frames the network was trained on; ``val`` and ``test``
stay out). The dropout masks stay float inputs, so Monte-Carlo sampling works as before.

Writes ``segnet_camvid_int8.onnx`` and its metadata ``segnet_camvid_int8.json`` (the float
model's, plus the quantisation's provenance and both models' ``val`` scores at T = 1, measured
here). Deterministic: the same inputs give the same file.

Run: ``python scripts/quantize_segnet.py [--data ../shared/data/camvid]`` (needs the ``train``
extra for ``onnx``).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from stablecues.semantics.evaluate import evaluate_model
from stablecues.semantics.inference import SegmentationModel, default_weights_path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "src" / "stablecues" / "data"
OPS = ["Conv", "ConvTranspose", "Add", "Relu", "Resize", "Concat", "MaxPool"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "camvid")
    ap.add_argument("--every", type=int, default=10, help="calibrate on every k-th train frame")
    ap.add_argument("--out", type=Path, default=DATA / "segnet_camvid_int8.onnx")
    args = ap.parse_args()
    try:
        from onnxruntime.quantization import (
            CalibrationDataReader,
            CalibrationMethod,
            QuantFormat,
            QuantType,
            quantize_static,
        )
        from onnxruntime.quantization.shape_inference import quant_pre_process
    except ImportError as exc:
        sys.exit(f"quantize_segnet: onnxruntime's quantisation tools need onnx: "
                 f"pip install -e '.[train]' ({exc})")
    if not args.out.parent.is_dir():
        sys.exit(f"quantize_segnet: {args.out.parent}: no such directory for the output")
    if args.every < 1:
        sys.exit(f"quantize_segnet: --every {args.every}: expected a positive frame step")
    frames = sorted((args.data.resolve() / "train").glob("*.[jp][pn]g"))[:: args.every]  # read in tmp
    if not frames:
        sys.exit(f"quantize_segnet: {args.data / 'train'}: no CamVid train frames found")
    src = default_weights_path()
    fp32 = SegmentationModel.load(src, threads=1)
    h, w = fp32.input_size
    m16, m8 = fp32.masks(1, h, w)

    def prepared(path: Path) -> np.ndarray:  # as SegmentationModel.predict prepares a frame
        rgb = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
        interp = cv2.INTER_AREA if rgb.shape[0] > h else cv2.INTER_LINEAR
        x = cv2.resize(rgb, (w, h), interpolation=interp).astype(np.float32) * np.float32(1.0 / 255.0)
        return np.ascontiguousarray(x.transpose(2, 0, 1)[None])

    class Frames(CalibrationDataReader):  # type: ignore[misc]
        def __init__(self) -> None:
            self.it = iter(frames)

        def get_next(self) -> dict[str, np.ndarray] | None:
            f = next(self.it, None)
            return None if f is None else {"image": prepared(f), "mask16": m16, "mask8": m8}

    args.out = args.out.resolve()
    # the quantizer writes scratch files (an augmented model's external data, "<uuid>.data") into
    # the working directory: run it inside the temporary folder so that none is left behind
    with tempfile.TemporaryDirectory() as tmp, contextlib.chdir(tmp):
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)
        quantize_static(str(pre), str(args.out), Frames(), quant_format=QuantFormat.QDQ,
                        op_types_to_quantize=OPS, per_channel=True, weight_type=QuantType.QInt8,
                        activation_type=QuantType.QUInt8, calibrate_method=CalibrationMethod.MinMax)
    meta: dict[str, Any] = json.loads(src.with_suffix(".json").read_text())
    meta["onnx"] = args.out.name
    meta["sha256"] = hashlib.sha256(args.out.read_bytes()).hexdigest()
    int8 = SegmentationModel.load(args.out, threads=1)
    scores = {}
    for name, model in (("float32", fp32), ("int8", int8)):
        r = evaluate_model(model, args.data, "val", 1)
        scores[name] = {k: r[k] for k in ("frames", "miou", "global_acc", "class_acc")}
        print(f"{name}: val mIoU {r['miou']:.4f}, global accuracy {r['global_acc']:.4f}", flush=True)
    meta["quantization"] = {
        "from": src.name, "from_sha256": hashlib.sha256(src.read_bytes()).hexdigest(),
        "tool": "onnxruntime.quantization.quantize_static", "format": "QDQ",
        "weights": "int8, per output channel", "activations": "uint8, MinMax calibration",
        "ops": OPS, "calibration": f"every {args.every}th frame of CamVid train ({len(frames)} frames)",
        "command": "python scripts/quantize_segnet.py", "val_T1": scores,
    }
    meta["metrics"] = {"val_T1": scores["int8"]}  # this model's own (the float model's are above)
    args.out.with_suffix(".json").write_text(json.dumps(meta, indent=2) + "\n")
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.2f} MB) and its metadata")


if __name__ == "__main__":
    main()
