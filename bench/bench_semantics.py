"""Benchmark of the shipped segmentation weights: CamVid test accuracy and CPU speed per T.

    python bench/bench_semantics.py [--data ../shared/data/camvid] [--limit N] [--threads 2]

Prints the figures and writes bench/results/semantics.json with the keys miou, global_acc,
class_acc (CamVid test, default T, void ignored), ms_t1 and ms_default_t (median wall time of
``SegmentationModel.predict`` on a 480x360 frame, onnxruntime on 2 threads), input_size,
default_t, the cost of every T, and the per-class IoU; and under ``int8`` the shipped int8 copy
(``scripts/quantize_segnet.py``) against the float model: T = 1 time on one thread and on
``--threads``, CamVid test mIoU at T = 1, and the share of CamVid val pixels both give the same
class.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from stablecues.semantics import SegmentationModel  # noqa: E402
from stablecues.semantics.data import load_split  # noqa: E402
from stablecues.semantics.evaluate import evaluate_model, format_report  # noqa: E402


def time_predict(model: SegmentationModel, image: np.ndarray, t: int, repeats: int) -> dict[str, float]:
    """Median / min / mean milliseconds of ``predict`` (after two warm-up calls)."""
    for _ in range(2):
        model.predict(image, t, bgr=False)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        model.predict(image, t, bgr=False)
        times.append(1000.0 * (time.perf_counter() - start))
    return {"median": float(np.median(times)), "min": float(np.min(times)), "mean": float(np.mean(times))}


def compare_int8(args: argparse.Namespace, image: np.ndarray, det_fp32: dict) -> dict:
    """The int8 copy against the float weights (both shipped)."""
    out: dict = {}
    models = {p: {th: SegmentationModel.load(threads=th, precision=p) for th in (1, args.threads)}
              for p in ("float32", "int8")}
    for th in (1, args.threads):  # interleaved, so that both see the same machine
        for p in models:
            out[f"ms_t1_{p}_{th}_threads"] = time_predict(models[p][th], image, 1, args.repeats)["median"]
    det = evaluate_model(models["int8"][args.threads], args.data, "test", 1, limit=args.limit)
    out["test_t1"] = {"miou": det["miou"], "global_acc": det["global_acc"], "class_acc": det["class_acc"]}
    out["test_t1_float32"] = {k: det_fp32[k] for k in ("miou", "global_acc", "class_acc")}
    val = load_split(args.data, "val")
    same = [float(np.mean(models["int8"][1].predict(im, 1, bgr=False).labels
                          == models["float32"][1].predict(im, 1, bgr=False).labels)) for im in val.images]
    out["val_same_class"] = {"mean": float(np.mean(same)), "min": float(np.min(same)), "frames": len(same)}
    out["weights"] = models["int8"][1].path.name
    out["sha256"] = models["int8"][1].meta.get("sha256")
    same_pct = 100 * out["val_same_class"]["mean"]
    print(f"int8: T=1 {out['ms_t1_int8_1_threads']:.1f} ms on 1 thread (float32 "
          f"{out['ms_t1_float32_1_threads']:.1f}), test mIoU {100 * det['miou']:.1f} % (float32 "
          f"{100 * det_fp32['miou']:.1f} %), same class as float32 on {same_pct:.2f} % of val pixels")
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default=str(REPO.parent / "shared" / "data" / "camvid"))
    p.add_argument("--weights", default=None)
    p.add_argument("--limit", type=int, default=None, help="evaluate only the first N test frames")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--out", default=str(REPO / "bench" / "results" / "semantics.json"))
    args = p.parse_args()

    model = SegmentationModel.load(args.weights, threads=args.threads)
    t_default = model.default_t
    frames = load_split(args.data, "test", limit=2)
    image = frames.images[0]
    cost = {}
    for t in sorted({1, 2, 4, t_default, 8, 12}):
        cost[t] = time_predict(model, image, t, args.repeats)
        print(f"T={t:2d}: {cost[t]['median']:.1f} ms median ({cost[t]['min']:.1f} min)")
    t1 = cost[1]["median"]
    per_sample = float(np.polyfit(list(cost), [c["median"] for c in cost.values()], 1)[0])
    print(f"cost per extra sample: {per_sample:.2f} ms (trunk runs once)")

    result = evaluate_model(model, args.data, "test", t_default, limit=args.limit, progress=True)
    det = evaluate_model(model, args.data, "test", 1, limit=args.limit)
    print(format_report(result))
    print(f"deterministic (T=1): mIoU {100 * det['miou']:.1f} %, global {100 * det['global_acc']:.1f} %")
    out = {
        "miou": result["miou"],
        "global_acc": result["global_acc"],
        "class_acc": result["class_acc"],
        "ms_t1": t1,
        "ms_default_t": cost[t_default]["median"],
        "input_size": list(model.input_size),
        "frame_size": [int(image.shape[0]), int(image.shape[1])],
        "default_t": t_default,
        "threads": args.threads,
        "ms_per_t": {str(t): c for t, c in cost.items()},
        "ms_per_extra_sample": per_sample,
        "iou": result["iou"],
        "acc": result["acc"],
        "calibration": result["calibration"],
        "t1": {k: det[k] for k in ("miou", "global_acc", "class_acc", "iou")},
        "test_frames": result["frames"],
        "weights": str(model.path.name),
        "sha256": model.meta.get("sha256"),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs visible",
        "load_average": list(os.getloadavg()),
    }
    print(
        f"miou {100 * out['miou']:.1f} %  global {100 * out['global_acc']:.1f} %"
        f"  class {100 * out['class_acc']:.1f} %"
        f"  ms_t1 {t1:.1f}  ms_T{t_default} {out['ms_default_t']:.1f}  input {model.input_size}"
    )
    if args.weights is None:
        out["int8"] = compare_int8(args, image, det)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
