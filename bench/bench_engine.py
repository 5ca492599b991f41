#!/usr/bin/env python
"""Engine benchmark (issues 2 and 13): vocabulary transform and loading, database add/query at
scale, and the end-to-end per-frame cost on real frames.

Prints the figures and writes ``bench/results/engine.json``. One thread: run it as
``OMP_NUM_THREADS=1 python bench/bench_engine.py`` (the script sets the variable itself too).
``--sections vocabulary`` (or ``database``, ``end_to_end``) runs only those parts; the figures
of the other parts already in the JSON are kept. Every timing is a median over repeats, and the
machine's load average is written beside them (the 2 cores are shared).

Vocabulary figures: the transform of ~1000 ORB descriptors of CamVid test frames with the shipped
vocabulary (compiled and NumPy engines, and the first call of a fresh process with and without
numba's on-disk cache), the shipped vocabulary as ORB-SLAM text (size, load), and a real-size
10^6-word ORBvoc.txt written from the synthetic k=10, L=6 tree (size, load), with the binary
loads beside them.

Scale runs use a synthetic k=10, L=6 (10^6-word) tree whose centres form a real hierarchy
and synthetic descriptors drawn a few bits around its leaves (heavy-tailed word popularity,
consecutive entries sharing half their words); see ``engine_synth.py``. The 100k-entry run
goes to an SQLite file (descriptors and keypoints stored, as a SLAM system would) in a
subprocess so that its peak memory is its own.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import contextlib
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from engine_synth import EntryMaker, synthetic_vocabulary  # noqa: E402
from stablecues.database import Database  # noqa: E402
from stablecues.features import OrbExtractor  # noqa: E402
from stablecues.imageio import read_image  # noqa: E402
from stablecues.types import Features  # noqa: E402
from stablecues.vocabulary import (  # noqa: E402
    Vocabulary,
    default_vocabulary,
    default_vocabulary_path,
    load_vocabulary,
    save_vocabulary,
)

SHARED = HERE.parent.parent / "shared" / "data"


def median_ms(fn, repeat: int) -> float:  # type: ignore[no-untyped-def]
    fn()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times) * 1000)


def fake_features(desc: np.ndarray, rng: np.random.Generator) -> Features:
    n = desc.shape[0]
    return Features(
        keypoints=(rng.random((n, 2)) * [640, 480]).astype(np.float32), descriptors=desc,
        octaves=rng.integers(0, 8, n).astype(np.int16), angles=(rng.random(n) * 360).astype(np.float32),
        responses=rng.random(n).astype(np.float32), sizes=np.full(n, 31, np.float32), image_size=(640, 480),
    )


def build(db: Database, voc: Vocabulary, n: int, seed: int = 1) -> tuple[float, list[np.ndarray]]:
    """Add n synthetic entries; returns the add throughput (entries/s, add only) and some
    descriptor sets kept to query with."""
    maker = EntryMaker(voc, seed=seed)
    rng = np.random.default_rng(seed)
    add_time = 0.0
    kept: list[np.ndarray] = []
    for i in range(n):
        d = maker.next()
        bow, fvec = voc.transform(d)
        feats = fake_features(d, rng)
        t = time.perf_counter()
        db.add(bow, fvec, feats, timestamp=float(i))
        add_time += time.perf_counter() - t
        if i % max(n // 200, 1) == 0:
            kept.append(d)
        if (i + 1) % 10000 == 0:
            print(f"  ... {i + 1} entries", flush=True)
    return n / add_time, kept


def query_ms(db: Database, voc: Vocabulary, kept: list[np.ndarray], repeat: int = 200,
             max_results: int = 10) -> float:
    """Median query time for revisits: stored images seen again with 20 % new words."""
    rng = np.random.default_rng(7)
    bows = []
    for d in kept:
        q = d.copy()
        swap = rng.random(q.shape[0]) < 0.2
        q[swap] = voc.descriptors[rng.choice(voc.word_nodes, int(swap.sum()))]
        bows.append(voc.transform(q)[0])
    times = []
    for i in range(repeat):
        b = bows[i % len(bows)]
        t = time.perf_counter()
        db.query(b, max_results=max_results)
        times.append(time.perf_counter() - t)
    return float(np.median(times) * 1000)


def peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM; ru_maxrss survives exec on Linux and would
    report the parent's peak)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def scale_child(voc_path: str, n: int, db_path: str) -> None:
    """Subprocess body of the 100k run: prints one JSON line."""
    voc = load_vocabulary(voc_path)
    db = Database(voc, db_path)
    t0 = time.perf_counter()
    rate, kept = build(db, voc, n)
    build_s = time.perf_counter() - t0
    q = query_ms(db, voc, kept)
    stats = db.stats()
    db.close()
    del db  # free the first index before measuring the reopened one
    t = time.perf_counter()
    db2 = Database(voc, db_path)
    reopen = time.perf_counter() - t
    q2 = query_ms(db2, voc, kept, repeat=50)
    peak = peak_rss_mb()
    print(json.dumps({
        "entries": n, "add_per_s": rate, "build_s": build_s, "query_ms": q, "query_ms_reopened": q2,
        "reopen_s": reopen, "file_bytes": stats["file_bytes"], "bytes_per_entry": stats["file_bytes"] / n,
        "postings": stats["postings"], "index_bytes": stats["index_bytes"], "peak_rss_mb": peak,
    }))


def real_frames() -> list[Path]:
    for folder in (SHARED / "kitti" / "frames_seq0x", SHARED / "camvid" / "test"):
        files = sorted(p for p in folder.glob("*") if p.suffix.lower() in (".png", ".jpg"))
        if files:
            return files[:100]
    return []


def end_to_end(files: list[Path]) -> dict[str, object]:
    voc = default_vocabulary()
    ex = OrbExtractor()
    db = Database(voc)
    stages: dict[str, list[float]] = {"extract": [], "transform": [], "add": [], "query": []}
    for f in files:
        img = read_image(f, "grey")
        t0 = time.perf_counter()
        feats = ex.extract(img)
        t1 = time.perf_counter()
        bow, fvec = voc.transform(feats.descriptors)
        t2 = time.perf_counter()
        db.query(bow, max_results=10)  # against every earlier frame: the full query cost
        t3 = time.perf_counter()
        db.add(bow, fvec, feats)
        t4 = time.perf_counter()
        for k, v in zip(stages, (t1 - t0, t2 - t1, t4 - t3, t3 - t2), strict=True):
            stages[k].append(v * 1000)
    med = {k: round(float(np.median(v)), 3) for k, v in stages.items()}
    total = float(np.median(np.sum([stages[k] for k in stages], axis=0)))
    return {"frames": len(files), "source": str(files[0].parent.relative_to(SHARED)),
            "image_size": list(read_image(files[0], "grey").shape[::-1]),
            "median_ms": med, "total_median_ms": round(total, 3), "vocabulary": voc.info().n_words}


def load_average() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def camvid_descriptors(count: int = 20) -> tuple[list[np.ndarray], str]:
    """ORB descriptors (at most 1000 each) of ``count`` CamVid test frames spread over the split."""
    files = sorted(p for p in (SHARED / "camvid" / "test").glob("*") if p.suffix.lower() in (".png", ".jpg"))
    if not files:
        rng = np.random.default_rng(0)
        return [rng.integers(0, 256, (1000, 32), dtype=np.uint8)], "1000 random descriptors (no CamVid)"
    ex = OrbExtractor()
    picked = files[:: max(len(files) // count, 1)][:count]
    sets = [ex.extract(read_image(f, "grey")).descriptors[:1000] for f in picked]
    mean = float(np.mean([d.shape[0] for d in sets]))
    return sets, f"ORB descriptors of {len(sets)} CamVid test frames ({mean:.0f} a frame on average)"


def median_over(sets: list[np.ndarray], fn, repeat: int) -> float:  # type: ignore[no-untyped-def]
    """Median over frames of each frame's median time (ms)."""
    return float(np.median([median_ms(lambda d=d: fn(d), repeat) for d in sets]))


