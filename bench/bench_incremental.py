"""The incremental vocabulary (issue 37) against the trained one: accuracy on every development
set, the settings it was chosen with, and its costs as a map grows.

Sections (``--sections``, all by default):

``grid``
    The merge threshold and the word index (hash tables x bits) on four development sets
    (train_drives, the corridor, Gardens Point day_left -> day_right and day_right -> night_right),
    ORB with ``fast`` and XFeat with ``learned``: R@100P, words after the run, ms per frame. The
    defaults (``stablecues.vocabulary.incremental.DEFAULTS``) are the settings that did best over
    all four, not on one.
``sets``
    Every development set (the three Gardens Point pairings, both CamVid revisit sets, the
    corridor, desk_loop10, the EuRoC loop pairs) with ``fast``, ``default`` and ``learned``, each
    with its trained vocabulary and with ``vocabulary: incremental``: R@100P, the loss funnel,
    words after the run, ms per frame by stage.
``scale``
    Add and query milliseconds per frame at 10^3, 10^4 and 10^5 entries (the 200 frames before
    each; the map is built without queries in between), trained against incremental, on one
    core: a robot patrolling a world of real ORB frames (CamVid train + val, 468 frames; each lap
    flips 8 random bits of every descriptor: a place seen again, not the same pixels), and an
    exploring one (each lap a new world: every descriptor of the lap XORed with a mask of 96
    bits, so nothing of the earlier laps matches) up to 10^4 (``--scale-walks`` picks them).
    Words made and live, the vocabulary's memory, bytes of the words file per entry, and the
    time to read the words back (restore and index rebuild) at the largest size. Maps in memory
    without descriptors (the map's own costs are ``bench_scale.py``'s): what is measured is
    what the vocabulary adds.
``index``
    The map's inverted index alone: an add of 900 random words at the trained vocabulary's
    96,618 words against the incremental id space of 2^22 (what the id space costs the index).

Writes ``bench/results/incremental.json`` (sections not run keep their figures).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench_learned import GARDENS, PAIRINGS, PLACES, WINDOWS, gardens_dataset, merge
from bench_loops import REVISITS, SHARED, bench_desk, bench_euroc, needs_segmentation, network_available
from stablecues.database import Database, DatabaseConfig
from stablecues.datasets import open_dataset
from stablecues.detection import preset
from stablecues.detection.run import run_dataset
from stablecues.errors import ModelError
from stablecues.evaluation import evaluate_run, load_run
from stablecues.evaluation.funnel import loss_funnel
from stablecues.features import make_extractor
from stablecues.groundtruth import GroundTruth, load_ground_truth
from stablecues.imageio import read_image
from stablecues.types import DescriptorKind, Features
from stablecues.vocabulary import default_vocabulary
from stablecues.vocabulary.incremental import IncrementalVocabulary

HERE = Path(__file__).resolve().parent
PRESETS = ("fast", "default", "learned")
GRID_SETS = ("train_drives", "corridor", "day_left->day_right", "day_right->night_right")
GRID = {  # preset -> (thresholds, (tables, bits) pairs, sets)
    "fast": ((56, 64, 72), ((4, 16), (8, 16), (16, 12)), GRID_SETS),
    # learned descriptors are for the changes of light: both night pairings
    "learned": ((0.6, 0.7, 0.8), ((16, 12),), ("train_drives", "corridor", "day_right->night_right",
                                               "day_left->night_right")),
}
GRID_PRESETS = list(GRID)  # --grid-presets
SETS_PRESETS = list(PRESETS)  # --sets-presets
SCALE_SIZES = (1_000, 10_000, 100_000)
# entries timed before each size (half the size at most): several rebuilds of the word index
# fall in it at every size (one every 200-300 adds at 10^5), so its mean is the amortised cost
SCALE_WINDOW = 1000
FLIP_BITS = 8  # bits flipped per descriptor per patrol lap
WORLD_MASK_BITS = 96  # bits of each exploring lap's mask


# ---------------------------------------------------------------------------------- data
def load_sets() -> dict[str, tuple[Any, dict[str, GroundTruth]]]:
    """name -> (dataset, ground truths, the first scored): every sequence set."""
    out: dict[str, tuple[Any, dict[str, GroundTruth]]] = {}
    work = Path(tempfile.mkdtemp(prefix="bench_incremental_"))
    truth = {w: load_ground_truth(GARDENS / f) for w, f in WINDOWS.items()}
    for pairing, (ref, qry) in PAIRINGS.items():
        out[pairing] = (gardens_dataset(ref, qry, work / f"gardens_{ref}_{qry}"), truth)
    dev = SHARED / "camvid_revisit_dev"
    for name in REVISITS:
        out[name] = (open_dataset(dev / name / "frames", format="folder"),
                     {"exact": load_ground_truth(dev / name / "gt.png")})
    corridor = open_dataset(SHARED / "corridor", format="vprbench")
    out["corridor"] = (corridor, {"exact": corridor.ground_truth()})
    return out


# ---------------------------------------------------------------------------------- one run
def run_one(ds: Any, gts: dict[str, GroundTruth], name: str, over: dict[str, Any],
            vocabulary: Any, work: Path, folder: str) -> dict[str, Any]:
    """One configuration over one set: R@100P on every ground truth, the funnel of the first,
    words after the run, ms per frame by stage (all frames but the first)."""
    cfg = preset(name, over)
    run_dir = work / folder
    shutil.rmtree(run_dir, ignore_errors=True)
    t = time.perf_counter()
    try:
        summary = run_dataset(ds, cfg, run_dir, preset_name=name, progress=False, pictures=0,
                              vocabulary=vocabulary)
    except ModelError as exc:
        return {"skipped": str(exc)}
    wall = time.perf_counter() - t
    run = load_run(run_dir)
    out: dict[str, Any] = {"ms_per_frame": round(summary.ms_per_frame, 2), "wall_s": round(wall, 1)}
    timings = json.loads((run_dir / "timings.json").read_text())
    out["stages_ms"] = {k: round(v["mean"], 2) for k, v in timings.items()
                        if isinstance(v, dict) and v.get("mean") is not None}
    for i, (key, gt) in enumerate(gts.items()):
        ev, _ = evaluate_run(run, gt, protocol="exact", tolerance=0, exclude=0)
        res = {"r_at_100p": round(ev.recall_at_100p, 4), "tp_at_100p": ev.tp_at_100p, "tp": ev.tp,
               "fp": ev.fp, "queries_with_loop": ev.positives}
        if i == 0:
            res["funnel"] = loss_funnel(run, gt.matrix, ev, query_mask=gt.query_mask).counts
        out[key] = res
    voc = vocabulary
    if voc is None and cfg.vocabulary == "incremental":  # made by the detector: read back from the map
        voc = _reopened_words(run_dir, cfg)
    if isinstance(voc, IncrementalVocabulary):
        out["words_live"], out["words_made"] = voc.words_live, voc.words_made
    else:
        out["words_live"] = default_vocabulary(cfg.features.name).n_words
    shutil.rmtree(run_dir, ignore_errors=True)
    return out


def _reopened_words(run_dir: Path, cfg: Any) -> IncrementalVocabulary:
    kind = make_extractor(cfg.features).descriptor_kind
    voc = IncrementalVocabulary(kind, threshold=cfg.incremental_threshold)
    with Database(voc, run_dir / "map.sqlite", readonly=True):
        pass
    return voc


def line(set_name: str, label: str, r: dict[str, Any]) -> None:
    if "skipped" in r:
        print(f"  {set_name:24s} {label:28s} skipped: {r['skipped'][:80]}", flush=True)
        return
    first = first_figures(r)
    print(f"  {set_name:24s} {label:28s} R@100P {first['r_at_100p']:.3f} "
          f"(TP {first['tp']} FP {first['fp']})  words {r['words_live']:>8}  "
          f"{r['ms_per_frame']:6.1f} ms/frame", flush=True)


def first_figures(r: dict[str, Any]) -> dict[str, Any]:
    """A run's figures on its first ground truth."""
    return next(v for v in r.values() if isinstance(v, dict) and "r_at_100p" in v)


