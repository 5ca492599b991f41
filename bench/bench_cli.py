"""How long the command line takes to answer ``--help`` (issue 35: <= 0.3 s on this machine).

Each of ``stablecues --help`` and ``stablecues COMMAND --help`` (every command of
``stablecues.cli.commands.COMMANDS``) runs in a fresh process, ``REPEATS`` times; the median
and the slowest wall time from start to exit are kept, with what the process imported (numpy,
SciPy, numba, OpenCV, the detector). ``--src DIR`` times another checkout's ``src`` folder
instead of the installed package (``PYTHONPATH`` put first), for before/after figures:

    python bench/bench_cli.py                          # writes bench/results/cli.json
    git worktree add /tmp/old 40dec37 && python bench/bench_cli.py --src /tmp/old/src --label before

The figures are merged into ``cli.json`` under their label (default ``now``); a run replaces
its own label and keeps the others.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "cli.json"
REPEATS = 5
HEAVY = ("numpy", "scipy", "numba", "cv2", "onnxruntime", "stablecues.detection.detector")
# the process itself reports what it imported, after printing the help
PROBE = (
    "import sys, atexit\n"
    "atexit.register(lambda: print('IMPORTED', *[m for m in {heavy!r} if m in sys.modules],\n"
    "                              file=sys.stderr))\n"
    "from stablecues.cli.main import main\n"
    "sys.exit(main({argv!r}))\n"
)


def commands(src: Path | None) -> list[str]:
    """The command names of the tree being timed (an older tree lists them in cli/main.py)."""
    code = ("from stablecues.cli import main as m\n"
            "c = getattr(m, 'COMMANDS', None)\n"
            "if c is None:\n    from stablecues.cli.commands import COMMANDS as c\n"
            "print(' '.join(c))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env(src),
                         check=True)
    return out.stdout.split()


def env(src: Path | None) -> dict[str, str]:
    e = dict(os.environ)
    if src is not None:
        e["PYTHONPATH"] = f"{src}{os.pathsep}{e['PYTHONPATH']}" if e.get("PYTHONPATH") else str(src)
    return e


def time_help(argv: list[str], src: Path | None) -> dict[str, Any]:
    code = PROBE.format(heavy=HEAVY, argv=argv)
    walls, imported = [], []
    for _ in range(REPEATS):
        t = time.perf_counter()
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env(src))
        walls.append(time.perf_counter() - t)
        if out.returncode != 0 or "usage:" not in out.stdout:
            raise SystemExit(f"stablecues {' '.join(argv)}: exit {out.returncode}: "
                             f"{out.stderr.strip()[-300:]}")
        line = next((ln for ln in out.stderr.splitlines() if ln.startswith("IMPORTED")), "IMPORTED")
        imported = line.split()[1:]
    return {"median_s": round(statistics.median(walls), 3), "max_s": round(max(walls), 3),
            "imported": imported}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--src", type=Path, help="time this source tree (its stablecues package) instead")
    ap.add_argument("--label", default="now", help="the key the figures are kept under in cli.json")
    args = ap.parse_args()
    src = args.src.resolve() if args.src else None
    rows: dict[str, Any] = {}
    for name in ["", *commands(src)]:
        argv = [name, "--help"] if name else ["--help"]
        rows[f"stablecues {' '.join(argv)}"] = r = time_help(argv, src)
        print(f"  stablecues {' '.join(argv):22s} median {r['median_s']:.3f} s  max {r['max_s']:.3f} s  "
              f"imports {', '.join(r['imported']) or '-'}", flush=True)
    worst = max(r["median_s"] for r in rows.values())
    print(f"  slowest median {worst:.3f} s (goal <= 0.3 s)")
    doc: dict[str, Any] = json.loads(OUT.read_text()) if OUT.exists() else {}
    doc["what"] = ("wall time of `stablecues [COMMAND] --help` in a fresh process, median and max of "
                   f"{REPEATS}, and the heavy modules it imported")
    doc.setdefault("runs", {})[args.label] = {
        "source": str(src) if src else "installed package",
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}",
        "load_1min": round(os.getloadavg()[0], 2),
        "slowest_median_s": worst,
        "commands": rows,
    }
    OUT.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