FIRST_CALL = """
import json, sys, time
t0 = time.perf_counter()
import numpy as np
from stablecues.vocabulary import default_vocabulary
voc = default_vocabulary()
d = np.load(sys.argv[1])
t1 = time.perf_counter()
voc.transform(d)
t2 = time.perf_counter()
voc.transform(d)
t3 = time.perf_counter()
print(json.dumps({"import_and_load_s": t1 - t0, "first_transform_s": t2 - t1,
                  "second_transform_ms": (t3 - t2) * 1000, "engine": getattr(voc, "engine", "numpy")}))
"""


def first_calls(desc: np.ndarray, tmp: Path) -> dict[str, object]:
    """A fresh process's first transform: numba compiling (empty cache), then loading its cache."""
    np.save(tmp / "d.npy", desc)
    cache = Path(tempfile.mkdtemp(dir=tmp, prefix="numba_cache_"))  # empty: the first run compiles
    out: dict[str, object] = {}
    for label in ("cold_cache", "warm_cache"):
        env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
        run = subprocess.run([sys.executable, "-c", FIRST_CALL, str(tmp / "d.npy")], env=env,
                             check=True, capture_output=True, text=True)
        fig = json.loads(run.stdout.strip().splitlines()[-1])
        out[label] = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in fig.items()}
    return out