def kind_of(name: str) -> DescriptorKind:
    return make_extractor(preset(name).features).descriptor_kind


# ---------------------------------------------------------------------------------- sections
def bench_grid(work: Path, network: bool) -> dict[str, Any]:
    sets = load_sets()
    out: dict[str, Any] = {"sets": {name: list(spec[2]) for name, spec in GRID.items()}}
    for name, (thresholds, indexes, grid_sets) in GRID.items():
        if name not in GRID_PRESETS:
            continue
        if needs_segmentation(preset(name)) and not network:
            out[name] = {"skipped": "needs the segmentation network"}
            continue
        res: dict[str, Any] = {}
        kind = kind_of(name)
        for thr in thresholds:
            for tables, bits in indexes:
                label = f"t{thr:g}_{tables}x{bits}"
                per: dict[str, Any] = {}
                for set_name in grid_sets:
                    ds, gts = sets[set_name]
                    voc = IncrementalVocabulary(kind, threshold=thr, tables=tables, bits=bits)
                    per[set_name] = run_one(ds, gts, name, {}, voc, work, f"grid_{name}_{label}")
                    line(set_name, f"{name} {label}", per[set_name])
                figures = [first_figures(r)["r_at_100p"] for r in per.values() if "skipped" not in r]
                res[label] = {"threshold": thr, "tables": tables, "bits": bits, "sets": per,
                              "mean_r_at_100p": round(float(np.mean(figures)), 4) if figures else None,
                              "min_r_at_100p": round(float(np.min(figures)), 4) if figures else None}
                print(f"  {name} {label}: mean R@100P {res[label]['mean_r_at_100p']}", flush=True)
        out[name] = res
    return out


