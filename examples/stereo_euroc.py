"""Loop closure on a stereo stream: EuRoC sequences and stereo pairs, one frame at a time.

    python examples/stereo_euroc.py --calib ../shared/data/calibration/EuRoC_stereo.yaml \\
        ../shared/data/euroc/loop_pairs/left_img_0.png,../shared/data/euroc/loop_pairs/right_img_0.png \\
        ../shared/data/euroc/V1_01_micro \\
        ../shared/data/euroc/loop_pairs/left_img_1.png,../shared/data/euroc/loop_pairs/right_img_1.png

Each SOURCE is an EuRoC sequence in ASL layout (the folder holding ``mav0/``; its left and right
images are streamed in time order) or one stereo pair ``LEFT,RIGHT``; the frames are streamed in
the order given. Every accepted loop is printed with the relative pose (candidate camera ->
current camera) that geometric verification found.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from stablecues import Frame, LoopDetector, StableCuesError, preset
from stablecues.geometry import rotation_angle_deg


def read_grey(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise SystemExit(f"error: cannot read image {path}")
    return image


def stereo_pairs(sources: list[str]) -> Iterator[tuple[str, Path, Path]]:
    """(name, left, right) of every frame of the sources, in order."""
    for source in sources:
        if "," in source:
            left_name, right_name = source.split(",", 1)
            yield Path(left_name).name, Path(left_name), Path(right_name)
            continue
        cam0 = Path(source) / "mav0" / "cam0" / "data"
        if not cam0.is_dir():
            raise SystemExit(f"error: {source}: expected LEFT,RIGHT or an EuRoC folder holding "
                             "mav0/cam0/data")
        for image in sorted(cam0.glob("*.png")):
            yield f"{Path(source).name}/{image.name}", image, cam0.parents[1] / "cam1" / "data" / image.name


def describe(pose: np.ndarray | None) -> str:
    if pose is None:
        return "no pose (the check that accepted it gives none)"
    t = pose[:3, 3]
    return f"t = {np.array2string(t, precision=2)} m ({np.linalg.norm(t):.2f} m), " \
           f"rotation {rotation_angle_deg(pose[:3, :3]):.1f} deg"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sources", nargs="+", metavar="SOURCE", help="EuRoC ASL folder, or LEFT,RIGHT images")
    parser.add_argument("--calib", required=True,
                        help="stereo calibration: ORB-SLAM settings, or the left EuRoC sensor.yaml")
    parser.add_argument("--preset", default="default", help="detector preset (default: %(default)s)")
    parser.add_argument("--exclude-recent", type=int, default=None,
                        help="the latest N frames are never proposed as loops (preset: 20)")
    parser.add_argument("--database", default=None, help="SQLite map file, reopened and continued")
    parser.add_argument("--fps", type=float, default=20.0, help="frame rate for timestamps (default: 20)")
    args = parser.parse_args(argv)
    overrides = {} if args.exclude_recent is None else {"query": {"exclude_recent": args.exclude_recent}}
    try:
        config = preset(args.preset, overrides)
        detector = LoopDetector(config, database=args.database, calibration=args.calib)
        names: dict[int, str] = {}
        loops, start = 0, time.perf_counter()
        with detector:
            first = detector.next_index  # a reopened map continues its frame numbers
            for i, (name, left, right) in enumerate(stereo_pairs(args.sources), start=first):
                frame = Frame(index=i, name=name, timestamp=i / args.fps, image=read_grey(left),
                              right=read_grey(right))
                d = detector.process(frame)
                names[i] = name
                if d.accepted:
                    loops += 1
                    inliers = d.verification.n_inliers if d.verification is not None else 0
                    earlier = names.get(d.candidate_frame, "from the map")
                    print(f"loop: frame {i} ({name}) -> frame {d.candidate_frame} ({earlier}), "
                          f"{inliers} inliers, {describe(d.relative_pose)}")
        per_frame = (time.perf_counter() - start) / max(len(names), 1) * 1e3
        print(f"{len(names)} frames, {loops} loops, {per_frame:.0f} ms per frame")
    except StableCuesError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
