"""How long the documentation site takes to build, and how many pages it has.

Builds the site (``mkdocs build --strict -f mkdocs.yml``) into a temporary folder ``--repeats``
times, each in a fresh process, and keeps every wall time from start to exit, their median, and
the number of HTML pages built (the hand-written pages, the getting-started pages, one page per
preset and the API reference, plus MkDocs' 404 page):

    python bench/bench_docs.py                 # writes bench/results/docs.json

Needs the ``docs`` extra (``pip install -e ".[docs]"``). A build with a warning fails (strict).
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
OUT = HERE / "results" / "docs.json"
PACKAGES = ("mkdocs", "mkdocs-material", "mkdocstrings", "mkdocstrings-python", "griffelib")


def build(out: Path) -> float:
    """Build the site into ``out`` in a fresh process; the wall time in seconds."""
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}  # Material's end-of-life banner
    t = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(REPO / "mkdocs.yml"), "-d", str(out)],
        capture_output=True, text=True, cwd=REPO, env=env,
    )
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise SystemExit(f"mkdocs build --strict: exit {proc.returncode}: {proc.stderr.strip()[-500:]}")
    return wall


def versions() -> dict[str, str]:
    out = {}
    for name in PACKAGES:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            continue
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3, help="builds to time (default 3)")
    args = ap.parse_args()
    if args.repeats < 1:
        raise SystemExit("--repeats: expected at least 1")
    walls, pages = [], 0
    with tempfile.TemporaryDirectory(prefix="stablecues-site-") as tmp:
        for k in range(args.repeats):
            out = Path(tmp) / f"site{k}"
            walls.append(round(build(out), 2))
            pages = sum(1 for _ in out.rglob("*.html"))
    doc: dict[str, Any] = {
        "what": "wall time of `mkdocs build --strict` of the documentation site in a fresh process "
                f"(median of {args.repeats}), and the HTML pages it built",
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}",
        "load_1min": round(os.getloadavg()[0], 2),
        "build_s": statistics.median(walls),
        "build_s_each": walls,
        "html_pages": pages,
        "versions": versions(),
    }
    OUT.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"mkdocs build --strict: {doc['build_s']:.2f} s (median of {args.repeats}: "
          f"{', '.join(f'{w:.2f}' for w in walls)}), {pages} HTML pages; wrote {OUT.relative_to(REPO)}")


if __name__ == "__main__":
    main()