def bench_sets(work: Path, network: bool) -> dict[str, Any]:
    sets = load_sets()
    out: dict[str, Any] = {}
    for set_name, (ds, gts) in sets.items():
        res: dict[str, Any] = {"frames": len(ds)}
        for name in SETS_PRESETS:
            for vocab in ("trained", "incremental"):
                label = f"{name} {vocab}"
                if needs_segmentation(preset(name)) and not network:
                    res[label] = {"skipped": "needs the segmentation network"}
                    continue
                res[label] = run_one(ds, gts, name, {"vocabulary": vocab}, None, work,
                                     f"sets_{name}_{vocab}")
                line(set_name, label, res[label])
        out[set_name] = res
    small: dict[str, Any] = {}
    names = [n for n in SETS_PRESETS if network or not needs_segmentation(preset(n))]
    for vocab in ("trained", "incremental"):
        small[vocab] = {"desk_loop10": bench_desk(names, {"vocabulary": vocab}),
                        "euroc_pairs": bench_euroc(names, {"vocabulary": vocab})}
    out["small"] = small
    return out


def _pool() -> list[Features]:
    """ORB features of CamVid train + val, in order (the patrol's world)."""
    ex = make_extractor("orb")
    files = [f for split in ("train", "val") for f in sorted((SHARED / "camvid" / split).glob("*.jpg"))]
    return [ex.extract(read_image(f, "grey")) for f in files]


def _flip(d: np.ndarray, bits: int, rng: np.random.Generator) -> np.ndarray:
    """``d`` with ``bits`` random bits of every row flipped."""
    n = d.shape[0]
    pos = rng.integers(0, 256, (n, bits))
    while True:  # distinct positions in every row: rows that drew one twice draw again
        s = np.sort(pos, axis=1)
        again = np.flatnonzero((s[:, 1:] == s[:, :-1]).any(axis=1))
        if not again.size:
            break
        pos[again] = rng.integers(0, 256, (again.size, bits))
    mask = np.zeros((n, 256), np.uint8)
    np.put_along_axis(mask, pos, 1, axis=1)
    return d ^ np.packbits(mask, axis=1, bitorder="little")


