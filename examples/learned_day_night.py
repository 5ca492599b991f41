"""Loop closure across day and night with learned features (``--preset learned``).

    python examples/learned_day_night.py ../shared/data/gardens_point_dev/day_right \\
        ../shared/data/gardens_point_dev/night_right [--places 40] [--preset learned] [--map MAP]

A robot that maps a place by day and comes back at night: the reference traversal (a folder of
images, in name order) is fed to the detector first, then the revisit, one frame at a time, as a
SLAM system would. Every accepted loop is printed with the frame it closes on, its inliers and
the matcher and verifier that decided. On Gardens Point (frame k of each traversal shows about
the same place) the loop's place error is printed too, so ``--preset default`` (ORB: blind by
night) and ``--preset learned`` (XFeat) can be compared.

With ``--map FILE`` the map is kept in a file: run it once on the day folder alone
(``--revisit`` left out) and later on the night folder with the same ``--map``; the detector
reopens the map and continues, numbering frames after the ones already there. Each traversal is
a session of its own (``Frame.session``; the next one a reopened map gives from
``LoopDetector.next_session``): a loop to the other traversal is taken before a view of the one
under way.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from stablecues import Frame, LoopDetector, StableCuesError, preset
from stablecues.imageio import list_images, read_image


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reference", type=Path, help="folder of the first traversal's images")
    ap.add_argument("revisit", type=Path, nargs="?", help="folder of the revisit's images")
    ap.add_argument("--places", type=int, default=None, help="use the first N images of each folder")
    ap.add_argument("--preset", default="learned", help="detector preset (default: learned)")
    ap.add_argument("--map", type=Path, help="keep the map in this file (reopened and continued)")
    args = ap.parse_args(argv)
    try:
        return run(args)
    except StableCuesError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1


def run(args: argparse.Namespace) -> int:
    folders = [args.reference] + ([args.revisit] if args.revisit is not None else [])
    traversals = [list_images(f, f"images of {f}")[: args.places] for f in folders]
    detector = LoopDetector(preset(args.preset), database=str(args.map) if args.map else None)
    start = detector.next_index  # a reopened map: this run numbers on from where it stopped
    session = detector.next_session  # each traversal is a session: loops to another one come first
    first_of = {}  # frame index -> (traversal, place)
    loops, t0 = 0, time.perf_counter()
    index = start
    for t, images in enumerate(traversals):
        for place, path in enumerate(images):
            first_of[index] = (t, place)
            d = detector.process(Frame(index=index, name=path.name, timestamp=math.nan,
                                       image=read_image(path, "bgr"), session=session + t))
            if d.accepted and d.verification is not None:
                loops += 1
                where = first_of.get(d.candidate_frame)
                off = f", {abs(where[1] - place)} places off" if where is not None and where[0] != t else ""
                print(f"loop: {path.name} (frame {index}) -> frame {d.candidate_frame}{off}; "
                      f"{d.verification.n_inliers} inliers, matcher {d.verification.matcher}, "
                      f"verifier {d.verification.method.value}")
            index += 1
    frames = index - start
    ms = (time.perf_counter() - t0) * 1e3 / max(frames, 1)
    print(f"{frames} frames, {loops} loops accepted, {ms:.0f} ms a frame ({args.preset})")
    detector.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
