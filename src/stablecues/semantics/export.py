"""Export a trained network to the ONNX graph that onnxruntime runs (needs torch and onnx).

The graph has three inputs and one output, with the sample count T and the image size dynamic:

- ``image``: (1, 3, H, W) float32 RGB in [0, 1] (normalisation is inside the graph);
- ``mask16``: (T, c16, h16, w16) float32 dropout mask on the encoder output (0 or 1/(1-p));
- ``mask8``: (T, c8, h8, w8) float32 dropout mask on the first decoder stage;
- ``prob``: (T, 11, ceil(H/4), ceil(W/4)) float32 softmax of each Monte-Carlo sample.

Batch norm is folded into the convolutions by onnxruntime's graph optimiser at load time.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path
from typing import Any

from .classes import CLASS_NAMES, VOID_NAME

INPUT_NAMES = ["image", "mask16", "mask8"]
OUTPUT_NAMES = ["prob"]


def export_onnx(net: Any, path: str | Path, input_size: tuple[int, int], opset: int = 17) -> Path:
    """Write ``net`` (a :class:`~stablecues.semantics.model.BayesLiteSeg`) as ONNX.

    Args:
        net: the trained network (its mode is set to evaluation).
        path: the ``.onnx`` file to write.
        input_size: (height, width) used to trace; the exported graph accepts any size.
        opset: ONNX opset.

    Returns:
        The path written.
    """
    import torch

    from .model import SamplingWrapper

    net.eval()
    h, w = input_size
    (c16, h16, w16), (c8, h8, w8) = net.mask_shapes(h, w)
    args = (torch.rand(1, 3, h, w), torch.ones(2, c16, h16, w16), torch.ones(2, c8, h8, w8))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the TorchScript exporter, on purpose
        _export(torch, SamplingWrapper(net).eval(), args, path, opset)
    return path


def _export(torch: Any, module: Any, args: tuple[Any, ...], path: Path, opset: int = 17) -> None:
    torch.onnx.export(
        module,
        args,
        str(path),
        input_names=INPUT_NAMES,
        output_names=OUTPUT_NAMES,
        dynamic_axes={
            "image": {2: "H", 3: "W"},
            "mask16": {0: "T", 2: "h16", 3: "w16"},
            "mask8": {0: "T", 2: "h8", 3: "w8"},
            "prob": {0: "T", 2: "h4", 3: "w4"},
        },
        opset_version=opset,
        do_constant_folding=True,
        dynamo=False,
    )


def sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def write_metadata(
    onnx_path: str | Path,
    meta_path: str | Path,
    *,
    net: Any,
    input_size: tuple[int, int],
    default_t: int,
    metrics: dict[str, Any],
    training: dict[str, Any],
) -> dict[str, Any]:
    """Write the JSON that travels with the weights and return it.

    Args:
        onnx_path: the exported graph (hashed into the metadata).
        meta_path: the JSON to write.
        net: the network (architecture facts are read from it).
        input_size: (height, width) frames are resized to before inference.
        default_t: Monte-Carlo samples used when the caller does not choose.
        metrics: evaluation figures ({"val": {...}, "test": {...}}).
        training: how the weights were made (command, epochs, seconds, seed).
    """
    from .model import DROPOUT_P, MEAN, STD, count_parameters

    (c16, _, _), (c8, _, _) = net.mask_shapes(*input_size)
    meta = {
        "format": "stablecues-segnet-1",
        "onnx": Path(onnx_path).name,
        "sha256": sha256(onnx_path),
        "architecture": "BayesLiteSeg (SegNet-style residual encoder-decoder, MC dropout head)",
        "widths": list(net.widths),
        "parameters": count_parameters(net),
        "classes": list(CLASS_NAMES),
        "void": VOID_NAME,
        "input_size": list(input_size),
        "input": "RGB float32 in [0, 1], (1, 3, H, W); mean/std applied inside the graph",
        "mean": list(MEAN),
        "std": list(STD),
        "output_stride": 4,
        "dropout_p": DROPOUT_P,
        "mask_channels": {"mask16": c16, "mask8": c8},
        "default_t": default_t,
        "uncertainty": "variance over the T samples of the softmax of the class with the highest mean",
        "metrics": metrics,
        "training": training,
    }
    Path(meta_path).write_text(json.dumps(meta, indent=2) + "\n")
    return meta