def _trajectory(pool: list[Features], n: int, explore: bool, seed: int = 0) -> Any:
    """Entry i: pool frame i mod len(pool), lap i // len(pool); patrol: FLIP_BITS new bits flipped
    each lap; explore: each lap XORed with a mask of WORLD_MASK_BITS bits of its own."""
    rng = np.random.default_rng(seed)
    mask = np.zeros(32, np.uint8)
    for i in range(n):
        lap, k = divmod(i, len(pool))
        if k == 0 and explore and lap:
            m = np.zeros(256, np.uint8)
            m[rng.choice(256, WORLD_MASK_BITS, replace=False)] = 1
            mask = np.packbits(m, bitorder="little")
        f = pool[k]
        if explore:
            d = f.descriptors ^ mask
        else:
            d = _flip(f.descriptors, FLIP_BITS, rng) if lap else f.descriptors
        yield dataclasses.replace(f, descriptors=np.ascontiguousarray(d))


def _time_growth(pool: list[Features], sizes: tuple[int, ...], explore: bool, incremental: bool,
                 work: Path) -> dict[str, Any]:
    kind = DescriptorKind("binary", 32)
    voc: Any = IncrementalVocabulary(kind) if incremental else default_vocabulary("orb")
    db = Database(voc, config=DatabaseConfig(store_descriptors=False))
    last = max(sizes)
    windows = {s: (s - min(SCALE_WINDOW, s // 2), s) for s in sizes}
    add: dict[int, list[float]] = {s: [] for s in sizes}
    query: dict[int, list[float]] = {s: [] for s in sizes}
    out: dict[str, Any] = {}
    rebuilds: list[tuple[float, int]] = []  # ms and page faults of each rebuild of the word index
    if incremental:
        compact = voc._compact

        def timed_compact() -> None:
            f = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            t = time.perf_counter()
            compact()
            ms = (time.perf_counter() - t) * 1e3
            rebuilds.append((ms, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f))

        voc._compact = timed_compact
    t_all = time.perf_counter()
    for i, feats in enumerate(_trajectory(pool, last, explore)):
        timed = [s for s, (a, b) in windows.items() if a <= i < b]
        if not timed:  # only what building the map needs: the queries are timed in the windows
            bow, fv = (voc.learn if incremental else voc.transform)(feats.descriptors)
            db.add(bow, fv, feats)
            continue
        t = time.perf_counter()
        bow, fv = voc.transform(feats.descriptors)
        if len(db):
            db.query(bow, max_results=50)
        tq = time.perf_counter()
        if incremental:
            bow, fv = voc.learn(feats.descriptors)
        db.add(bow, fv, feats)
        ta = time.perf_counter()
        for s in timed:
            query[s].append((tq - t) * 1e3)
            add[s].append((ta - tq) * 1e3)
        if i + 1 in sizes:
            out[str(i + 1)] = {
                "query_ms": _stats(query[i + 1]), "add_ms": _stats(add[i + 1]),
                "words_live": voc.words_live if incremental else voc.n_words,
                "wall_s": round(time.perf_counter() - t_all, 1)}
            if incremental:
                out[str(i + 1)]["index_rebuilds"] = {"so_far": len(rebuilds),
                                                     "last_ms": [round(x, 1) for x, _ in rebuilds[-5:]],
                                                     "last_page_faults": [f for _, f in rebuilds[-5:]]}
                out[str(i + 1)]["words_made"] = voc.words_made
                out[str(i + 1)]["vocabulary_mb"] = round(voc.nbytes / 2**20, 1)
            got = out[str(i + 1)]
            who = f"{'incremental' if incremental else 'trained':11s} {'explore' if explore else 'patrol':7s}"
            print(f"    {who} {i + 1:>7} entries: query {got['query_ms']['mean']:.2f} ms, add "
                  f"{got['add_ms']['mean']:.2f} ms (p99 {got['add_ms']['p99']:.2f}), "
                  f"words {got['words_live']}", flush=True)
    if incremental:
        path = work / "scale.words"
        uuid = bytes(16)
        t = time.perf_counter()
        voc.save(path, uuid)
        save_s = time.perf_counter() - t
        again = IncrementalVocabulary(kind)
        t = time.perf_counter()
        again.restore(path, uuid)
        out["words_file"] = {"entries": last, "bytes": path.stat().st_size,
                             "bytes_per_entry": round(path.stat().st_size / last, 1),
                             "save_s": round(save_s, 3), "restore_s": round(time.perf_counter() - t, 3),
                             "same_words": again.words_live == voc.words_live}
        print(f"    words file at {last} entries: {out['words_file']}", flush=True)
        path.unlink()
    db.close()
    return out


def _stats(values: list[float]) -> dict[str, float]:
    a = np.asarray(values)
    return {"mean": round(float(a.mean()), 3), "p50": round(float(np.median(a)), 3),
            "p99": round(float(np.percentile(a, 99)), 3), "max": round(float(a.max()), 3), "n": int(a.size)}


def bench_scale(work: Path, network: bool, sizes: tuple[int, ...] = SCALE_SIZES,
                walks: tuple[str, ...] = ("patrol", "explore")) -> dict[str, Any]:
    del network
    pool = _pool()
    out: dict[str, Any] = {
        "pool": f"ORB 1000 of CamVid train + val ({len(pool)} frames)", "window": SCALE_WINDOW,
        "flip_bits": FLIP_BITS, "world_mask_bits": WORLD_MASK_BITS, "database": "memory, no descriptors",
        "query": "transform + top-50 query", "add": "learn (incremental) + add",
        "load_before": list(os.getloadavg())}
    for explore, top in ((False, max(sizes)), (True, min(max(sizes), 10_000))):
        part = tuple(s for s in sizes if s <= top)
        key = "explore" if explore else "patrol"
        if key not in walks:
            continue
        out[key] = {v: _time_growth(pool, part, explore, v == "incremental", work)
                    for v in ("trained", "incremental")}
    out["load_after"] = list(os.getloadavg())
    return out


def bench_index(work: Path, network: bool, n: int = 20_000) -> dict[str, Any]:
    """The map's inverted index alone, adding ``n`` entries of 900 words drawn at random (memory,
    inline maintenance, one core): the trained vocabulary's 96,618 words against the
    incremental one's id space of 2^22, with the words used spanning 96,618 ids or all of them
    (ids given again after they ran out). What an add costs the index whatever the vocabulary."""
    del work, network
    from stablecues.database import InvertedIndex
    from stablecues.vocabulary import Scoring

    out: dict[str, Any] = {"entries": n, "words_per_entry": 900, "timed": "entries 500 .. n"}
    for label, n_words, span in (("96618_words", 96_618, 96_618), ("2^22_ids_span_96618", 1 << 22, 96_618),
                                 ("2^22_ids_span_all", 1 << 22, 1 << 22)):
        rng = np.random.default_rng(0)
        index = InvertedIndex(n_words, Scoring.L1)
        times = []
        for _ in range(n):
            words = np.unique(rng.integers(0, span, 900)).astype(np.int32)
            weights = rng.random(words.shape[0]).astype(np.float32)
            t = time.perf_counter()
            index.add(words, weights)
            times.append((time.perf_counter() - t) * 1e3)
        out[label] = _stats(times[500:])
        print(f"    {label:22s} add {out[label]['mean']:.3f} ms (p99 {out[label]['p99']:.2f}, "
              f"max {out[label]['max']:.1f})", flush=True)
    return out


SECTIONS = {"grid": bench_grid, "sets": bench_sets, "scale": bench_scale, "index": bench_index}
_GRID_LINE = re.compile(r"^\s+(\S+)\s+(\w+) t([0-9.]+)_(\d+)x(\d+)\s+R@100P ([0-9.]+) \(TP (\d+) FP (\d+)\)"
                        r"\s+words\s+(\d+)\s+([0-9.]+) ms/frame")


def grid_from_log(path: Path) -> dict[str, Any]:
    """The ``grid`` section from the lines a run of it printed (a run stopped before it wrote its
    results: what it printed is what it measured)."""
    out: dict[str, Any] = {"from_log": str(path.name), "sets": {"fast": list(GRID_SETS)},
                           "note": "the fast grid ran on 2026-12-06 before a descriptor that joins no word "
                                   "became a word of its own (it then first joined a word made by the "
                                   "same image within the threshold); the settings are unchanged"}
    for text in path.read_text().splitlines():
        m = _GRID_LINE.match(text)
        if not m:
            continue
        set_name, name, thr, tables, bits, r, tp, fp, words, ms = m.groups()
        label = f"t{float(thr):g}_{tables}x{bits}"
        entry = out.setdefault(name, {}).setdefault(label, {"threshold": float(thr), "tables": int(tables),
                                                            "bits": int(bits), "sets": {}})
        entry["sets"][set_name] = {"r_at_100p": float(r), "tp": int(tp), "fp": int(fp),
                                   "words_live": int(words), "ms_per_frame": float(ms)}
    for key, configs in out.items():
        if key != "sets" and isinstance(configs, dict):
            for entry in configs.values():
                figures = [v["r_at_100p"] for v in entry["sets"].values()]
                entry["mean_r_at_100p"] = round(float(np.mean(figures)), 4)
                entry["min_r_at_100p"] = round(float(np.min(figures)), 4)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated: {', '.join(SECTIONS)}")
    ap.add_argument("--scale-sizes", default=",".join(map(str, SCALE_SIZES)),
                    help="entries at which the scale section times adds and queries")
    ap.add_argument("--scale-walks", default="patrol,explore", help="the walks the scale section times")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "incremental.json")
    ap.add_argument("--grid-log", type=Path, metavar="LOG",
                    help="take the grid section from what a run of it printed (LOG), then stop")
    ap.add_argument("--grid-presets", default=",".join(GRID), help="the presets the grid section runs")
    ap.add_argument("--sets-presets", default=",".join(PRESETS), help="the presets the sets section runs")
    args = ap.parse_args()
    GRID_PRESETS[:] = [p for p in args.grid_presets.split(",") if p]
    SETS_PRESETS[:] = [p for p in args.sets_presets.split(",") if p]
    if args.grid_log is not None:
        old = json.loads(args.out.read_text()) if args.out.is_file() else {}
        old["grid"] = merge(old.get("grid", {}), grid_from_log(args.grid_log), depth=1)
        args.out.write_text(json.dumps(old, indent=2, default=str) + "\n")
        for name, configs in old["grid"].items():
            if name != "sets" and isinstance(configs, dict):
                for label, entry in configs.items():
                    print(f"  {name} {label}: mean R@100P {entry['mean_r_at_100p']}, "
                          f"min {entry['min_r_at_100p']}")
        return
    if not SHARED.exists():
        sys.exit(f"{SHARED} is absent: this benchmark needs the real data")
    sections = [s for s in args.sections.split(",") if s]
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        sys.exit(f"unknown section(s) {', '.join(unknown)}; known: {', '.join(SECTIONS)}")
    network = network_available()
    results: dict[str, Any] = {"protocol": "exact cell of the ground truth, no exclusion; Gardens Point at "
                                           f"|j - k| <= 8 (pm8) and <= 2 (pm2), {PLACES} places",
                               "machine": "2-core shared VM, one process"}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for section in sections:
            print(f"{section}:", flush=True)
            if section == "scale":
                sizes = tuple(int(s) for s in args.scale_sizes.split(","))
                walks = tuple(w for w in args.scale_walks.split(",") if w)
                results[section] = bench_scale(Path(tmp), network, sizes, walks)
                results[section][f"measured_{'_'.join(walks)}"] = time.strftime("%Y-%m-%d %H:%M")
            else:
                results[section] = SECTIONS[section](Path(tmp), network)
    results["last_run"] = {"sections": sections, "date": time.strftime("%Y-%m-%d %H:%M"),
                           "wall_s": round(time.perf_counter() - t0, 1)}
    if args.out.is_file():
        results = merge(json.loads(args.out.read_text()), results, depth=4)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2, default=str) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