def fresh_text_load(path: Path, runs: int = 3) -> float:
    """Median over fresh processes of one text load, the first thing each does after its imports."""
    code = ("import sys, time\nfrom stablecues.vocabulary import load_vocabulary\n"
            "t = time.perf_counter(); load_vocabulary(sys.argv[1]); print(time.perf_counter() - t)")
    times = [float(subprocess.run([sys.executable, "-c", code, str(path)], check=True, capture_output=True,
                                  text=True).stdout.split()[-1]) for _ in range(runs)]
    return round(float(np.median(times)), 4)


def timed_loads(path: Path, repeat: int, **kw: object) -> float:
    """Median seconds to load a vocabulary file."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        load_vocabulary(path, **kw)  # type: ignore[arg-type]
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def vocabulary_section(tmp: Path) -> dict[str, object]:
    """Transform and load figures (issue 13): shipped vocabulary and a 10^6-word ORBvoc.txt."""
    out: dict[str, object] = {"vocabulary_load_average_before": load_average()}
    shipped = default_vocabulary()
    sets, source = camvid_descriptors()
    out["transform_input"] = source
    engines = {}
    for name in ("compiled", "numpy"):
        if not hasattr(shipped, "engine"):  # a version without engines (for before/after runs)
            engines["numpy"] = shipped
            break
        twin = Vocabulary(shipped.k, shipped.levels, shipped.parents, shipped.descriptors,
                          shipped.weights, shipped.weighting, shipped.scoring, shipped.levels_up)
        twin.engine = name
        if twin.engine == name:
            engines[name] = twin
    for name, voc in engines.items():
        key = "transform_ms" if name == next(iter(engines)) else f"transform_ms_{name}"
        out[key] = round(median_over(sets, voc.transform, 100), 4)
        print(f"  transform ({name}): {out[key]} ms", flush=True)
    if "compiled" in engines:
        out["transform_engine"] = "compiled (numba)"
        weights = [np.random.default_rng(0).random(d.shape[0]) for d in sets]
        out["transform_ms_weighted"] = round(float(np.median(
            [median_ms(lambda d=d, w=w: engines["compiled"].transform(d, weights=w), 100)
             for d, w in zip(sets, weights, strict=True)])), 4)
        out["leaves_ms"] = {n: round(median_over(sets, v.leaves_of, 100), 4) for n, v in engines.items()}
        out["transform_first_call"] = first_calls(sets[0], tmp)
    out["transform_ms_default_vocab"] = out["transform_ms"]

    text = tmp / "shipped.txt"
    save_vocabulary(shipped, text)
    out["text_vocab_load_s"] = round(timed_loads(text, 9), 4)
    out["text_vocab_load_s_fresh_process"] = fresh_text_load(text)
    out["text_vocab_mb"] = round(text.stat().st_size / 2**20, 2)
    out["text_vocab_ends_with_newline"] = text.read_bytes()[-1:] == b"\n"
    out["binary_vocab_load_ms"] = {
        "read": round(timed_loads(default_vocabulary_path(), 15) * 1000, 2),
        "mmap": round(timed_loads(default_vocabulary_path(), 15, mmap=True) * 1000, 2),
    }
    print(f"  shipped vocabulary as text: {out['text_vocab_mb']} MB, loads in {out['text_vocab_load_s']} s",
          flush=True)

    print("  building the 10^6-word synthetic vocabulary ...", flush=True)
    voc = synthetic_vocabulary()
    bin_path, txt_path = tmp / "voc1m.scv", tmp / "ORBvoc.txt"
    save_vocabulary(voc, bin_path)
    t = time.perf_counter()
    save_vocabulary(voc, txt_path)
    out["vocab_save_s_text"] = round(time.perf_counter() - t, 2)
    out["vocab_load_s_text"] = round(timed_loads(txt_path, 3), 3)
    out["vocab_load_s_binary"] = round(timed_loads(bin_path, 5), 4)
    out["vocab_load_s_binary_mmap"] = round(timed_loads(bin_path, 5, mmap=True), 4)
    out["vocab_words"] = voc.n_words
    out["vocab_file_mb"] = {"binary": round(bin_path.stat().st_size / 2**20, 1),
                            "text": round(txt_path.stat().st_size / 2**20, 1)}
    out["transform_ms_1m"] = round(median_over(sets, voc.transform, 100), 4)
    print(f"  10^6 words: ORBvoc.txt {txt_path.stat().st_size / 2**20:.1f} MB loads in "
          f"{out['vocab_load_s_text']} s, binary in {out['vocab_load_s_binary']} s; transform "
          f"{out['transform_ms_1m']} ms", flush=True)
    out["vocabulary_load_average_after"] = load_average()
    return out


def database_section(args: argparse.Namespace, tmp: Path) -> dict[str, object]:
    """Database add / query at 10k (memory) and 100k (file, subprocess) entries."""
    results: dict[str, object] = {"database_load_average_before": load_average()}
    voc = synthetic_vocabulary()
    bin_path = tmp / "voc1m_db.scv"
    save_vocabulary(voc, bin_path)
    print(f"building a {args.entries_small}-entry database ...", flush=True)
    db = Database(voc)
    rate, kept = build(db, voc, args.entries_small)
    results["query_ms_10k"] = round(query_ms(db, voc, kept), 3)
    results["add_per_s_10k_memory"] = round(rate, 1)
    results["postings_10k"] = db.stats()["postings"]
    db.close()

    print(f"building a {args.entries_large}-entry database on disk (subprocess) ...", flush=True)
    out = subprocess.run(
        [sys.executable, __file__, "--child", str(bin_path), str(args.entries_large), str(tmp / "big.db")],
        check=True, capture_output=True, text=True,
    )
    big = json.loads(out.stdout.strip().splitlines()[-1])
    results["query_ms_100k"] = round(big["query_ms"], 3)
    results["query_ratio_100k_10k"] = round(big["query_ms"] / results["query_ms_10k"], 2)  # type: ignore[operator]
    results["scale_100k"] = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in big.items()}
    results["database_load_average_after"] = load_average()
    return results


#: a fresh process's time to its first decision: start, imports, detector, the first frame
FIRST_DECISION = r"""
import time
t0 = time.perf_counter()
import json, sys
import cv2
from stablecues import Frame, LoopDetector, preset
image = cv2.imread(sys.argv[1], cv2.IMREAD_GRAYSCALE)
t_import = time.perf_counter()
detector = LoopDetector(preset(sys.argv[2]))
decision = detector.process(Frame(index=0, name="0", timestamp=0.0, image=image))
t_first = time.perf_counter()
second = detector.process(Frame(index=1, name="1", timestamp=0.1, image=image))
t_second = time.perf_counter()
from stablecues.vocabulary.engine import loaded_kernels
print(json.dumps({"imports_s": t_import - t0, "first_frame_s": t_first - t_import,
                  "to_first_decision_s": t_first - t0, "second_frame_ms": (t_second - t_first) * 1e3,
                  "kernels_loaded_after_two_frames": loaded_kernels() is not None}))
