"""Benchmark of the synthetic town renderer: ms per frame at 512x384 (and 384x288).

Prints the figures and writes bench/results/synthetic.json. Times are wall-clock per frame after
a warm-up pass over the same frames (so procedural textures are already made), and separately the
first pass (textures made on first use), which is what ``stablecues synth`` pays.

    python bench/bench_synthetic.py [--frames N]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from stablecues.synthetic import SyntheticTown, SyntheticTownConfig, write_sequence


def time_frames(town: SyntheticTown, frames: list[int], **kw: bool) -> tuple[float, float]:
    """Mean wall and CPU milliseconds per frame over ``frames``."""
    w0, c0 = time.perf_counter(), time.process_time()
    for i in frames:
        town.frame(i, **kw)
    n = len(frames)
    return (time.perf_counter() - w0) / n * 1e3, (time.process_time() - c0) / n * 1e3


def orb_check(town: SyntheticTown) -> dict[str, float]:
    """ORB corners per frame, and matches of revisit pairs against unrelated pairs."""
    gt = town.ground_truth()
    orb = cv2.ORB_create(1000)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    cache: dict[int, tuple[list, np.ndarray | None]] = {}

    def feats(i: int) -> tuple[list, np.ndarray | None]:
        if i not in cache:
            img = cv2.cvtColor(town.frame(i, right=False, labels=False).image, cv2.COLOR_BGR2GRAY)
            cache[i] = orb.detectAndCompute(img, None)
        return cache[i]

    def good(i: int, j: int) -> int:
        _, da = feats(i)
        _, db = feats(j)
        if da is None or db is None:
            return 0
        return sum(1 for m in bf.match(da, db) if m.distance < 40)

    rng = np.random.default_rng(0)
    qs = np.nonzero(gt.any(axis=1))[0]
    sel = rng.choice(qs, size=min(25, len(qs)), replace=False) if len(qs) else []
    loop_m, other_m = [], []
    for i in sel:
        j = int(
            np.nonzero(gt[i])[0][
                np.argmin(np.linalg.norm(town.positions[np.nonzero(gt[i])[0]] - town.positions[i], axis=1))
            ]
        )
        far = (
            np.nonzero(np.linalg.norm(town.positions[: i - 20] - town.positions[i], axis=1) > 60)[0]
            if i > 20
            else []
        )
        if not len(far):
            continue
        k = int(rng.choice(far))
        loop_m.append(good(int(i), j))
        other_m.append(good(int(i), k))
    n_kp = [len(feats(int(i))[0]) for i in list(cache)[:20]]
    lm, om = np.array(loop_m), np.array(other_m)
    return {
        "orb_keypoints_per_frame_mean": float(np.mean(n_kp)) if n_kp else 0.0,
        "revisit_pairs": len(loop_m),
        "revisit_beats_unrelated_fraction": float(np.mean(lm > om)) if len(lm) else 0.0,
        "revisit_good_matches_median": float(np.median(loop_m)) if loop_m else 0.0,
        "unrelated_good_matches_median": float(np.median(other_m)) if other_m else 0.0,
        "loop_queries": int(gt.any(axis=1).sum()),
        "loop_pairs": int(gt.sum()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=40, help="frames timed per resolution")
    args = ap.parse_args()
    out: dict[str, object] = {
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0],
        "opencv_threads": cv2.getNumThreads(),
    }
    for w, h in ((512, 384), (384, 288)):
        cfg = SyntheticTownConfig(frames=300, width=w, height=h, seed=1)
        town = SyntheticTown(cfg)
        frames = list(np.linspace(0, cfg.frames - 1, args.frames).astype(int))
        first, first_cpu = time_frames(town, frames)
        full, full_cpu = time_frames(town, frames)
        left, left_cpu = time_frames(town, frames, right=False)
        key = f"{w}x{h}"
        out[f"ms_per_frame_{key}"] = full
        out[f"cpu_ms_per_frame_{key}"] = full_cpu
        out[f"ms_per_frame_left_only_{key}"] = left
        out[f"ms_per_frame_first_pass_{key}"] = first
        print(
            f"{key}: {full:.1f} ms/frame stereo+depth+labels ({full_cpu:.1f} ms CPU), "
            f"left only {left:.1f} ms, first pass with texture making {first:.1f} ms"
        )
    with tempfile.TemporaryDirectory() as tmp:
        cfg = SyntheticTownConfig(frames=300, width=384, height=288, seed=2)
        t0 = time.perf_counter()
        write_sequence(cfg, Path(tmp) / "seq", progress=False)
        out["write_sequence_300_384x288_s"] = time.perf_counter() - t0
        print(f"write_sequence 300 frames 384x288: {out['write_sequence_300_384x288_s']:.1f} s")
    town = SyntheticTown(SyntheticTownConfig(frames=300, width=512, height=384, seed=1))
    t0 = time.perf_counter()
    town.ground_truth()
    out["ground_truth_300_frames_s"] = time.perf_counter() - t0
    orb = orb_check(town)
    out.update(orb)
    print("ORB:", json.dumps(orb))
    path = Path(__file__).resolve().parent / "results" / "synthetic.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
