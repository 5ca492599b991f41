#!/usr/bin/env python
"""Database at scale (issue 13): add latency, reopen time, memory, query time, bytes per entry.

Prints the figures and writes ``bench/results/scale.json``. Three parts, each in its own
subprocesses so that every peak-memory figure is that process's own:

``adds``  10,000 adds of real ORB frames (the 233 CamVid test frames of ``../shared/data``,
          cycled; synthetic descriptors when absent) with the shipped vocabulary, back to back,
          in memory and in a file, with inline (the default) and background index
          maintenance: mean, median, p99 and max of single adds, and their CPU time. Also:
          keeping only BoW and direct index as DBoW3 does (``bow-only``), no index maintenance
          at all (``control``: the floor an add costs here), and 3,000 adds to a file at a
          camera's pace of 100 Hz (``paced``: back to back, the disk itself stalls writes).
``100k``  100,000 entries of 1000 features (keypoints and descriptors stored, as a SLAM system
          would) with the synthetic 10^6-word tree of ``engine_synth.py``: add throughput and
          max add, then in a fresh process: reopen time, query p50/p90, resident and peak memory.
``1m``    1,000,000 entries of 300 features (keypoints and descriptors left out), built in
          resumable chunks of subprocesses (``--work`` keeps the map between calls), then the
          same reopen / query / memory figures and bytes on disk per entry.

The machine is shared: every figure carries the 1-minute load average around it, and the
``adds`` part runs ``--repeat`` times and keeps the medians. Run it as
``OMP_NUM_THREADS=1 python bench/bench_scale.py`` (the script sets the variable itself too).
``--baseline DIR`` measures another implementation of ``stablecues.database`` (a copy of an
older version's package, importable as ``olddb`` from DIR) with the same workload.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import contextlib
import gc
import json
import resource
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from engine_synth import EntryMaker, synthetic_vocabulary  # noqa: E402
from stablecues.types import Features  # noqa: E402
from stablecues.vocabulary import Vocabulary, load_vocabulary, save_vocabulary  # noqa: E402

SHARED = HERE.parent.parent / "shared" / "data"


# ---------------------------------------------------------------------------- helpers
def load() -> float:
    return round(os.getloadavg()[0], 2)


def machine_memory_gb() -> dict[str, float]:
    """The machine's free memory and page cache (``/proc/meminfo``): fresh memory costs an add
    much more when the page cache has to be reclaimed for it first (an add at 10k took 0.55 ms
    on average in a run right after the 10^6-entry map's files had filled the cache, 0.14-0.18
    in the next two)."""
    out = {}
    with contextlib.suppress(OSError):
        for line in Path("/proc/meminfo").read_text().splitlines():
            key, _, rest = line.partition(":")
            if key in ("MemFree", "MemAvailable", "Cached"):
                out[key] = round(int(rest.split()[0]) / 2**20, 2)
    return out


def memory_gb() -> dict[str, float]:
    """This process's resident (VmRSS) and peak resident (VmHWM) memory."""
    out = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        for key, name in (("VmRSS:", "rss_gb"), ("VmHWM:", "peak_rss_gb")):
            if line.startswith(key):
                out[name] = round(int(line.split()[1]) / 2**20, 3)
    return out


def fake_features(desc: np.ndarray, rng: np.random.Generator) -> Features:
    n = desc.shape[0]
    return Features(
        keypoints=(rng.random((n, 2)) * [640, 480]).astype(np.float32), descriptors=desc,
        octaves=rng.integers(0, 8, n).astype(np.int16), angles=(rng.random((n,)) * 360).astype(np.float32),
        responses=rng.random((n,)).astype(np.float32), sizes=np.full(n, 31, np.float32),
        image_size=(640, 480),
    )


def database_module(baseline: str | None) -> Any:
    if baseline:
        sys.path.insert(0, baseline)
        import olddb

        return olddb
    import stablecues.database as module

    return module


def child(args: list[str]) -> dict[str, Any]:
    """Run this script in a subprocess; its last stdout line is a JSON object."""
    proc = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"child {args[:2]} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def stats_ms(times: list[float]) -> dict[str, float]:
    t = np.asarray(times) * 1e3
    return {"mean": round(float(t.mean()), 4), "median": round(float(np.median(t)), 4),
            "p99": round(float(np.percentile(t, 99)), 3), "max": round(float(t.max()), 3)}