"""


def first_decision(runs: int = 5) -> dict[str, object]:
    """Time from process start to the first LoopDecision on a real EuRoC frame, in fresh
    processes (median of ``runs``): with an empty numba cache (the first run after an install:
    the kernels compile in a background thread while the first frames run on NumPy), with a
    warm one, and with ``STABLECUES_COMPILE=wait`` (the kernels loaded before the first frame,
    as before); ``fast`` and the default (its network loads in the first frame). The process
    writes Python's bytecode as an installed package has it (one run first to write it)."""
    frames = sorted((SHARED / "euroc" / "V1_01_micro" / "mav0" / "cam0" / "data").glob("*.png"))
    if not frames:
        return {"skipped": "no EuRoC frame under ../shared/data"}
    image = str(frames[0])
    base = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    subprocess.run([sys.executable, "-c", FIRST_DECISION, image, "fast"], env=base, check=True,
                   capture_output=True)  # bytecode written, as pip install compiles it
    out: dict[str, object] = {"frame": str(frames[0].relative_to(SHARED)), "runs": runs,
                              "load_average": load_average()}
    for name in ("fast", "default"):
        for label, extra in (("cold_cache", {}), ("warm_cache", {}),
                             ("warm_cache_kernels_first", {"STABLECUES_COMPILE": "wait"})):
            figures = []
            for _ in range(runs):
                cache = tempfile.mkdtemp(prefix="numba_cache_") if label == "cold_cache" else None
                env = {**base, **extra, **({"NUMBA_CACHE_DIR": cache} if cache else {})}
                run = subprocess.run([sys.executable, "-c", FIRST_DECISION, image, name], env=env,
                                     check=True, capture_output=True, text=True)
                figures.append(json.loads(run.stdout.strip().splitlines()[-1]))
            row = {key: round(float(np.median([f[key] for f in figures])), 3)
                   for key in ("imports_s", "first_frame_s", "to_first_decision_s", "second_frame_ms")}
            row["to_first_decision_max_s"] = round(max(f["to_first_decision_s"] for f in figures), 3)
            out[f"{name}_{label}"] = row
            print(f"  first decision, {name:7s} {label:26s} {row['to_first_decision_s']:.3f} s "
                  f"(imports {row['imports_s']:.3f}, first frame {row['first_frame_s']:.3f}; "
                  f"second frame {row['second_frame_ms']:.0f} ms)", flush=True)
    return out


