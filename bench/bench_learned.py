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
  with ``bench_loops.py``'s corridor protocols (exact / tolerance 2 / iBoW-LCD 2, exclusion 20).

For every run: time per frame by stage (the run folder's per-frame stage times: extract, segment,
mask, transform, lift, query, verify, add, total, whatever the detector records), as the mean
milliseconds per frame over all frames but the first (the first one loads the network, the
vocabulary's compiled code, ...); a stage that did not run for a frame counts 0 there, so the
stages add up to the total; ``when_run_ms`` gives the mean over the frames where it ran.

Run::

    python bench/bench_learned.py                                   # default,fast,bow, all sections
    python bench/bench_learned.py --presets learned --sections gardens
    python bench/bench_learned.py --presets fast --config 'xfeat-fast=fast:{"features":{"name":"xfeat"}}'
    python bench/bench_learned.py --quick 20 --sections gardens     # first 20 query places only

Prints tables and writes ``bench/results/learned.json`` (``--quick``: ``learned_quick.json``),
merged into the file already there: a run replaces the figures of the sets and configurations it
ran and keeps the others. About 4-5 minutes on 2 cores for default, fast and bow over all sections.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench_loops import PROTOCOLS, REVISITS, SHARED, _run_eval, needs_segmentation, network_available
from stablecues.datasets import open_dataset
from stablecues.detection import describe_preset, preset, preset_names
from stablecues.errors import ConfigError, ModelError
from stablecues.evaluation import evaluate_run, load_run
from stablecues.evaluation.funnel import loss_funnel
from stablecues.groundtruth import GroundTruth, load_ground_truth

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


def score(run: Any, gt: GroundTruth, places: int | None) -> dict[str, Any]:
    """A run scored as ``_run_eval`` scores one (exact cell, no exclusion, its loss funnel)."""
    ev, _ = evaluate_run(run, gt, protocol="exact", tolerance=0, exclude=0)
    funnel = loss_funnel(run, gt.matrix, ev, query_mask=gt.query_mask)
    return {"r_at_100p": round(ev.recall_at_100p, 4), "queries_with_loop": ev.positives,
            "tp_at_100p": ev.tp_at_100p, "threshold_at_100p": ev.threshold_at_100p,
            "tp": ev.tp, "fp": ev.fp, "auc": round(ev.auc, 4),
            "candidate_correct": candidates_correct(run, gt), "funnel": funnel.counts,
            "top_false_positives": false_positives(run, ev, gt, places)}


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
        for proto, tol in PROTOCOLS:
            ev, _ = evaluate_run(run, gts[first], protocol=proto, tolerance=tol, exclude=20)
            out["protocols_exclude_20"][proto] = {"tolerance": tol, "r_at_100p": round(ev.recall_at_100p, 4),
                                                  "tp": ev.tp, "fp": ev.fp, "positives": ev.positives}
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
        folder = gardens_sequence(ref, qry, work / f"gardens_{ref}_{qry}")
        ds, gts = limit(open_dataset(folder, format="folder"), truth, quick)
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


SECTIONS = {"gardens": bench_gardens, "revisits": bench_revisits, "corridor": bench_corridor}


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
                    help="comma-separated: gardens,revisits,corridor (default: all)")
    ap.add_argument("--quick", type=int, metavar="N", help="only the first N query places of each set")
    ap.add_argument("--out", type=Path, help="results file (default bench/results/learned.json, "
                                             "learned_quick.json with --quick)")
    args = ap.parse_args()
    if not SHARED.exists():
        sys.exit(f"{SHARED} is absent: this benchmark needs the real data")
    sections = [s for s in args.sections.split(",") if s]
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        sys.exit(f"unknown section(s) {', '.join(unknown)}; known: {', '.join(SECTIONS)}")
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
            results[section] = SECTIONS[section](configs, Path(tmp), network, args.quick)
            walls[section] = round(time.perf_counter() - t, 1)
    results["last_run"] = {"sections": sections, "configs": list(configs), "quick": args.quick,
                           "wall_s": round(time.perf_counter() - t0, 1), "section_wall_s": walls,
                           "load_before": load_before,
                           "load_after": list(os.getloadavg())}
    out_path.parent.mkdir(parents=True, exist_ok=True)
    if out_path.is_file():  # the sets and configurations not run this time keep their figures
        results = merge(json.loads(out_path.read_text()), results, depth=2)
    out_path.write_text(json.dumps(results, indent=2, default=str) + "\n")
    print(f"written {out_path} in {results['last_run']['wall_s']:.0f} s")


if __name__ == "__main__":
    main()