# ---------------------------------------------------------------------------- adds at 10k
def real_frames() -> list[np.ndarray]:
    from stablecues.features import OrbExtractor
    from stablecues.imageio import read_image

    files = sorted((SHARED / "camvid" / "test").glob("*.jpg"))
    ex = OrbExtractor()
    return [ex.extract(read_image(f, "grey")).descriptors for f in files]


def adds_child(where: str, maintenance: str, n: int, baseline: str | None) -> None:
    from stablecues.vocabulary import default_vocabulary

    mod = database_module(baseline)
    voc = default_vocabulary()
    descs = real_frames()
    source = "camvid/test ORB"
    if not descs:
        maker = EntryMaker(voc, n_features=1000)
        descs = [maker.next() for _ in range(233)]
        source = "synthetic"
    rng = np.random.default_rng(0)
    prepared = [(*voc.transform(d), fake_features(d, rng)) for d in descs]
    path = None
    if where == "file":
        tmp = Path(os.environ.get("TMPDIR", "/tmp")) / f"bench_scale_adds_{os.getpid()}"
        tmp.mkdir(exist_ok=True)
        path = tmp / "map.sqlite"
    if baseline:
        cfg = None
    elif maintenance == "control":  # nothing is ever sorted or merged: the floor of an add
        cfg = mod.DatabaseConfig(tail_postings=1 << 40)
    elif maintenance == "bow-only":  # what DBoW3 keeps: BoW and direct index, no features
        cfg = mod.DatabaseConfig(store_descriptors=False)
    elif maintenance == "paced":  # a camera's pace (100 Hz), not as fast as the disk takes it
        cfg = mod.DatabaseConfig()
        n = min(n, 3000)
    else:
        cfg = mod.DatabaseConfig(maintenance=maintenance)
    db = mod.Database(voc, path, cfg)
    times, cpu = [], []
    start_load = load()
    machine = machine_memory_gb()
    process0 = time.process_time()
    period = 0.01 if maintenance == "paced" else 0.0
    next_at = time.perf_counter()
    for i in range(n):
        bow, fvec, feats = prepared[i % len(prepared)]
        if period:
            next_at += period
            time.sleep(max(next_at - time.perf_counter(), 0.0))
        t, c = time.perf_counter(), time.thread_time()
        db.add(bow, fvec, feats, timestamp=float(i), meta={"frame": i})
        cpu.append(time.thread_time() - c)
        times.append(time.perf_counter() - t)
    process_ms = (time.process_time() - process0) * 1e3 / n  # sleeping takes no CPU time
    out = {"source": source, "features_mean": round(float(np.mean([len(p[2]) for p in prepared])), 1),
           "add_ms": stats_ms(times),
           # CPU time: what an add costs whatever else runs on the machine
           "add_cpu_ms": {"mean_adding_thread": round(float(np.mean(cpu)) * 1e3, 4),
                          "mean_all_threads": round(process_ms, 4)},
           "load": [start_load, load()], "machine_memory_gb_at_start": machine}
    db.close()
    if path is not None:
        shutil.rmtree(path.parent, ignore_errors=True)
    print(json.dumps(out))


def gc_child() -> None:
    """What a full garbage collection costs once the compiled kernels are loaded (the first
    transform imports numba), with the library's freeze (default) or without it
    (``STABLECUES_GC_FREEZE=0``): a full collection runs in whichever thread triggers it, an
    add included."""
    from stablecues.vocabulary import default_vocabulary

    voc = default_vocabulary()
    voc.transform(np.zeros((10, 32), np.uint8))
    times = []
    for _ in range(5):
        t = time.perf_counter()
        gc.collect()
        times.append(time.perf_counter() - t)
    print(json.dumps({"freeze": os.environ.get("STABLECUES_GC_FREEZE", "1") != "0",
                      "tracked_objects": len(gc.get_objects()), "frozen_objects": gc.get_freeze_count(),
                      "full_collection_ms": stats_ms(times), "load": load()}))


def run_gc() -> dict[str, Any]:
    out = {}
    for setting in ("1", "0"):
        env = {**os.environ, "STABLECUES_GC_FREEZE": setting}
        proc = subprocess.run([sys.executable, __file__, "--child", "gc"], capture_output=True, text=True,
                              env=env, check=True)
        out["freeze" if setting == "1" else "no_freeze"] = json.loads(proc.stdout.strip().splitlines()[-1])
    return out


