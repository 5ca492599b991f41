#!/usr/bin/env python
"""Engine benchmark (issue 2): vocabulary transform and loading, database add/query at scale,
and the end-to-end per-frame cost on real frames.

Prints the figures and writes ``bench/results/engine.json``. One thread: run it as
``OMP_NUM_THREADS=1 python bench/bench_engine.py`` (the script sets the variable itself too).

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
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from engine_synth import EntryMaker, synthetic_vocabulary  # noqa: E402
from stablecues.database import Database  # noqa: E402
from stablecues.features import OrbExtractor  # noqa: E402
from stablecues.imageio import read_image  # noqa: E402
from stablecues.types import Features  # noqa: E402
from stablecues.vocabulary import Vocabulary, default_vocabulary, load_vocabulary, save_vocabulary  # noqa: E402

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


def query_ms(db: Database, voc: Vocabulary, kept: list[np.ndarray], repeat: int = 200) -> float:
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
        db.query(b, max_results=10)
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--entries-small", type=int, default=10_000)
    ap.add_argument("--entries-large", type=int, default=100_000)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "engine.json")
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        scale_child(args.child[0], int(args.child[1]), args.child[2])
        return

    results: dict[str, object] = {"threads": 1, "machine": f"{os.cpu_count()} cores"}
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        print("building the 10^6-word synthetic vocabulary ...", flush=True)
        voc = synthetic_vocabulary()
        bin_path, txt_path = tmp / "voc1m.scv", tmp / "voc1m.txt"
        save_vocabulary(voc, bin_path)
        save_vocabulary(voc, txt_path)
        loads = []
        for _ in range(5):
            t = time.perf_counter()
            load_vocabulary(bin_path)
            loads.append(time.perf_counter() - t)
        t = time.perf_counter()
        load_vocabulary(txt_path)
        results["vocab_load_s_text"] = round(time.perf_counter() - t, 3)
        results["vocab_load_s_binary"] = round(float(np.median(loads)), 4)
        results["vocab_words"] = voc.n_words
        results["vocab_file_mb"] = {"binary": round(bin_path.stat().st_size / 2**20, 1),
                                    "text": round(txt_path.stat().st_size / 2**20, 1)}

        frames = real_frames()
        if frames:
            desc = OrbExtractor().extract(read_image(frames[0], "grey")).descriptors
            results["transform_input"] = f"{desc.shape[0]} ORB descriptors of {frames[0].name}"
        else:
            desc = EntryMaker(voc).next()
            results["transform_input"] = "1000 synthetic descriptors"
        desc = desc[:1000]
        results["transform_ms_1m"] = round(median_ms(lambda: voc.transform(desc), 300), 3)
        results["transform_ms_default_vocab"] = round(
            median_ms(lambda: default_vocabulary().transform(desc), 300), 3)

        print(f"building a {args.entries_small}-entry database ...", flush=True)
        db = Database(voc)
        rate, kept = build(db, voc, args.entries_small)
        results["query_ms_10k"] = round(query_ms(db, voc, kept), 3)
        results["add_per_s_10k_memory"] = round(rate, 1)
        results["postings_10k"] = db.stats()["postings"]
        db.close()

        print(f"building a {args.entries_large}-entry database on disk (subprocess) ...", flush=True)
        out = subprocess.run(
            [sys.executable, __file__, "--child", str(bin_path), str(args.entries_large),
             str(tmp / "big.db")],
            check=True, capture_output=True, text=True,
        )
        big = json.loads(out.stdout.strip().splitlines()[-1])
        results["query_ms_100k"] = round(big["query_ms"], 3)
        results["query_ratio_100k_10k"] = round(big["query_ms"] / results["query_ms_10k"], 2)  # type: ignore[operator]
        results["scale_100k"] = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in big.items()}

    if frames:
        print("end to end on real frames ...", flush=True)
        results["end_to_end"] = end_to_end(frames)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
