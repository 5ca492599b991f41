"""Print the README's results table from the bench results (``bench/results/learned.json``,
``loops.json`` and ``incremental.json``), so that every figure of the table is one a bench
script wrote.

    python scripts/readme_results.py          # the table, as the README has it

``tests/test_readme.py`` checks that the README holds exactly this table.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
#: (label, key in learned.json; None for the row of loops.json's DBoW2 baseline)
ROWS = (("`default`", "default"), ("`fast`", "fast"), ("`bow` (DLoopDetector)", "bow"),
        ("DBoW2 top-1, raw score", None), ("`learned`", "learned"))
#: rows of incremental.json's sets: (label, "preset vocabulary")
INCREMENTAL_ROWS = (("`fast --vocab incremental`", "fast incremental"),
                    ("`learned --vocab incremental`", "learned incremental"))
GARDENS = ("day_left->day_right", "day_right->night_right", "day_left->night_right")


def _date(path: Path) -> str:
    """The day the results file was last committed (else its modification day)."""
    try:
        out = subprocess.run(["git", "log", "-1", "--format=%cs", "--", str(path)], cwd=REPO,
                             capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        out = ""
    if out:
        return out
    import datetime as dt

    return dt.date.fromtimestamp(path.stat().st_mtime).isoformat()


def _cell(value: Any, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def table() -> str:
    learned = json.loads((RESULTS / "learned.json").read_text())
    loops = json.loads((RESULTS / "loops.json").read_text())
    lines = [
        "| preset | CamVid train_drives | CamVid val_drive | corridor | GP left -> right | GP day -> night "
        "| GP left -> night |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, key in ROWS:
        if key is None:
            base = "dbow2 top-1, raw score swept"
            rev = [loops["revisits"][s][base]["r_at_100p"] for s in ("train_drives", "val_drive", "corridor")]
            gardens: list[Any] = [None, None, None]
        else:
            rev = [learned["revisits"][s][key]["exact"]["r_at_100p"] for s in ("train_drives", "val_drive")]
            rev.append(learned["corridor"]["corridor"][key]["exact"]["r_at_100p"])
            gardens = [learned["gardens"][p][key]["pm8"]["r_at_100p"] for p in GARDENS]
        cells = [_cell(rev[0], 3), _cell(rev[1], 3), _cell(rev[2], 3), *(_cell(g) for g in gardens)]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    inc = json.loads((RESULTS / "incremental.json").read_text())["sets"]
    for label, key in INCREMENTAL_ROWS:
        rev = [inc[s][key]["exact"]["r_at_100p"] for s in ("train_drives", "val_drive", "corridor")]
        gardens = [inc[p][key]["pm8"]["r_at_100p"] for p in GARDENS]
        cells = [*(_cell(r, 3) for r in rev), *(_cell(g) for g in gardens)]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    when = max(_date(RESULTS / f) for f in ("learned.json", "loops.json", "incremental.json"))
    lines.append("")
    lines.append(f"R@100P, exact cell of the ground truth (Gardens Point: within 8 places); measured up to "
                 f"{when} on a shared 2-core x86 machine (`bench/bench_learned.py`, `bench/bench_loops.py`, "
                 "`bench/bench_incremental.py`).")
    return "\n".join(lines)


if __name__ == "__main__":
    print(table())
