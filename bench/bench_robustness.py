"""Malformed inputs through the CLI, each in its own process: how does stablecues fail?

Every case of ``tests/malformed_cases.py`` (ground truth, runs, configuration, images,
calibration, trajectories, manifests, flight logs; the vocabulary and database cases join the
same table) is built in a fresh folder and its command run as ``stablecues ...`` in a child
process with a memory cap (``resource.setrlimit(RLIMIT_AS)``, so a blow-up fails fast instead of
eating the machine). Each case ends as one of:

==================== ==========================================================================
clear                exit 1 and exactly one line on stderr that names the file (error cases)
correct              exit 0 and the result checks out (cases of inputs that must work)
unnamed              exit 1 and one line, but the line does not name the file
traceback            a Python traceback on stderr
memory               peak RSS over 1 GB, a MemoryError, or killed (by the cap)
silent               exit 0 on a malformed input, or a wrong result / a side effect
executed             the crafted input ran code (its canary file exists)
refused              exit 1 on an input that must work
hang                 no answer within the time limit
other                anything else (another exit status, several lines)
==================== ==========================================================================

Writes ``bench/results/robustness.json``. ``python bench/bench_robustness.py [-k TEXT]``.

``--entrylog`` (a section of its own, about a minute): a map whose last 30 acknowledged adds are
in its entry log only (the writer killed before SQLite took them, as
``tests/database/test_database_entrylog.py`` does it) has one byte of the log flipped at a time,
at offsets spread over every record (its magic, length, CRC, id, body and metadata bytes, and
a stride through its blobs), and is reopened each time: how many of the 30 acknowledged
entries come back, and how many ids the damage cost (the goal: all but the damaged record).

``--segments`` (a section of its own, under a minute): the cost of checking index files before
they answer: a map of 20,000 entries of 300 random ORB words each (the shipped vocabulary,
descriptors not stored) is reopened three times; the reopen time, the first query's time (it
reads every index file once to check its checksum) and the median of the next 20, and the bytes
checked per second; then one byte of a body flipped: what a reader and the writer do.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from malformed_cases import CASES, Case, canary  # noqa: E402

MEMORY_CAP = 4 << 30  # address space of a child; its RSS is what is reported
OVER = 1 << 30  # "memory over 1 GB"
TIME_LIMIT = 180.0

# the child blocks the modules of a "missing dependency" case, runs the command, and on its way
# out writes its own peak RSS (ru_maxrss, kB on Linux) where the parent reads it
CHILD = (
    "import atexit, json, resource, sys\n"
    "peak = lambda: str(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)\n"
    "atexit.register(lambda: open(sys.argv[3], 'w').write(peak()))\n"
    "for m in json.loads(sys.argv[1]):\n"
    "    sys.modules[m] = None\n"
    "from stablecues.cli.main import main\n"
    "sys.exit(main(json.loads(sys.argv[2])))\n"
)


def _limit() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP, MEMORY_CAP))


def run_case(case: Case, folder: Path) -> dict[str, Any]:
    t0 = time.perf_counter()
    try:
        setup = case.build(folder)
    except (Exception, SystemExit) as exc:  # a case that cannot be built is reported, not hidden
        return {"name": case.name, "area": case.area, "expect": case.expect, "outcome": "other",
                "detail": f"building the case failed: {type(exc).__name__}: {exc}"}
    peak_file = folder / "peak_rss_kb"
    argv = [sys.executable, "-c", CHILD, json.dumps(list(setup.block)), json.dumps(setup.argv)]
    argv.append(str(peak_file))
    env = {**os.environ, "MPLBACKEND": "Agg"}
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=_limit, env=env)
    try:
        _, err = proc.communicate(timeout=TIME_LIMIT)
        hung = False
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        hung = True
    peak = int(peak_file.read_text()) * 1024 if peak_file.is_file() else None
    text = err.decode("utf-8", errors="replace")
    lines = [ln for ln in text.splitlines() if ln.strip()]
    outcome, detail = _judge(case, setup, proc.returncode, lines, text, peak, hung, folder)
    return {
        "name": case.name,
        "area": case.area,
        "expect": case.expect,
        "outcome": outcome,
        "exit": proc.returncode,
        "peak_rss_mb": None if peak is None else round(peak / 2**20, 1),
        "seconds": round(time.perf_counter() - t0, 2),
        "stderr": lines[-1][:300] if lines else "",
        "detail": detail,
    }


def _judge(
    case: Case, setup: Any, rc: int, lines: list[str], text: str, peak: int | None, hung: bool, folder: Path
) -> tuple[str, str]:
    if canary(folder).exists():
        return "executed", "the canary file was created"
    if hung:
        return "hang", f"no answer in {TIME_LIMIT:.0f} s"
    if (peak is not None and peak > OVER) or "MemoryError" in text or rc < 0:
        return "memory", f"peak {peak and peak / 2**30:.2f} GB, exit {rc}"
    if "Traceback (most recent call last)" in text:
        return "traceback", lines[-1][:200] if lines else ""
    try:
        problem = setup.check(folder) if setup.check is not None and rc in (0, 1) else None
    except Exception as exc:  # the result is not there to check: as wrong as a wrong one
        problem = f"its result could not be checked ({type(exc).__name__}: {exc})"
    if case.expect == "ok":
        if rc == 0:
            return ("silent", problem) if problem else ("correct", "")
        return ("refused", lines[-1][:200]) if rc == 1 else ("other", f"exit {rc}")
    if rc == 0:
        return "silent", "exit 0 on a malformed input" + (f"; {problem}" if problem else "")
    if problem:
        return "silent", problem
    if rc == 1 and len(lines) == 1:
        return ("clear", "") if setup.names and setup.names in lines[0] else ("unnamed", lines[0][:200])
    return "other", f"exit {rc}, {len(lines)} lines on stderr"


def entrylog_damage(stride: int = 997) -> dict[str, Any]:
    """The ``--entrylog`` section (see the module's docstring)."""
    sys.path.insert(0, str(REPO / "tests" / "database"))
    from test_database_entrylog import _uuid, run_stuck_writer

    from dbkit import make_images
    from stablecues.database import Database, entrylog
    from stablecues.database.entrylog import HEADER_SIZE, log_path, read_log
    from stablecues.vocabulary import train_vocabulary

    voc = train_vocabulary(make_images(), k=6, levels=4, seed=0, levels_up=2, progress=False)
    work = Path(tempfile.mkdtemp(prefix="robust_elog_"))
    try:
        src = work / "src"
        src.mkdir()
        committed, stuck = 4, 30
        acked = run_stuck_writer(voc, src, committed=committed, stuck=stuck)
        db = src / "db.sqlite"
        data = log_path(db).read_bytes()
        rows = read_log(log_path(db), _uuid(db), committed).rows
        sizes = [len(entrylog.encode(r)) for r in rows]
        starts = [HEADER_SIZE + sum(sizes[:k]) for k in range(len(rows))]
        offsets = []
        for k, (start, size) in enumerate(zip(starts, sizes, strict=True)):
            fixed = [0, 4, 8, 12, 20, 28, size - 1]  # magic, length, CRC, id, timestamp, n, meta
            offsets += [(k, start + o) for o in sorted({*fixed, *range(40, size, stride)}) if o < size]
        outcome = {"all_but_damaged": 0, "all": 0, "lost_more": 0, "error": 0}
        worst: list[dict[str, Any]] = []
        t0 = time.perf_counter()
        for k, at in offsets:
            case = work / "case"
            shutil.copytree(src, case)
            bad = bytearray(data)
            bad[at] ^= 0x5A
            log_path(case / "db.sqlite").write_bytes(bytes(bad))
            try:
                with Database(voc, case / "db.sqlite") as reopened:
                    kept = set(int(i) for i in reopened.ids())
            except Exception as exc:  # reported, not hidden
                outcome["error"] += 1
                worst.append({"record": k, "offset": at, "error": f"{type(exc).__name__}: {exc}"})
                shutil.rmtree(case)
                continue
            lost = sorted(set(range(committed, acked)) - kept)
            key = "all" if not lost else "all_but_damaged" if lost == [committed + k] else "lost_more"
            outcome[key] += 1
            if key == "lost_more":
                worst.append({"record": k, "offset": at, "lost": lost})
            shutil.rmtree(case)
        return {"acknowledged_in_log": acked - committed, "records": len(rows), "bytes": len(data),
                "damaged_offsets": len(offsets), "outcomes": outcome, "worst": worst[:10],
                "wall_s": round(time.perf_counter() - t0, 1),
                "offsets": "per record: its magic, length, CRC, id, timestamp, feature count and last "
                           f"byte, and every {stride}th byte of its blobs"}
    finally:
        shutil.rmtree(work, ignore_errors=True)


def segment_checks(entries: int = 20_000, features: int = 300) -> dict[str, Any]:
    """The ``--segments`` section (see the module's docstring)."""
    import numpy as np

    from dbkit import fill  # tests/ is on the path (above)
    from stablecues.database import Database, DatabaseConfig
    from stablecues.database.files import index_dir
    from stablecues.errors import DatabaseError
    from stablecues.vocabulary import default_vocabulary

    voc = default_vocabulary("orb")
    work = Path(tempfile.mkdtemp(prefix="segs_"))
    rng = np.random.default_rng(0)
    try:
        path = work / "map.sqlite"
        images = [rng.integers(0, 256, (features, 32), dtype=np.uint8) for _ in range(entries)]
        probes = [voc.transform(d)[0] for d in images[:: entries // 20]]
        with Database(voc, path, DatabaseConfig(store_descriptors=False)) as db:
            fill(db, voc, images)
            db.flush()
        files = sorted(index_dir(path).glob("seg-*.sci"))
        index_bytes = sum(f.stat().st_size for f in files)
        runs = []
        for _ in range(3):
            t = time.perf_counter()
            db = Database(voc, path, readonly=True)
            reopen = time.perf_counter() - t
            t = time.perf_counter()
            db.query(probes[0], 10)
            first = time.perf_counter() - t
            later = []
            for bow in probes[1:]:
                t = time.perf_counter()
                db.query(bow, 10)
                later.append(time.perf_counter() - t)
            db.close()
            runs.append({"reopen_ms": round(reopen * 1e3, 2), "first_query_ms": round(first * 1e3, 2),
                         "later_query_ms_median": round(sorted(later)[len(later) // 2] * 1e3, 2)})
        extra = min(r["first_query_ms"] - r["later_query_ms_median"] for r in runs)
        raw = bytearray(files[0].read_bytes())
        raw[128 + 8 * 100 + 2] ^= 0x08
        files[0].write_bytes(bytes(raw))
        with Database(voc, path, readonly=True) as reader:
            try:
                reader.query(probes[0], 10)
                reader_says = "answered (damage not seen)"
            except DatabaseError as exc:
                reader_says = str(exc)
        with Database(voc, path) as writer:
            writer_answers = len(writer.query(probes[0], 10))
            writer_check = writer.check()
        return {"entries": entries, "words_per_entry": features, "index_files": len(files),
                "index_bytes": index_bytes, "runs": runs,
                "checked_gb_per_s": round(index_bytes / max(extra, 1e-3) / 1e6, 2),
                "damaged_body": {"reader": reader_says, "writer_results": writer_answers,
                                 "writer_check_after": writer_check}}
    finally:
        shutil.rmtree(work, ignore_errors=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-k", default="", help="only cases whose name contains this text")
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "robustness.json")
    parser.add_argument("--entrylog", action="store_true",
                        help="run the entry-log damage sweep only, merged into --out")
    parser.add_argument("--segments", action="store_true",
                        help="time the index files' checks on reopen and first query only, merged into --out")
    args = parser.parse_args()
    if args.segments:
        res = segment_checks()
        doc = json.loads(args.out.read_text()) if args.out.is_file() else {}
        doc["segment_checks"] = res
        args.out.write_text(json.dumps(doc, indent=1) + "\n")
        print(json.dumps(res, indent=1))
        print(f"written: {args.out}")
        return 0
    if args.entrylog:
        res = entrylog_damage()
        doc = json.loads(args.out.read_text()) if args.out.is_file() else {}
        doc["entrylog_damage"] = res
        args.out.write_text(json.dumps(doc, indent=1) + "\n")
        o = res["outcomes"]
        print(f"entry log, one byte flipped at {res['damaged_offsets']} offsets of {res['records']} records: "
              f"{o['all']} lost nothing, {o['all_but_damaged']} lost the damaged record only, "
              f"{o['lost_more']} lost more, {o['error']} did not open")
        print(f"written: {args.out}")
        return 0
    cases = [c for c in CASES if args.k in c.name]
    results = []
    t0 = time.perf_counter()
    for k, case in enumerate(cases, 1):
        folder = Path(tempfile.mkdtemp(prefix="robust_"))
        try:
            res = run_case(case, folder)
        finally:
            shutil.rmtree(folder, ignore_errors=True)
        results.append(res)
        mark = "" if res["outcome"] in ("clear", "correct") else f"  <- {res['detail'] or res['stderr']}"
        print(f"[{k:3d}/{len(cases)}] {res['outcome']:9s} {case.name}{mark}", flush=True)
    totals: dict[str, int] = {}
    for r in results:
        totals[r["outcome"]] = totals.get(r["outcome"], 0) + 1
    over = sum(1 for r in results if (r.get("peak_rss_mb") or 0) > OVER / 2**20)
    summary = {
        "cases": len(results),
        "clear_errors": totals.get("clear", 0),
        "correct": totals.get("correct", 0),
        "unnamed": totals.get("unnamed", 0),
        "tracebacks": totals.get("traceback", 0),
        "memory_over_1gb": over + sum(1 for r in results if r["outcome"] == "memory" and
                                      (r.get("peak_rss_mb") or 0) <= OVER / 2**20),
        "silent": totals.get("silent", 0),
        "code_executed": totals.get("executed", 0),
        "refused": totals.get("refused", 0),
        "hang": totals.get("hang", 0),
        "other": totals.get("other", 0),
        "by_area": _by_area(results),
    }
    old = json.loads(args.out.read_text()) if args.out.is_file() else {}
    kept = old.get("entrylog_damage")
    doc = {
        "what": "malformed inputs through the CLI, one child process each (bench/bench_robustness.py)",
        "conditions": {
            "python": platform.python_version(),
            "platform": platform.platform(),
            "memory_cap_bytes": MEMORY_CAP,
            "time_limit_s": TIME_LIMIT,
            "cpus": os.cpu_count(),
            "wall_s": round(time.perf_counter() - t0, 1),
            "filter": args.k or None,
        },
        "summary": summary,
        "cases": results,
    }
    if kept is not None:  # the --entrylog section's last result stays
        doc["entrylog_damage"] = kept
    if old.get("segment_checks") is not None:  # and the --segments one's
        doc["segment_checks"] = old["segment_checks"]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    print()
    print(
        f"{summary['cases']} cases: {summary['clear_errors']} clear one-line errors, "
        f"{summary['correct']} correct, "
        f"{summary['unnamed']} unnamed, {summary['tracebacks']} tracebacks, "
        f"{summary['memory_over_1gb']} memory over 1 GB, {summary['silent']} silent, "
        f"{summary['code_executed']} code executed, {summary['refused']} refused, {summary['hang']} hangs, "
        f"{summary['other']} other"
    )
    print(f"written: {args.out}")
    return 0


def _by_area(results: list[dict[str, Any]]) -> dict[str, dict[str, int]]:
    out: dict[str, dict[str, int]] = {}
    for r in results:
        area = out.setdefault(r["area"], {})
        area[r["outcome"]] = area.get(r["outcome"], 0) + 1
    return out


if __name__ == "__main__":
    sys.exit(main())