def run_adds(repeat: int, n: int, baseline: str | None) -> dict[str, Any]:
    configs = [("memory", "inline"), ("memory", "background"), ("memory", "bow-only"), ("memory", "control"),
               ("file", "inline"), ("file", "background"), ("file", "paced")]
    if baseline:
        configs = [("memory", "-"), ("file", "-")]
    out: dict[str, Any] = {}
    for where, maintenance in configs:
        runs = []
        for r in range(repeat):
            print(f"  adds: {where} {maintenance} run {r + 1}/{repeat} ...", flush=True)
            runs.append(child(["--child", "adds", where, maintenance, str(n), baseline or ""]))
        key = f"{where}_{maintenance}" if not baseline else where
        out[key] = {
            "add_ms": {k: round(float(np.median([x["add_ms"][k] for x in runs])), 4)
                       for k in runs[0]["add_ms"]},
            "add_cpu_ms": {k: round(float(np.median([x["add_cpu_ms"][k] for x in runs])), 4)
                           for k in runs[0]["add_cpu_ms"]},
            "runs": [x["add_ms"] for x in runs],
            "load": [x["load"] for x in runs],
            # page faults on fresh memory decide the tail: a full page cache makes them slower
            "machine_memory_gb_at_start": [x["machine_memory_gb_at_start"] for x in runs],
            "features_mean": runs[0]["features_mean"], "source": runs[0]["source"],
        }
    return out


# ---------------------------------------------------------------------------- large maps
def instrument(db: Any) -> list[list[Any]]:
    """What runs inside an add, as [what, ms], appended to the list returned (the caller clears
    it before each add): the index's inline maintenance (a sort of the latest blocks or a merge
    step, with their postings; a merge job's start; a finished job's install and the discard of
    what it replaced), its seals, the entry log's append."""
    parts: list[list[Any]] = []

    def timed(obj: Any, name: str, what: Any) -> None:
        method = getattr(obj, name)

        def run(*args: Any, **kwargs: Any) -> Any:
            t = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                parts.append([what(*args), round(1e3 * (time.perf_counter() - t), 2)])

        setattr(obj, name, run)

    timed(db.index, "_advance", lambda job: (f"sort {sum(b.words.size for b in job.blocks)}" if job.blocks
                                               else f"merge step, {job.remaining} left"))
    timed(db.index, "_start", lambda inputs, *_: f"merge start, {sum(x.size for x in inputs)} postings")
    timed(db.index, "_install", lambda job: "install")
    timed(db.index, "_discard", lambda old: f"discard {len(old)}")
    timed(db.index, "_seal", lambda: "seal")
    if db._entries is not None:
        timed(db._entries, "add", lambda row: "entry log")
    return parts


def thread_cpu_ms() -> dict[str, float]:
    """CPU time (ms) of every thread of this process by name, from /proc (empty elsewhere)."""
    names = {t.native_id: t.name for t in threading.enumerate()}
    out: dict[str, float] = {}
    with contextlib.suppress(OSError):
        for tid in os.listdir("/proc/self/task"):
            with contextlib.suppress(OSError, ValueError, IndexError):
                ns = int(Path(f"/proc/self/task/{tid}/schedstat").read_text().split()[0])
                name = names.get(int(tid), f"thread {tid}")
                out[name] = out.get(name, 0.0) + ns / 1e6
    return out