def growing_map(tail: int | None = None, repeat: int = 3) -> dict[str, object]:
    """A map queried after every add, as a SLAM system queries while it maps: the 233 CamVid
    test frames (ORB 1000, the shipped vocabulary, top-50 query), and 10,000 synthetic entries
    of the same vocabulary (``engine_synth.py``) queried after every 10th add. Median and p90
    of the queries (all, and the last 50), median and max of the adds; ``tail`` is
    ``DatabaseConfig.tail_postings`` (None: the default). Medians over ``repeat`` runs."""
    from stablecues.database import DatabaseConfig

    voc = default_vocabulary()
    voc.warm_up()
    files = sorted((SHARED / "camvid" / "test").glob("*.jpg"))[:233]  # the peers' run's frames
    orb = OrbExtractor()
    rng = np.random.default_rng(0)
    real = [orb.extract(read_image(f, "8bit-grey")).descriptors for f in files]
    config = DatabaseConfig() if tail is None else DatabaseConfig(tail_postings=tail)
    out: dict[str, object] = {"tail_postings": config.tail_postings, "load_average": load_average()}

    def one(descs: list[np.ndarray], every: int) -> dict[str, float]:
        bows = [voc.transform(d) for d in descs]
        feats = [fake_features(d, rng) for d in descs]
        db = Database(voc, None, config)
        adds, queries = [], []
        for i, (bow, fvec) in enumerate(bows):
            t = time.perf_counter()
            db.add(bow, fvec, feats[i], timestamp=float(i))
            adds.append(time.perf_counter() - t)
            if i % every == 0:
                t = time.perf_counter()
                db.query(bow, max_results=50)
                queries.append(time.perf_counter() - t)
        db.close()
        q, a = np.array(queries) * 1e3, np.array(adds) * 1e3
        return {"query_ms_median": float(np.median(q)), "query_ms_p90": float(np.percentile(q, 90)),
                "query_ms_last50_median": float(np.median(q[-50:])), "add_ms_median": float(np.median(a)),
                "add_ms_mean": float(a.mean()), "add_ms_max": float(a.max())}

    def medians(runs: list[dict[str, float]]) -> dict[str, float]:
        return {k: round(float(np.median([r[k] for r in runs])), 3) for k in runs[0]}

    figures: dict[str, dict[str, float]] = {}
    if real:
        figures["camvid_233_every_add"] = medians([one(real, 1) for _ in range(repeat)])
    maker = EntryMaker(voc, seed=1)
    synth = [maker.next() for _ in range(10_000)]
    figures["synthetic_10k_every_10th_add"] = medians([one(synth, 10) for _ in range(max(1, repeat - 1))])
    for key, r in figures.items():
        print(f"  growing map, tail {config.tail_postings}, {key}: query median {r['query_ms_median']:.3f} "
              f"p90 {r['query_ms_p90']:.3f} last 50 {r['query_ms_last50_median']:.3f} ms; add mean "
              f"{r['add_ms_mean']:.3f} max {r['add_ms_max']:.1f} ms", flush=True)
    out.update(figures)
    return out


