#!/usr/bin/env python
"""Loop-closure benchmark (issue 5) on the real data in ``../shared/data``.

Presets side by side (the default, the paper, the DBoW2/DLoopDetector baselines and the
ablations) on:

* ``corridor``: a two-pass indoor set (reference pass, then query pass, one sequence); query i
  closes a loop with reference i+-2 (its ground truth file). Protocols exact / tolerance /
  iBoW-LCD with n = 2, the detector's exclusion window of 20 frames.
* ``camvid/test``: a real urban retrieval task. Frames where the camera has not moved since
  the last kept one are dropped first (median LK optical flow of tracked corners under 3 px:
  the car stands still there, while people and other cars may move); then per sequence the
  even frames form the database and the odd ones are queries whose true matches are the
  database frames directly before and after them.
  Recall@1 (the top BoW candidate, before verification) and R@100P of accepted detections;
  masking from CamVid's own test labels (an upper bound for masking) and, when the network's
  weights are there, from the shipped network.
* ``desk_loop10``: 10 frames circling a desk, frame 10 re-views frame 1 (no temporal
  consistency possible: one loop frame); exclusion of 3 frames.
* ``euroc/loop_pairs``: two real stereo loop pairs (0-1, 2-3) and their cross pairs; frames
  stored 0, 2 then queried 1, 3: are 1->0 and 3->2 accepted, is anything else?
* ``camvid_revisit_dev`` (issue 11's development sets, CamVid ``train`` / ``val`` drives never
  ``test``): two traversals, the second under a changed appearance, distractor runs between;
  ground truth by verified visual overlap (``gt.png``), exact-cell protocol. Beside every preset:
  a DBoW2-style top-1 retrieval with its raw score swept (no normalisation, no islands, no
  temporal window, no geometry), and the loss funnel of each run (where the true loops were lost).

* ``viewpoint`` (not in the default sections): the nearest-viewpoint walk's settings around
  the default's on the corridor and the two revisit sets:
  ``python bench/bench_loops.py --sections viewpoint``.

* ``sift`` (not in the default sections; issue 14): SIFT with the shipped float vocabulary
  against ORB with the shipped binary one, on the corridor and the two revisit sets, BoW stages
  only: ``python bench/bench_loops.py --sections sift --out bench/results/sift.json``.

Prints tables and writes ``bench/results/loops.json``. Runs in a few minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from stablecues.datasets import open_dataset
from stablecues.detection import LoopDetector, describe_preset, preset
from stablecues.detection.run import run_dataset
from stablecues.errors import ModelError
from stablecues.evaluation import evaluate_detections, evaluate_run, load_run
from stablecues.evaluation.funnel import loss_funnel
from stablecues.groundtruth import load_ground_truth
from stablecues.imageio import read_image
from stablecues.types import Frame

HERE = Path(__file__).resolve().parent
SHARED = HERE.parent.parent / "shared" / "data"
MAIN_PRESETS = ["default", "fast", "paper", "bow", "bow-nogeom"]
ABLATIONS = ["mask-only", "triangles-only", "paper-triangles-noise", "dilate", "patch", "dynamic",
             "weighted", "mono-triangles"]
#: issue 11's switches, each turned off from the default (or on, for the ones it leaves off)
SWITCHES: dict[str, dict[str, Any]] = {
    "default": {},
    "- run-aware window (a fixed 20 frames)": {"query": {"run_break": None}},
    "- several islands (verify 1, as DLoopDetector)": {"query": {"islands_verified": 1}},
    "- refined entry (the island's best, as DLoopDetector)": {"query": {"refine": 0}},
    "- nearest-viewpoint walk (the entry with the most inliers)": {"query": {"viewpoint_steps": 0}},
    "- fundamental thresholds (12 inliers, no ratio, RANSAC)": {
        "verification": {"min_fundamental_inliers": 12, "min_fundamental_ratio": 0.0,
                         "fundamental_method": "ransac"}},
    "- static matches kept (none left out at 0.5 px)": {"verification": {"static_px": None}},
    "+ temporal window k = 2": {"query": {"temporal_k": 2}},
    "+ temporal window k = 3 (DLoopDetector)": {"query": {"temporal_k": 3}},
    "+ monocular triangles": {"monocular": {}},
    "+ monocular triangles, stable ranking of triangle matches": {
        "monocular": {}, "verification": {"stable_ranking": True}},
    "- semantic weighting (dynamic mask only)": {"weighting": None},
    "- dynamic mask (weighting only)": {"masking": None},
    "- semantics (preset fast: no network)": {"weighting": None, "masking": None},
    "hard static mask instead (the paper's)": {"weighting": None, "masking": {"mode": "hard"}},
    "- int8 network (float32, as trained)": {"segmentation_precision": "float32"},
}
STABLE_RANKING = "default + stable ranking of triangle matches"
TOP1 = {"query": {"use_nss": False, "alpha": 0.0, "temporal_k": 1, "island_gap": 0, "islands_verified": 1},
        "confidence": "bow", "similarity": False}
PROTOCOLS = (("exact", 0), ("tolerance", 2), ("ibow", 2))


def needs_segmentation(cfg: Any) -> bool:
    """Whether a configuration needs segmentation (a mask or semantic weighting)."""
    return cfg.masking is not None or cfg.weighting is not None


def uses_masking(name: str) -> bool:
    """Whether the preset needs segmentation (a mask or semantic weighting)."""
    return needs_segmentation(preset(name))


def network_available() -> bool:
    try:
        from stablecues.semantics.inference import SegmentationModel

        SegmentationModel.load()
        return True
    except (ModelError, ImportError, FileNotFoundError):
        return False


# ---------------------------------------------------------------------------------- corridor
def bench_corridor(names: list[str], work: Path) -> dict[str, Any]:
    root = SHARED / "corridor"
    ds = open_dataset(root, format="vprbench")
    gt = ds.ground_truth()
    out: dict[str, Any] = {"frames": len(ds), "gt_file": str(gt.path), "protocols": {}}
    for name in names:
        run_dir = work / f"corridor_{name}"
        t = time.perf_counter()
        summary = run_dataset(ds, preset(name), run_dir, preset_name=name, progress=False, pictures=0)
        wall = time.perf_counter() - t
        run = load_run(run_dir)
        res: dict[str, Any] = {
            "ms_per_frame": round(summary.ms_per_frame, 2),
            "wall_s": round(wall, 1),
            "loops": summary.loops,
            "mask_fallbacks": summary.mask_fallbacks,
        }
        for proto, tol in PROTOCOLS:
            ev, _ = evaluate_run(run, gt, protocol=proto, tolerance=tol, exclude=20)
            res[f"{proto}"] = {
                "r_at_100p": round(ev.recall_at_100p, 4),
                "auc": round(ev.auc, 4),
                "tp": ev.tp,
                "fp": ev.fp,
                "fn": ev.fn,
                "positives": ev.positives,
            }
        out[name] = res
        print(
            f"  corridor {name:22s} R@100P exact {res['exact']['r_at_100p']:.3f} "
            f"tol {res['tolerance']['r_at_100p']:.3f} ibow {res['ibow']['r_at_100p']:.3f} "
            f"(TP {res['tolerance']['tp']} FP {res['tolerance']['fp']}) {res['ms_per_frame']} ms/frame",
            flush=True,
        )
    return out


# ---------------------------------------------------------------------------------- camvid
STILL_PX = 3.0  # median optical flow under this (of 480 px) from the last kept frame: the car stands still


def median_flow(a: np.ndarray, b: np.ndarray) -> float:
    """Median displacement in pixels of corners tracked from image a to image b (LK flow).

    A camera standing still has near-zero flow on the static background even when people and
    cars move, which a plain image difference cannot tell apart from real motion."""
    p = cv2.goodFeaturesToTrack(a, 400, 0.01, 7)
    if p is None:
        return float("inf")
    q, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p, None, winSize=(21, 21), maxLevel=3)
    ok = st.ravel() == 1
    if not ok.any():
        return float("inf")
    return float(np.median(np.linalg.norm((q - p).reshape(-1, 2)[ok], axis=1)))


def camvid_frames() -> tuple[list[Frame], list[int], list[int], np.ndarray]:
    """Deduplicated CamVid test frames with labels; database / query indices; ground truth."""
    files = sorted((SHARED / "camvid" / "test").glob("*.jpg"))
    kept: list[tuple[str, Path]] = []
    last: np.ndarray | None = None
    last_seq = None
    for f in files:
        seq = f.name.split("_")[0]
        grey = read_image(f, "grey")
        if seq == last_seq and last is not None and median_flow(last, grey) < STILL_PX:
            continue
        kept.append((seq, f))
        last, last_seq = grey, seq
    db_files, q_files = [], []
    by_seq: dict[str, list[Path]] = {}
    for seq, f in kept:
        by_seq.setdefault(seq, []).append(f)
    truth_pairs: list[tuple[Path, list[Path]]] = []
    for seq_files in by_seq.values():
        evens = seq_files[0::2]
        db_files += evens
        for k, f in enumerate(seq_files):
            if k % 2 == 1:
                q_files.append(f)
                truth_pairs.append(
                    (f, [seq_files[k - 1]] + ([seq_files[k + 1]] if k + 1 < len(seq_files) else []))
                )
    order = db_files + q_files
    index = {f: i for i, f in enumerate(order)}
    frames = []
    for i, f in enumerate(order):
        labels = cv2.imread(str(SHARED / "camvid" / "testannot" / (f.stem + ".png")), cv2.IMREAD_UNCHANGED)
        frames.append(Frame(index=i, name=f.name, timestamp=float(i), image=read_image(f), labels=labels))
    gt = np.zeros((len(order), len(order)), bool)
    for q, truths in truth_pairs:
        for t in truths:
            gt[index[q], index[t]] = True
    return frames, list(range(len(db_files))), [index[q] for q, _ in truth_pairs], gt


def bench_camvid(names: list[str], network: bool) -> dict[str, Any]:
    frames, db_idx, q_idx, gt = camvid_frames()
    out: dict[str, Any] = {
        "database": len(db_idx),
        "queries": len(q_idx),
        "dropped_static": 233 - len(frames),
    }
    retrieval = {"query": {"exclude_recent": 0, "temporal_k": 1, "use_nss": False, "alpha": 0.0}}
    for name in names:
        sources = ["labels", "network"] if uses_masking(name) else ["none"]
        for source in sources:
            if source == "network" and not network:
                continue
            over: dict[str, Any] = dict(retrieval)
            if source != "none":
                over["semantic_source"] = source
            det = LoopDetector(preset(name, over))
            for i in db_idx:
                det.store(frames[i])
            top1, cands, scores, totals, fallbacks = [], [], [], [], 0
            for i in q_idx:
                d = det.process(frames[i], store=False)
                top1.append(d.candidate_frame >= 0 and gt[i, d.candidate_frame])
                cands.append(d.candidate_frame if d.accepted else -1)
                scores.append(d.confidence)
                totals.append(d.timings["total"])
                fallbacks += int(d.mask_fallback)
            ev = evaluate_detections(gt, np.array(q_idx), np.array(cands), np.array(scores), protocol="exact")
            key = name if source == "none" else f"{name}[{source}]"
            out[key] = {
                "recall_at_1": round(float(np.mean(top1)), 4),
                "r_at_100p": round(ev.recall_at_100p, 4),
                "auc": round(ev.auc, 4),
                "tp": ev.tp,
                "fp": ev.fp,
                "positives": ev.positives,
                "ms_per_query": round(float(np.mean(totals)), 2),
                "mask_fallbacks": fallbacks,
            }
            print(
                f"  camvid {key:30s} recall@1 {out[key]['recall_at_1']:.3f} R@100P {ev.recall_at_100p:.3f} "
                f"(TP {ev.tp} FP {ev.fp} of {ev.positives}) {out[key]['ms_per_query']} ms/query",
                flush=True,
            )
            det.close()
    return out


# ---------------------------------------------------------------------------------- small sets
def bench_desk(names: list[str], overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """desk_loop10 with each preset (``overrides`` on top of the set's own, e.g. a vocabulary)."""
    folder = SHARED / "desk_loop10"
    frames = [
        Frame(index=i, name=f"{i + 1}.png", timestamp=float(i), image=read_image(folder / f"{i + 1}.png"))
        for i in range(10)
    ]
    out: dict[str, Any] = {}
    for name in names:
        over = {"query": {"exclude_recent": 3, "temporal_k": 1}, **(overrides or {})}
        det = LoopDetector(preset(name, over))
        decisions = [det.process(f) for f in frames]
        loops = [(d.frame_index + 1, d.candidate_frame + 1) for d in decisions if d.accepted]
        last = decisions[-1]
        out[name] = {
            "loops_1based": loops,
            "frame10": last.status.value,
            "frame10_candidate": last.candidate_frame + 1,
            "true_loop_found": (10, 1) in loops,
            "false_loops": [p for p in loops if p != (10, 1)],
            "ms_per_frame": round(float(np.mean([d.timings["total"] for d in decisions])), 2),
        }
        print(
            f"  desk_loop10 {name:22s} loops {loops} "
            f"frame 10: {last.status.value} -> {last.candidate_frame + 1}",
            flush=True,
        )
    return out


def bench_euroc(names: list[str], overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The EuRoC loop pairs with each preset (``overrides`` on top, as for :func:`bench_desk`)."""
    from stablecues.geometry import load_euroc_stereo

    root = SHARED / "euroc" / "loop_pairs"
    calib = load_euroc_stereo(root / "sensorLeft.yaml", root / "sensorRight.yaml")

    def frame(i: int, k: int) -> Frame:
        return Frame(
            index=k,
            name=f"left_img_{i}.png",
            timestamp=float(k),
            image=read_image(root / f"left_img_{i}.png", "grey"),
            right=read_image(root / f"right_img_{i}.png", "grey"),
            calibration=calib,
        )

    out: dict[str, Any] = {}
    # the one development set whose frames form triangles: the stable ranking switched on too
    variants: dict[str, tuple[str, dict[str, Any]]] = {name: (name, {}) for name in names}
    if "default" in names:
        variants[STABLE_RANKING] = ("default", {"verification": {"stable_ranking": True}})
    for name, (preset_name, extra) in variants.items():
        over: dict[str, Any] = {
            "query": {"exclude_recent": 0, "temporal_k": 1, "use_nss": False, "alpha": 0.0},
            "features": {"n_features": 2000}, **extra, **(overrides or {}),
        }
        if uses_masking(preset_name):
            over["semantic_source"] = "network"
        try:
            det = LoopDetector(preset(preset_name, over))
            det.store(frame(0, 0))
            det.store(frame(2, 1))
            d1 = det.process(frame(1, 2), store=False)
            d3 = det.process(frame(3, 3), store=False)
        except ModelError as exc:
            out[name] = {"skipped": str(exc)}
            continue
        def row(d: Any, want: int) -> dict[str, Any]:
            v = d.verification
            return {
                "candidate": {0: "0", 1: "2"}.get(d.candidate, "-"),
                "accepted": d.accepted,
                "correct": d.accepted and d.candidate == want,
                "verification": None if v is None else v.reason,
            }

        out[name] = {"1->0": row(d1, 0), "3->2": row(d3, 1)}
        print(
            f"  euroc {name:22s} 1->{out[name]['1->0']['candidate']} {d1.status.value}; "
            f"3->{out[name]['3->2']['candidate']} {d3.status.value}",
            flush=True,
        )
    return out


# ---------------------------------------------------------------------------------- revisits
REVISITS = ("train_drives", "val_drive")
DYNAMIC_IDS = (8, 9, 10)  # CamVid Car, Pedestrian, Bicyclist


def make_swapped(src: Path, dst: Path, seed: int = 0) -> Path:
    """A copy of a revisit set whose second traversal has other cars and people: every dynamic
    object (CamVid's own labels) is inpainted away and the dynamic objects of another frame of the
    set (at least a third of the set away) are pasted in at their own pixels. Written to ``dst``
    (a temporary folder: derived data never enters the repository)."""
    gt = cv2.imread(str(src / "gt.png"), cv2.IMREAD_GRAYSCALE) > 0
    rows = set(np.flatnonzero(gt.any(axis=1)).tolist())
    frames = sorted((src / "frames").glob("*.jpg"))
    labels = sorted((src / "labels").glob("*.png"))
    rng = np.random.default_rng(seed)
    (dst / "frames").mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(frames):
        img = cv2.imread(str(f))
        if i in rows:
            lab = cv2.imread(str(labels[i]), cv2.IMREAD_GRAYSCALE)
            dyn = np.isin(lab, DYNAMIC_IDS).astype(np.uint8)
            if dyn.any():
                img = cv2.inpaint(img, cv2.dilate(dyn, np.ones((5, 5), np.uint8)) * 255, 5, cv2.INPAINT_TELEA)
            gap = min(30, len(frames) // 3)
            j = int(rng.choice([k for k in range(len(frames)) if abs(k - i) > gap]))
            other, olab = cv2.imread(str(frames[j])), cv2.imread(str(labels[j]), cv2.IMREAD_GRAYSCALE)
            if other.shape == img.shape:
                paste = np.isin(olab, DYNAMIC_IDS)
                img[paste] = other[paste]
        cv2.imwrite(str(dst / "frames" / f.name), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    (dst / "gt.png").write_bytes((src / "gt.png").read_bytes())
    return dst


def _run_eval(ds: Any, gt: Any, cfg: Any, work: Path, name: str, score: str = "score") -> dict[str, Any]:
    run_dir = work / name.replace(" ", "_").replace("/", "_")
    summary = run_dataset(ds, cfg, run_dir, preset_name=name, progress=False, pictures=0)
    run = load_run(run_dir)
    ev, _ = evaluate_run(run, gt, protocol="exact", tolerance=0, exclude=0, score=score)  # type: ignore[arg-type]
    funnel = loss_funnel(run, gt.matrix, ev, query_mask=gt.query_mask)
    # the verifier that decided each verified frame (the fallback's name when it stood in)
    verifiers = Counter(str(e["verifier"]) for e in run.extra() if "verifier" in e)
    return {
        "r_at_100p": round(ev.recall_at_100p, 4), "tp": ev.tp, "fp": ev.fp, "positives": ev.positives,
        "tp_at_100p": ev.tp_at_100p, "ms_per_frame": round(summary.ms_per_frame, 2),
        "funnel": funnel.counts, "verifiers": dict(verifiers.most_common()),
        "scale_change": scale_of_loops(run, gt),
    }


def scale_of_loops(run: Any, gt: Any) -> dict[str, Any]:
    """|scale change| (``extra.jsonl``'s ``scale_change``) of the accepted loops of the scored
    queries, true and false ones apart: the median, and each false loop's (most confident
    first) with how many frames its candidate is off the nearest true one."""
    scale = {int(e["frame"]): abs(float(e["scale_change"])) for e in run.extra() if "scale_change" in e}
    tp, fp = [], []
    order = np.argsort(-np.asarray(run.scores, float), kind="stable")
    for i in order.tolist():
        f, c = int(run.frames[i]), int(run.candidates[i])
        scored = gt.query_mask is None or bool(gt.query_mask[f])
        if not run.accepted[i] or c < 0 or f not in scale or not scored:
            continue
        if gt.matrix[f, c]:
            tp.append(scale[f])
        else:
            true = np.flatnonzero(gt.matrix[f])
            off = int(np.min(np.abs(true - c))) if true.size else None
            fp.append({"frame": f, "candidate": c, "frames_off": off, "abs_scale": round(scale[f], 3)})
    return {"tp_median_abs": round(float(np.median(tp)), 3) if tp else None, "tp": len(tp),
            "fp": fp}


def eval_configs(ds: Any, gt: Any, configs: dict[str, Any], work: Path, tag: str, network: bool
                 ) -> dict[str, dict[str, Any]]:
    """Each configuration run and scored on one set (label -> :func:`_run_eval`'s figures, run
    folders ``{tag}_{label}``); those that need segmentation are left out without the network."""
    out: dict[str, dict[str, Any]] = {}
    for label, cfg in configs.items():
        if not network and needs_segmentation(cfg):
            continue
        out[label] = _run_eval(ds, gt, cfg, work, f"{tag}_{label}")
    return out


def bench_revisits(network: bool) -> dict[str, Any]:
    """The default, the presets, issue 11's switches and the DBoW2 top-1 baseline per set."""
    out: dict[str, Any] = {}
    dev = SHARED / "camvid_revisit_dev"
    corridor = open_dataset(SHARED / "corridor", format="vprbench")
    with tempfile.TemporaryDirectory() as tmp:
        sets = {name: (dev / name / "frames", dev / name / "gt.png") for name in REVISITS}
        for name in REVISITS:
            swapped = make_swapped(dev / name, Path(tmp) / f"swapped_{name}")
            sets[f"{name} (objects swapped)"] = (swapped / "frames", swapped / "gt.png")
        for set_name in [*sets, "corridor"]:
            if set_name == "corridor":
                ds, gt = corridor, corridor.ground_truth()
            else:
                ds = open_dataset(sets[set_name][0], format="folder")
                gt = load_ground_truth(sets[set_name][1])
            res: dict[str, Any] = {"frames": len(ds), "gt_file": str(gt.path) if "swapped" not in set_name
                                   else f"{gt.path.name} of {set_name.split()[0]}"}
            tag = set_name.split()[0] + ("_swapped" if "swapped" in set_name else "")
            res["dbow2 top-1, raw score swept"] = _run_eval(ds, gt, preset("bow-nogeom", TOP1), Path(tmp),
                                                            f"{tag}_top1", score="raw_score")
            configs = {name: preset(name) for name in ["bow", "paper", "bow-nogeom"]}
            configs.update({label: preset("default", over) for label, over in SWITCHES.items()})
            res.update(eval_configs(ds, gt, configs, Path(tmp), tag, network))
            out[set_name] = res
            for label, r in res.items():
                if isinstance(r, dict):
                    print(f"  {set_name[:24]:24s} {label:58s} R@100P {r['r_at_100p']:.3f} (TP {r['tp']} "
                          f"FP {r['fp']} of {r['positives']}) {r['ms_per_frame']} ms/frame", flush=True)
    return out


def bench_viewpoint(network: bool) -> dict[str, Any]:
    """The nearest-viewpoint walk's settings (``query.viewpoint_*``) around the default's, on the
    corridor and the two revisit sets (exact cell): is the figure a plateau or a peak?"""
    dev = SHARED / "camvid_revisit_dev"
    sets = {"corridor": open_dataset(SHARED / "corridor", format="vprbench")}
    sets.update({name: open_dataset(dev / name / "frames", format="folder") for name in REVISITS})
    truth = {"corridor": sets["corridor"].ground_truth()}
    truth.update({name: load_ground_truth(dev / name / "gt.png") for name in REVISITS})
    grid: dict[str, dict[str, Any]] = {"no walk (viewpoint_steps 0)": {"viewpoint_steps": 0}}
    for scale in (0.10, 0.15, 0.20):
        for margin in (0.03, 0.05, 0.08):
            grid[f"start {scale:.2f}, margin {margin:.2f}"] = {"viewpoint_scale": scale,
                                                               "viewpoint_margin": margin}
    grid["start 0.15, margin 0.05, inlier floor 0.5"] = {"viewpoint_inliers": 0.5}
    grid["start 0.15, margin 0.05, no inlier floor"] = {"viewpoint_inliers": 0.0}
    grid["start 0.15, margin 0.05, 6 steps"] = {"viewpoint_steps": 6}
    out: dict[str, Any] = {"protocol": "exact cell, no exclusion window (as the revisits section)",
                           "default": {k: v for k, v in vars(preset("default").query).items()
                                       if k.startswith("viewpoint")}}
    with tempfile.TemporaryDirectory() as tmp:
        for label, over in grid.items():
            row = {}
            for name, ds in sets.items():
                cfg = preset("default" if network else "fast", {"query": over})
                row[name] = _run_eval(ds, truth[name], cfg, Path(tmp), f"{name}_{label}")
            out[label] = row
            print(f"  {label:44s} " + "  ".join(f"{n} {r['r_at_100p']:.3f} ({r['tp']}/{r['fp']})"
                                                for n, r in row.items()), flush=True)
    return out


def bench_speed(rounds: int = 3) -> dict[str, Any]:
    """Milliseconds per 480x360 frame on ONE thread (OpenCV and onnxruntime), the CamVid revisit
    frames of ``train_drives``: the default, with monocular triangulation, with the network (T = 1).

    The variants run in lockstep, frame by frame (every variant processes frame i before any
    processes frame i + 1): a shared machine's speed drifts by a quarter within a minute, and
    this way every variant meets the same drift. That is repeated ``rounds`` times; each figure
    is the median over the rounds of the round's statistic, with every round's mean beside it."""
    from stablecues.semantics.inference import SegmentationModel

    cv2.setNumThreads(1)
    ds = open_dataset(SHARED / "camvid_revisit_dev" / "train_drives" / "frames", format="folder")
    frames = [ds[i] for i in range(len(ds))]
    out: dict[str, Any] = {"frames": len(frames), "threads": 1, "rounds": rounds,
                           "load_before": list(os.getloadavg())}
    models = ({p: SegmentationModel.load(threads=1, precision=p) for p in ("float32", "int8")}
              if network_available() else {})
    variants: dict[str, tuple[str, dict[str, Any]]] = {
        "default (network T = 1, int8)": ("default", {}),
        "default with the float32 network": ("default", {"segmentation_precision": "float32"}),
        "fast (the default without the network)": ("fast", {}),
        "fast + monocular triangulation": ("fast", {"monocular": {}}),
        "fast, 1 island verified (what 5 cost)": ("fast", {"query": {"islands_verified": 1}}),
        "fast, no nearest-viewpoint walk (what it costs)": ("fast", {"query": {"viewpoint_steps": 0}}),
        "bow (DBoW2 + fundamental)": ("bow", {}),
    }
    per_round: dict[str, list[dict[str, float]]] = {}
    for _ in range(rounds):
        detectors: dict[str, LoopDetector] = {}
        for label, (name, over) in variants.items():
            cfg = preset(name, {"similarity": False, **over})
            model = models.get(cfg.segmentation_precision)
            if needs_segmentation(cfg) and model is None:
                continue
            seg = (lambda image, m=model: m.predict(image, 1)) if model is not None else None  # noqa: E731
            detectors[label] = LoopDetector(cfg, segmenter=seg)
        times: dict[str, list[float]] = {label: [] for label in detectors}
        for f in frames:
            for label, det in detectors.items():
                times[label].append(det.process(f).timings["total"])
        for label, det in detectors.items():
            det.close()
            totals = times[label]
            per_round.setdefault(label, []).append(
                {"mean_ms": float(np.mean(totals)), "median_ms": float(np.median(totals)),
                 "p90_ms": float(np.percentile(totals, 90))})
    for label, runs in per_round.items():
        out[label] = {k: round(float(np.median([r[k] for r in runs])), 2) for k in runs[0]}
        out[label]["round_means_ms"] = [round(r["mean_ms"], 2) for r in runs]
        print(f"  {label:48s} mean {out[label]['mean_ms']:.1f} ms, median {out[label]['median_ms']:.1f} ms, "
              f"p90 {out[label]['p90_ms']:.1f} ms per frame (round means {out[label]['round_means_ms']})",
              flush=True)
    out["load_after"] = list(os.getloadavg())
    return out


# ---------------------------------------------------------------------------------- SIFT vs ORB
SIFT_SETS = ("corridor", "train_drives", "val_drive")


def _run_with_vocabulary(ds: Any, gt: Any, cfg: Any, vocabulary: Any, score: str) -> dict[str, Any]:
    """The detector over ``ds`` with a given vocabulary (``run_dataset`` takes the shipped ORB
    one), scored as ``_run_eval`` scores a run: exact cell, no exclusion, accepted detections."""
    det = LoopDetector(cfg, vocabulary=vocabulary)
    queries, cands, scores, totals, features = [], [], [], [], []
    for i in range(len(ds)):
        d = det.process(ds[i])
        queries.append(i)
        cands.append(d.candidate_frame if d.accepted else -1)
        value = d.confidence if score == "score" else d.raw_score
        scores.append(value if d.candidate >= 0 else float("nan"))
        totals.append(d.timings["total"])
        features.append(d.n_features)
    det.close()
    ev = evaluate_detections(gt.matrix, np.array(queries), np.array(cands), np.array(scores),
                             protocol="exact", query_mask=gt.query_mask)
    return {"r_at_100p": round(ev.recall_at_100p, 4), "tp": ev.tp, "fp": ev.fp, "positives": ev.positives,
            "tp_at_100p": ev.tp_at_100p, "ms_per_frame": round(float(np.mean(totals)), 2),
            "features_per_frame": round(float(np.mean(features)), 1)}


def bench_sift() -> dict[str, Any]:
    """SIFT (the shipped float vocabulary) against ORB (the shipped binary one) on the corridor
    and the CamVid revisit development sets: the whole ``fast`` preset (verification matches
    float descriptors by their unit-normalised L2 distance), and the BoW stages alone (preset
    bow-nogeom, and the DBoW2 top-1 raw-score sweep)."""
    from stablecues.vocabulary import default_vocabulary, default_vocabulary_path

    dev = SHARED / "camvid_revisit_dev"
    out: dict[str, Any] = {
        "load_before": list(os.getloadavg()),
        "vocabularies": {f: {"file": default_vocabulary_path(f).name, "words": default_vocabulary(f).n_words,
                             "descriptors": str(default_vocabulary(f).descriptor_kind)}
                         for f in ("orb", "sift")},
        "protocol": "exact cell, no exclusion window (as the revisits section)",
        "timing": "ms per frame of the whole detector (features, BoW, query), OpenCV threads as "
                  "configured, a shared 2-core machine: see the load averages",
    }
    for set_name in SIFT_SETS:
        if set_name == "corridor":
            ds = open_dataset(SHARED / "corridor", format="vprbench")
            gt = ds.ground_truth()
        else:
            ds = open_dataset(dev / set_name / "frames", format="folder")
            gt = load_ground_truth(dev / set_name / "gt.png")
        res: dict[str, Any] = {"frames": len(ds), "gt_file": str(gt.path)}
        for features in ("orb", "sift"):
            voc = default_vocabulary(features)
            feats = {"features": {"name": features}}
            for label, cfg, score in (
                ("fast", preset("fast", {**feats, "similarity": False}), "score"),
                ("bow-nogeom", preset("bow-nogeom", {**feats, "similarity": False}), "score"),
                ("dbow2 top-1, raw score swept", preset("bow-nogeom", {**TOP1, **feats}), "raw_score"),
            ):
                r = res[f"{features} {label}"] = _run_with_vocabulary(ds, gt, cfg, voc, score)
                print(f"  {set_name:14s} {features:4s} {label:30s} R@100P {r['r_at_100p']:.3f} (TP {r['tp']} "
                      f"FP {r['fp']} of {r['positives']}) {r['ms_per_frame']} ms/frame, "
                      f"{r['features_per_frame']} features", flush=True)
        out[set_name] = res
    out["load_after"] = list(os.getloadavg())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "loops.json")
    ap.add_argument("--quick", action="store_true", help="main presets only, no ablations")
    ap.add_argument("--sections", default="speed,revisits,corridor,camvid,desk,euroc",
                    help="comma-separated sections to run (default: all)")
    args = ap.parse_args()
    if not SHARED.exists():
        sys.exit(f"{SHARED} is absent: this benchmark needs the real data")
    network = network_available()
    names = MAIN_PRESETS + ([] if args.quick else ABLATIONS)
    runnable = [n for n in names if network or not uses_masking(n)]
    results: dict[str, Any] = {
        "presets": {n: describe_preset(n) for n in names},
        "network_weights": network,
        "note": "masking presets without network weights run on camvid with its ground-truth labels only",
    }
    sections = set(args.sections.split(","))
    if "speed" in sections:
        print("speed, one thread, 480x360:", flush=True)
        results["speed"] = bench_speed()
    if "revisits" in sections:
        print("camvid revisits (development sets) and corridor, exact cell:", flush=True)
        results["revisits"] = bench_revisits(network)
    if "corridor" in sections:
        with tempfile.TemporaryDirectory() as tmp:
            print("corridor (two-pass, indoor):", flush=True)
            results["corridor"] = bench_corridor(runnable, Path(tmp))
    if "camvid" in sections:
        print("camvid/test retrieval:", flush=True)
        results["camvid"] = bench_camvid(names, network)
    if "desk" in sections:
        print("desk_loop10:", flush=True)
        results["desk_loop10"] = bench_desk(runnable)
    if "euroc" in sections:
        print("euroc/loop_pairs:", flush=True)
        results["euroc_pairs"] = bench_euroc(runnable)
    if "viewpoint" in sections:
        print("nearest-viewpoint walk, settings around the default's, exact cell:", flush=True)
        results["viewpoint"] = bench_viewpoint(network)
    if "sift" in sections:
        print("SIFT vs ORB (shipped vocabularies), corridor and camvid revisits, exact cell:", flush=True)
        results["sift"] = bench_sift()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.out.is_file():  # the sections not run this time keep their figures
        results = {**json.loads(args.out.read_text()), **results}
    args.out.write_text(json.dumps(results, indent=2, default=str) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