class AddProbe:
    """What one add cost and what ran beside it: wall and CPU time of the adding thread, full
    garbage collections (any thread) that overlapped it, the parts :func:`instrument` timed
    inside it, the adding thread's page faults and the CPU that other threads of the process
    used meanwhile (a lock or the interpreter lock they held is time the add waited): their
    sum, or (``by_thread``) each thread's, which reads /proc for every thread before every add
    (0.15 ms with 7 threads: for the paced adds, not for a build of 10^6)."""

    def __init__(self, db: Any, adds_done: Any, by_thread: bool = False) -> None:
        self.parts = instrument(db)
        self.full_gc: list[list[float]] = []  # [start, end, adds done before it]
        self._adds_done = adds_done
        self._by_thread = by_thread
        gc.callbacks.append(self._on_gc)
        self._t = self._c = self._p = self._dt = self._cpu = self._others = 0.0
        self._faults = 0
        self._threads: dict[str, float] = {}

    def _on_gc(self, phase: str, info: dict[str, int]) -> None:
        if info["generation"] == 2:
            if phase == "start":
                self.full_gc.append([time.perf_counter(), float("nan"), self._adds_done()])
            elif self.full_gc:
                self.full_gc[-1][1] = time.perf_counter()

    def before(self) -> None:
        self.parts.clear()
        if self._by_thread:
            self._threads = thread_cpu_ms()
        self._faults = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
        self._p = time.process_time()
        self._c = time.thread_time()
        self._t = time.perf_counter()

    def after(self) -> float:
        """Seconds the add took."""
        self._dt = time.perf_counter() - self._t
        self._cpu = time.thread_time() - self._c
        self._others = time.process_time() - self._p - self._cpu
        return self._dt

    def record(self) -> list[Any]:
        """[wall ms, CPU ms, full-collection ms, parts] of the add just timed (call it right
        after :meth:`after`, only for the adds worth recording)."""
        t, dt = self._t, self._dt
        in_gc = sum(max(min(b, t + dt) - max(a, t), 0.0) for a, b, _ in self.full_gc[-3:])
        faults = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - self._faults
        others: float | dict[str, float] = round(1e3 * self._others, 2)
        if self._by_thread:
            me = threading.current_thread().name
            others = {k: round(v - self._threads.get(k, 0.0), 2) for k, v in thread_cpu_ms().items()
                      if k != me and v - self._threads.get(k, 0.0) >= 0.05}
        return [round(1e3 * dt, 2), round(1e3 * self._cpu, 2), round(1e3 * in_gc, 2),
                [*self.parts, ["page faults", faults], ["other threads' CPU ms", others]]]