def peers_section(tmp: Path, first_decision_figure: dict[str, Any] | None,
                  runs: int = 11) -> dict[str, object]:
    """Issue 38's side-by-side: this engine's figures on the inputs of the peers' run (the first
    233 CamVid test frames, ORB 1000, the shipped vocabulary), on one pinned core, medians over
    ``runs``, printed beside the peers' figures (``peers_reference.json``: quoted from that run,
    the peers being C++ libraries no registry here offers). The inputs are written to
    ``tmp/peers_inputs`` (``--peers-inputs DIR`` keeps them) for a peer's harness to read; the
    first decision is the ``first_decision`` section's (fast, empty numba cache)."""
    with contextlib.suppress(AttributeError, OSError):  # one core, as the peers' run was
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    voc = default_vocabulary()
    voc.warm_up()
    files = sorted((SHARED / "camvid" / "test").glob("*.jpg"))[:233]
    orb = OrbExtractor()
    frames = [orb.extract(read_image(f, "8bit-grey")).descriptors for f in files]
    mean = np.mean([len(d) for d in frames])
    what = (f"{len(frames)} CamVid test frames (sorted, the first 233), ORB {orb.config.n_features}, "
            f"{mean:.0f} a frame; the shipped vocabulary")
    out: dict[str, object] = {"inputs": what, "runs": runs, "load_average": load_average()}
    inputs = tmp / "peers_inputs"
    inputs.mkdir(parents=True, exist_ok=True)
    with open(inputs / "descriptors.bin", "wb") as f:  # uint32 frames, then per frame uint32 rows + rows x 32
        f.write(np.uint32(len(frames)).tobytes())
        for d in frames:
            f.write(np.uint32(d.shape[0]).tobytes() + np.ascontiguousarray(d).tobytes())
    text = inputs / "vocabulary.txt"  # ORB-SLAM's text format, as ORBvoc.txt
    save_vocabulary(voc, text)
    out["transform_ms"] = round(median_over(frames, voc.transform, runs), 4)
    out["text_load_ms"] = round(timed_loads(text, runs) * 1000, 1)
    out["binary_load_ms"] = round(timed_loads(default_vocabulary_path(), runs, mmap=True) * 1000, 3)
    rng = np.random.default_rng(0)
    bows = [voc.transform(d) for d in frames]
    feats = [fake_features(d, rng) for d in frames]
    adds, queries = [], []
    for _ in range(runs):
        db = Database(voc)
        a, q = [], []
        for i, (bow, fvec) in enumerate(bows):
            t = time.perf_counter()
            db.add(bow, fvec, feats[i], timestamp=float(i))
            t1 = time.perf_counter()
            db.query(bow, max_results=50)
            a.append(t1 - t)
            q.append(time.perf_counter() - t1)
        db.close()
        adds.append(np.mean(a) * 1e3)
        queries.append(np.median(q) * 1e3)
    out["add_ms_mean"] = round(float(np.median(adds)), 4)
    out["query_233_after_every_add_ms"] = round(float(np.median(queries)), 3)
    db = Database(voc)
    _, kept = build(db, voc, 10_000)
    out["query_10k_top50_ms"] = round(query_ms(db, voc, kept, max_results=50), 3)
    out["query_10k_entries"] = ("10,000 synthetic entries of the shipped vocabulary (engine_synth.py), "
                                "queried by revisits of them (the database section's protocol)")
    db.close()
    first = first_decision_figure.get("fast_cold_cache", {}) if first_decision_figure else {}
    if first:
        out["first_decision_s"] = first.get("to_first_decision_s")
    ref = json.loads((HERE / "peers_reference.json").read_text())
    out["peers"] = ref
    print(f"  {'figure':<34} {'stablecues':>12}  peer", flush=True)
    for key, peer in ref["figures"].items():
        mine = out.get(key, "-")
        print(f"  {peer['what'][:34]:<34} {mine!s:>12}  {peer['peer']} {peer['value']}", flush=True)
    print(f"  {'mean add of the 233':<34} {out['add_ms_mean']!s:>12}  (the peers' adds: 2-3x slower)",
          flush=True)
    return out


