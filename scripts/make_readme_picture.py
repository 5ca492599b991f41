"""Remake the README's picture: an accepted loop from ``stablecues demo``'s default run (its own
synthetic town, seed 0; nothing from any dataset), as the run's match picture shows it, halved.

    python scripts/make_readme_picture.py      # about 90 s: runs the demo in a temporary folder
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import cv2

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "docs" / "img" / "demo_loop.jpg"
LOOP = "loop_00105_00020.png"  # frame 105 on the second lap closes with frame 20


def main() -> None:
    from stablecues.demo import run_demo

    with tempfile.TemporaryDirectory() as tmp:
        result = run_demo(Path(tmp), progress=False)
        picture = result.runs["default"] / "matches" / LOOP
        if not picture.is_file():
            sys.exit(f"{picture}: the demo's default run did not accept that loop this time")
        image = cv2.imread(str(picture))
        small = cv2.resize(image, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
        OUT.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(OUT), small, [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