def build_child(voc_path: str, db_path: str, n_total: int, n_features: int, descriptors: bool,
                budget_s: float, seed: int) -> None:
    """Add entries to the map until it holds n_total or the time budget is spent."""
    from stablecues.database import Database, DatabaseConfig

    voc = load_vocabulary(voc_path)
    cfg = DatabaseConfig(store_descriptors=descriptors)
    t0 = time.perf_counter()
    db = Database(voc, db_path, cfg)
    open_s = time.perf_counter() - t0
    start = len(db)
    maker = EntryMaker(voc, n_features=n_features, seed=seed + start)
    rng = np.random.default_rng(seed + start)
    kept_path = Path(db_path).with_suffix(".queries.npy")
    kept = list(np.load(kept_path)) if kept_path.exists() else []
    times = []
    # [entry, wall ms, CPU ms of the adding thread, ms of full garbage collections (any thread)
    # inside it, what ran inside it] of every add over 10 ms (AddProbe)
    slow = []
    i = start
    probe = AddProbe(db, lambda: i - start)
    load0 = load()
    deadline = time.perf_counter() + budget_s
    while i < n_total and time.perf_counter() < deadline:
        d = maker.next()
        bow, fvec = voc.transform(d)
        feats = fake_features(d, rng)  # the direct index is stored; these only when descriptors
        probe.before()
        db.add(bow, fvec, feats, timestamp=float(i))
        dt = probe.after()
        times.append(dt)
        if dt > 0.010:
            slow.append([i, *probe.record()])
        if i % max(n_total // 200, 1) == 0:
            kept.append(d)
        i += 1
    t = time.perf_counter()
    db.close()
    close_s = time.perf_counter() - t
    if kept:
        np.save(kept_path, np.stack(kept))
    print(json.dumps({"start": start, "end": i, "add_s": float(np.sum(times)),
                      "wall_s": round(time.perf_counter() - t0, 3),
                      "add_ms": stats_ms(times) if times else {}, "slow_adds": slow,
                      # [ms, adds done before it]: numba's import (the first transform) runs
                      # a few before the first add
                      "full_gc_ms": [[round(1e3 * (b - a), 2), int(k)] for a, b, k in probe.full_gc],
                      "open_s": round(open_s, 3),
                      "close_s": round(close_s, 3), "load": [load0, load()], **memory_gb()}))


def query_bows(voc: Vocabulary, kept: np.ndarray, n: int) -> list[Any]:
    """Revisits: stored images seen again with 20 % of their descriptors replaced."""
    rng = np.random.default_rng(7)
    out = []
    for i in range(n):
        q = kept[i % len(kept)].copy()
        swap = rng.random(q.shape[0]) < 0.2
        q[swap] = voc.descriptors[rng.choice(voc.word_nodes, int(swap.sum()))]
        out.append(voc.transform(q)[0])
    return out


def reopen_child(voc_path: str, db_path: str, n_queries: int) -> None:
    """Reopen the map (as its writer), run queries, report times and memory."""
    from stablecues.database import Database

    voc = load_vocabulary(voc_path)
    kept = np.load(Path(db_path).with_suffix(".queries.npy"))
    bows = query_bows(voc, kept, n_queries)
    before = memory_gb()
    load0 = load()
    t = time.perf_counter()
    db = Database(voc, db_path)
    reopen_s = time.perf_counter() - t
    after_open = memory_gb()
    times = []
    for bow in bows:
        t = time.perf_counter()
        db.query(bow, max_results=50)
        times.append(time.perf_counter() - t)
    mem = memory_gb()
    stats = db.stats()
    q = np.asarray(times) * 1e3
    db.close()
    print(json.dumps({
        "entries": stats["entries"], "reopen_s": round(reopen_s, 3), "queries": n_queries,
        "query_ms": {"p50": round(float(np.percentile(q, 50)), 3),
                     "p90": round(float(np.percentile(q, 90)), 3), "max": round(float(q.max()), 3)},
        "rss_gb_before_open": before["rss_gb"], "rss_gb_after_open": after_open["rss_gb"],
        "rss_gb_after_queries": mem["rss_gb"], "peak_rss_gb": mem["peak_rss_gb"],
        "postings": stats["postings"], "segments": stats["segments"], "file_bytes": stats["file_bytes"],
        "bytes_per_entry": round(stats["file_bytes"] / max(stats["entries"], 1), 1), "load": [load0, load()],
    }))


def paced_child(voc_path: str, db_path: str, n_features: int, descriptors: bool, n: int, hz: float) -> None:
    """Add n more entries to the map at a camera's pace: the add latency a SLAM system sees."""
    from stablecues.database import Database, DatabaseConfig

    voc = load_vocabulary(voc_path)
    db = Database(voc, db_path, DatabaseConfig(store_descriptors=descriptors))
    start = len(db)
    maker = EntryMaker(voc, n_features=n_features, seed=10**7 + start)
    rng = np.random.default_rng(start)
    times = []
    # [add, wall ms, CPU ms of the adding thread, ms of full garbage collections, what ran
    # inside it] of every add over 10 ms (AddProbe)
    slow = []
    i = 0
    probe = AddProbe(db, lambda: i, by_thread=True)
    load0 = load()
    next_at = time.perf_counter()
    for i in range(n):
        d = maker.next()
        bow, fvec = voc.transform(d)
        feats = fake_features(d, rng)
        next_at += 1.0 / hz
        time.sleep(max(next_at - time.perf_counter(), 0.0))
        probe.before()
        db.add(bow, fvec, feats, timestamp=float(start + i))
        dt = probe.after()
        times.append(dt)
        if dt > 0.010:
            slow.append([i, *probe.record()])
    db.close()
    print(json.dumps({"entries_before": start, "adds": n, "hz": hz, "add_ms": stats_ms(times),
                      "slow_adds": slow, "load": [load0, load()]}))


def run_large(name: str, work: Path, n: int, n_features: int, descriptors: bool, chunk_s: float,
              n_queries: int, repeat: int) -> dict[str, Any]:
    work.mkdir(parents=True, exist_ok=True)
    voc_path = work / "voc1m.scv"
    if not voc_path.exists():
        print("  building the 10^6-word synthetic vocabulary ...", flush=True)
        save_vocabulary(synthetic_vocabulary(), voc_path)
    db_path = work / f"{name}.sqlite"
    log_path = work / f"{name}.build.json"
    chunks: list[dict[str, Any]] = json.loads(log_path.read_text()) if log_path.exists() else []
    done = chunks[-1]["end"] if chunks else 0
    built_now = done < n
    while done < n:
        print(f"  {name}: {done} entries, adding for up to {chunk_s:.0f} s ...", flush=True)
        res = child(["--child", "build", str(voc_path), str(db_path), str(n), str(n_features),
                     str(int(descriptors)), str(chunk_s), "1"])
        chunks.append(res)
        log_path.write_text(json.dumps(chunks))
        done = res["end"]
    add_s = sum(c["add_s"] for c in chunks)
    reopens = []
    for r in range(repeat):
        print(f"  {name}: reopen and {n_queries} queries, run {r + 1}/{repeat} ...", flush=True)
        reopens.append(child(["--child", "reopen", str(voc_path), str(db_path), str(n_queries)]))
    print(f"  {name}: 2000 more adds at 100 Hz ...", flush=True)
    paced = child(["--child", "paced", str(voc_path), str(db_path), str(n_features), str(int(descriptors)),
                   "2000", "100"])
    med = {k: float(np.median([x[k] for x in reopens])) for k in ("reopen_s", "rss_gb_after_queries")}
    return {
        "entries": n, "features": n_features, "descriptors_stored": descriptors, "built_now": built_now,
        "build_chunks": len(chunks), "add_per_s": round(n / add_s, 1),
        # everything a build does per entry: synthetic descriptors, transform, features, add
        "build_entries_per_s": round(n / sum(c.get("wall_s", float("nan")) for c in chunks), 1),
        "add_ms_max": max(c["add_ms"].get("max", 0.0) for c in chunks),
        # the slowest adds, [entry, wall ms, CPU ms of the adding thread, ms of full garbage
        # collections inside it]: CPU near the wall time is work done in the add (a collection
        # in the adding thread included), far below it a wait (the disk, a lock, other threads)
        "adds_over_10ms": sum(len(c.get("slow_adds", [])) for c in chunks),
        "adds_over_20ms": sum(1 for c in chunks for x in c.get("slow_adds", []) if x[1] > 20),
        "slowest_adds": sorted((x for c in chunks for x in c.get("slow_adds", [])), key=lambda x: -x[1])[:10],
        "full_gc_ms": [x for c in chunks for x in c.get("full_gc_ms", [])],
        "add_ms_mean": round(1e3 * add_s / n, 4),
        # an add returns once its entry is in the entry log; closing waits until SQLite holds
        # every entry (what the SQLite thread had still to write when the adds stopped)
        "close_s_max": max(c.get("close_s", float("nan")) for c in chunks),
        "peak_rss_gb_build": max(c["peak_rss_gb"] for c in chunks),
        "reopen_s": round(med["reopen_s"], 3),
        "query_ms_p50": round(float(np.median([x["query_ms"]["p50"] for x in reopens])), 3),
        "query_ms_p90": round(float(np.median([x["query_ms"]["p90"] for x in reopens])), 3),
        "rss_gb_after_reopen_and_queries": round(med["rss_gb_after_queries"], 3),
        "peak_rss_gb_reopen": max(x["peak_rss_gb"] for x in reopens),
        "bytes_per_entry": reopens[-1]["bytes_per_entry"], "postings": reopens[-1]["postings"],
        "segments": reopens[-1]["segments"],
        "build_load": [c["load"] for c in chunks], "reopen_runs": reopens, "paced_adds": paced,
    }


# ---------------------------------------------------------------------------- main
def build_record(r: dict[str, Any]) -> dict[str, Any]:
    """One line of a large build's history: the slowest adds swing from build to build on the
    same code (the machine, the page cache), so every build's figures are kept, not only the
    last one's."""
    commit = subprocess.run(["git", "-C", str(HERE), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip() or "unknown"
    return {"date": time.strftime("%Y-%m-%d %H:%M"), "commit": commit, "add_ms_max": r["add_ms_max"],
            "adds_over_10ms": r.get("adds_over_10ms"), "adds_over_20ms": r.get("adds_over_20ms"),
            "build_entries_per_s": r["build_entries_per_s"], "query_ms_p50": r["query_ms_p50"],
            "build_load": r["build_load"]}


def summary(results: dict[str, Any]) -> dict[str, Any]:
    """The figures issue 13 names, each with the load it was measured under."""
    out: dict[str, Any] = {}
    for key, part in (("", results.get("adds", {})), ("_before", results.get("adds_baseline", {}))):
        # the default configuration (inline maintenance), in memory as the peers' figures are;
        # the file database beside it
        for where in ("memory", "file"):
            r = part.get(f"{where}_inline") or part.get(where)
            if not r:
                continue
            loads = float(np.median([x for pair in r["load"] for x in pair]))
            name = "" if where == "memory" else "_file"
            out[f"add_ms_mean_10k{name}{key}"] = {"value": r["add_ms"]["mean"], "load": loads}
            out[f"add_ms_max_10k{name}{key}"] = {"value": r["add_ms"]["max"], "load": loads}
    if "gc" in results:
        out["full_gc_ms"] = {k: v["full_collection_ms"]["median"] for k, v in results["gc"].items()}
    for key, name in (("100k", "100k"), ("1m", "1m")):
        r = results.get(key)
        if not r:
            continue
        rl = float(np.median([x["load"][0] for x in r["reopen_runs"]]))
        bl = float(np.median([x[0] for x in r["build_load"]]))
        out[f"reopen_s_{name}"] = {"value": r["reopen_s"], "load": rl}
        out[f"add_per_s_{name}"] = {"value": r["add_per_s"], "load": bl}
        out[f"add_ms_max_{name}"] = {"value": r["add_ms_max"], "load": bl}
        if "slowest_adds" in r:
            out[f"adds_over_10ms_{name}"] = {"value": r["adds_over_10ms"], "over_20ms": r["adds_over_20ms"],
                                            "slowest_wall_cpu_ms": [x[1:] for x in r["slowest_adds"][:5]]}
        if f"{key}_builds" in results:
            # builds of other code kept for comparison carry a note
            out[f"add_ms_max_{name}_builds"] = [x["add_ms_max"] for x in results[f"{key}_builds"]
                                               if "note" not in x]
        out[f"bytes_per_entry_{name}"] = {"value": r["bytes_per_entry"]}
        out[f"query_ms_{name}"] = {"p50": r["query_ms_p50"], "p90": r["query_ms_p90"], "load": rl}
        peak = max(r["peak_rss_gb_build"], r["peak_rss_gb_reopen"])
        out[f"peak_rss_gb_{name}"] = {"value": peak, "build": r["peak_rss_gb_build"],
                                      "reopen_and_queries": r["peak_rss_gb_reopen"], "load": bl}
        out[f"rss_gb_{name}"] = {"value": r["rss_gb_after_reopen_and_queries"], "load": rl}
        if "paced_adds" in r:
            pa = r["paced_adds"]
            out[f"add_ms_{name}_at_100hz"] = {**pa["add_ms"], "load": float(np.median(pa["load"]))}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--parts", default="gc,adds,100k,1m", help="comma-separated: gc, adds, 100k, 1m")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each add and reopen measurement")
    ap.add_argument("--adds", type=int, default=10_000)
    ap.add_argument("--entries-100k", type=int, default=100_000)
    ap.add_argument("--entries-1m", type=int, default=1_000_000)
    ap.add_argument("--queries", type=int, default=100)
    ap.add_argument("--chunk-s", type=float, default=600.0, help="seconds per build subprocess")
    ap.add_argument("--work", type=Path, default=Path("/tmp/stablecues-bench-scale"),
                    help="where the large maps are built (kept, so a run can resume)")
    ap.add_argument("--baseline", help="directory holding an older database package as 'olddb'")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "scale.json")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        kind, *rest = args.child
        if kind == "adds":
            adds_child(rest[0], rest[1], int(rest[2]), rest[3] or None)
        elif kind == "build":
            build_child(rest[0], rest[1], int(rest[2]), int(rest[3]), bool(int(rest[4])),
                        float(rest[5]), int(rest[6]))
        elif kind == "gc":
            gc_child()
        elif kind == "paced":
            paced_child(rest[0], rest[1], int(rest[2]), bool(int(rest[3])), int(rest[4]), float(rest[5]))
        else:
            reopen_child(rest[0], rest[1], int(rest[2]))
        return

    results: dict[str, Any] = json.loads(args.out.read_text()) if args.out.exists() else {}
    results.update({"machine": f"{os.cpu_count()} cores, shared", "threads": 1,
                    "memory_gb": round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)})
    parts = args.parts.split(",")
    if "gc" in parts:
        print("gc: a full collection with and without the freeze ...", flush=True)
        results["gc"] = run_gc()
    if "adds" in parts:
        print(f"adds: {args.adds} single adds, {args.repeat} runs each ...", flush=True)
        key = "adds_baseline" if args.baseline else "adds"
        results[key] = run_adds(args.repeat, args.adds, args.baseline)
    if "100k" in parts:
        results["100k"] = run_large("map100k", args.work, args.entries_100k, 1000, True, args.chunk_s,
                                    args.queries, args.repeat)
    if "1m" in parts:
        results["1m"] = run_large("map1m", args.work, args.entries_1m, 300, False, args.chunk_s,
                                  args.queries, args.repeat)
        if results["1m"]["built_now"]:  # not a rerun of the reopen and paced parts on a built map
            results.setdefault("1m_builds", []).append(build_record(results["1m"]))
    results["summary"] = summary(results)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results["summary"], indent=2))


if __name__ == "__main__":
    main()