SECTIONS = ("vocabulary", "database", "end_to_end", "first_decision", "growing", "peers")


def median_of_runs(runs: list[dict[str, object]]) -> dict[str, object]:
    """Per figure, the median over runs (numbers), every run's value (load averages), or the
    first run's (text)."""
    out: dict[str, object] = {}
    for key, first in runs[0].items():
        values = [r[key] for r in runs]
        if isinstance(first, dict):
            out[key] = median_of_runs(values)  # type: ignore[arg-type]
        elif isinstance(first, bool) or not isinstance(first, int | float):
            out[key] = values if "load_average" in key else first
        elif all(v == first for v in values):
            out[key] = first  # a count, the same in every run
        else:
            out[key] = round(float(np.median(values)), 4)  # type: ignore[arg-type]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--entries-small", type=int, default=10_000)
    ap.add_argument("--entries-large", type=int, default=100_000)
    ap.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    ap.add_argument("--vocabulary-runs", type=int, default=3,
                    help="repeat the vocabulary section; each figure is the median over the runs")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "engine.json")
    ap.add_argument("--tails", type=int, nargs="+", default=[65536, 16384, 8192],
                    help="growing: the DatabaseConfig.tail_postings values compared")
    ap.add_argument("--peers-inputs", type=Path, default=None,
                    help="peers: keep the inputs (descriptors.bin, vocabulary.txt) in this folder")
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        scale_child(args.child[0], int(args.child[1]), args.child[2])
        return

    results: dict[str, object] = json.loads(args.out.read_text()) if args.out.is_file() else {}
    results.update({"threads": 1, "machine": f"{os.cpu_count()} cores"})
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        if "vocabulary" in args.sections:
            runs = []
            for i in range(args.vocabulary_runs):
                print(f"vocabulary, run {i + 1} of {args.vocabulary_runs} ...", flush=True)
                runs.append(vocabulary_section(tmp))
            results.update(median_of_runs(runs))
            results["vocabulary_runs"] = args.vocabulary_runs
            results["vocabulary_measured"] = time.strftime("%Y-%m-%d %H:%M")
        if "database" in args.sections:
            results.update(database_section(args, tmp))
            results["database_measured"] = time.strftime("%Y-%m-%d %H:%M")
    if "growing" in args.sections:
        print("a map queried while it grows ...", flush=True)
        results["growing"] = {str(t): growing_map(t) for t in args.tails}
        results["growing_measured"] = time.strftime("%Y-%m-%d %H:%M")
    if "first_decision" in args.sections:
        print("time to the first decision, fresh processes ...", flush=True)
        results["first_decision"] = first_decision()
        results["first_decision_measured"] = time.strftime("%Y-%m-%d %H:%M")
    if "peers" in args.sections:
        print("side by side with the peers' run ...", flush=True)
        with tempfile.TemporaryDirectory() as tmp_s:
            tmp = Path(tmp_s) if args.peers_inputs is None else args.peers_inputs
            first = results.get("first_decision")
            results["peers"] = peers_section(tmp, first if isinstance(first, dict) else None)
        results["peers_measured"] = time.strftime("%Y-%m-%d %H:%M")
    frames = real_frames()
    if "end_to_end" in args.sections and frames:
        print("end to end on real frames ...", flush=True)
        results["end_to_end"] = end_to_end(frames)
        results["end_to_end_measured"] = time.strftime("%Y-%m-%d %H:%M")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
