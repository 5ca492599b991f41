#!/usr/bin/env python
"""Build a CamVid revisit sequence: the recipe of ``../shared/data/camvid_revisit_dev``, for any split.

Reproduces how the development sets ``train_drives`` (CamVid ``train``) and ``val_drive`` (``val``)
were made, so that the same kind of sequence can be built once from ``test`` for a held-out report:

1. *Moving frames*, per drive (the file-name prefix, e.g. ``0001TP``): a frame is kept when the median
   Lucas-Kanade flow of corners tracked from the last kept frame is at least ``--still-px`` (3 px of
   480, ``STILL_PX`` of ``bench/bench_loops.py``): the car is not standing still there.
2. *First traversal*: the even moving frames of every revisited drive, drive after drive, unaltered.
3. *Second traversal*: the odd moving frames, in the same order, cut into 4 near-equal chunks
   (``np.array_split``) with a *distractor run* between consecutive chunks: 3 runs of 6 consecutive
   moving frames of another drive, run k starting at moving frame ``floor(k * (M - 6) / 3)`` of that
   drive's M moving frames.
4. *Changing appearance*: every frame after the first traversal (second traversal and distractors)
   is altered by gamma, a per-channel colour cast, contrast about the image mean, Gaussian blur and
   Gaussian noise. Each parameter follows a smooth curve over the altered part: random key values
   (from ``--seed``) at 5 evenly spaced points, eased in between. The ranges are those measured on
   the development sets (a per-frame fit of the altered frames to their originals): gamma 0.5-1.6
   (its key values alternate between darker and brighter, as the development sets swing from one
   end to the other), contrast 0.7-1.2, a colour cast of B, G, R gains within 0.8-1.2 (a
   zero-mean change of norm 0.12-0.24), blur sigma 0.5-1.5 px, noise sigma 0.5-6 grey levels
   (log-uniform: mostly light, at times heavy, as measured).
5. *Ground truth* ``gt.png`` (N x N, 255 = loop, row = the later frame), on the ORIGINAL frames: each
   second-traversal frame loops with the first-traversal frames next to it in its drive (moving
   frames k - 1 and k + 1) and with every first-traversal frame of its drive sharing at least 60
   SIFT matches (ratio test 0.8, later frame against earlier) that are inliers of a RANSAC
   fundamental matrix (1 px, confidence 0.99). First-traversal and distractor rows have no loops.
6. ``frames/0001.jpg ...`` (JPEG q95), ``labels/0001.png ...`` (CamVid's own class ids of each
   frame's original, the label PNG copied as is) and ``sources.csv`` (frame,split,source).

Distractors come from ``--distractor-split`` (default ``train``), from a drive that is not revisited.
By default that is ``0006R0`` (what ``val_drive`` used; it appears in no other split), else the
longest eligible drive; when the distractor split is the revisited split, its shortest drive (what
``train_drives`` used: ``0001TP`` of train) and the other drives are revisited. For ``test`` both
its drives are revisited and the distractors are train's ``0006R0``: train's ``0001TP`` is the same
drive as test's (it ends where test's begins, so it may show the same places, unlabelled loops).

Fidelity: ``--split train --distractor-split train`` rebuilds ``train_drives`` closely (297 frames
against 298, the same segments, 139 loop rows, 365 loop cells against 383). CamVid ``val`` is
sampled at 15 fps where ``train`` and ``test`` are at 1 fps, and ``val_drive`` keeps only 31 of its
101 frames (by a rule not recoverable from the data); the 3 px rule keeps 62 (80 frames in all),
``--still-px 7`` keeps 31 (49 frames, 15 loop rows, as ``val_drive``).

Run: ``python scripts/make_revisit_set.py --split test --out /tmp/revisit_test [--seed 0]``.
Derived data: write it outside the repository (never into it), like the data it comes from.
"""

from __future__ import annotations

import argparse
import csv
import shutil
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_CAMVID = ROOT.parent / "shared" / "data" / "camvid"

STILL_PX = 3.0  # median flow (of 480 px) from the last kept frame under this: the car stands still
CHUNKS = 4  # the second traversal is cut into this many chunks, a distractor run between each two
RUN_LENGTH = 6  # frames per distractor run
PREFERRED_DISTRACTOR = "0006R0"  # val_drive's distractor drive
RATIO = 0.8  # Lowe's ratio test
MIN_INLIERS = 60  # RANSAC-verified SIFT matches for a ground-truth loop
RANSAC_PX = 1.0
RANSAC_CONFIDENCE = 0.99
JPEG_QUALITY = 95
KEYS = 5  # key values per appearance parameter, evenly spaced over the altered frames
GAMMA = (0.5, 1.6)  # extremes; key values alternate darker / brighter, 40-100 % of the way in log
CONTRAST = (0.7, 1.2)
CAST = (0.12, 0.24)  # norm of the zero-mean change of the B, G, R gains (gains within 0.8-1.2)
BLUR = (0.5, 1.5)  # Gaussian sigma, px
NOISE = (0.5, 6.0)  # Gaussian sigma, grey levels, drawn log-uniform (mostly light, at times heavy)

Role = Literal["first", "second", "distractor"]


class BuildError(Exception):
    """Bad input: reported as one line, without a traceback."""


@dataclass(frozen=True)
class Source:
    """One CamVid frame: its image and label files."""

    split: str
    image: Path
    label: Path

    @property
    def drive(self) -> str:
        return self.image.name.split("_")[0]


@dataclass(frozen=True)
class Entry:
    """One output frame: its source, its role and its place among its drive's moving frames."""

    source: Source
    role: Role
    position: int


@dataclass(frozen=True)
class Look:
    """The appearance change of one frame."""

    gamma: float
    contrast: float
    cast: tuple[float, float, float]  # B, G, R gains
    blur: float
    noise: float


@dataclass(frozen=True)
class Features:
    points: np.ndarray  # (n, 2) float32
    descriptors: np.ndarray | None  # (n, 128) float32


# ------------------------------------------------------------------------------------------ input
def read_split(camvid: Path, split: str) -> dict[str, list[Source]]:
    """The frames of one CamVid split grouped by drive (drives and frames in name order)."""
    images, labels = camvid / split, camvid / f"{split}annot"
    for folder in (images, labels):
        if not folder.is_dir():
            raise BuildError(f"{folder}: no such folder (expected CamVid's {split}/ and {split}annot/)")
    files = sorted(images.glob("*.jpg")) + sorted(images.glob("*.png"))
    if not files:
        raise BuildError(f"{images}: no frames (*.jpg or *.png)")
    drives: dict[str, list[Source]] = {}
    for f in sorted(files, key=lambda p: p.name):
        label = labels / f"{f.stem}.png"
        if not label.is_file():
            raise BuildError(f"{label}: label of {f.name} not found")
        src = Source(split, f, label)
        drives.setdefault(src.drive, []).append(src)
    return drives


def read_grey(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise BuildError(f"{path}: not a readable image")
    return img


def read_colour(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise BuildError(f"{path}: not a readable image")
    return img


# ------------------------------------------------------------------------------------------ moving frames
def median_flow(a: np.ndarray, b: np.ndarray) -> float:
    """Median displacement (px) of corners tracked from grey image a to b (pyramidal LK flow)."""
    p = cv2.goodFeaturesToTrack(a, 400, 0.01, 7)
    if p is None:
        return float("inf")
    q, status, _ = cv2.calcOpticalFlowPyrLK(a, b, p, None, winSize=(21, 21), maxLevel=3)  # type: ignore[call-overload]
    ok = status.ravel() == 1
    if not ok.any():
        return float("inf")
    return float(np.median(np.linalg.norm((q - p).reshape(-1, 2)[ok], axis=1)))


def moving_frames(frames: Sequence[Source], still_px: float) -> list[Source]:
    """The frames of one drive where the car has moved at least ``still_px`` since the last kept one."""
    kept: list[Source] = []
    last: np.ndarray | None = None
    for src in frames:
        grey = read_grey(src.image)
        if last is not None and median_flow(last, grey) < still_px:
            continue
        kept.append(src)
        last = grey
    return kept


# ------------------------------------------------------------------------------------------ sequence
def choose_drives(
    split: str,
    drives: dict[str, list[Source]],
    distractor_split: str,
    distractor_drives: dict[str, list[Source]],
    revisit: list[str] | None,
    distractor: str | None,
) -> tuple[list[str], str]:
    """The revisited drives and the distractor drive (see the module docstring for the defaults)."""
    for d in revisit or []:
        if d not in drives:
            raise BuildError(f"drive {d} is not in split {split} (it has {', '.join(drives)})")
    if distractor is None and revisit is None and split == distractor_split:
        if len(drives) < 2:
            raise BuildError(f"split {split} has one drive: give --distractor-split another split")
        distractor = min(drives, key=lambda d: (len(drives[d]), d))
    if revisit is None:
        revisit = [d for d in drives if not (split == distractor_split and d == distractor)]
    if not revisit:
        raise BuildError(f"no drive of split {split} is left to revisit besides the distractor drive")
    if distractor is None:
        eligible = [d for d in distractor_drives if d not in revisit]
        if not eligible:
            raise BuildError(f"split {distractor_split} has no drive that is not revisited: choose another")
        distractor = (PREFERRED_DISTRACTOR if PREFERRED_DISTRACTOR in eligible
                      else max(eligible, key=lambda d: (len(distractor_drives[d]), d)))
    if distractor not in distractor_drives:
        raise BuildError(f"drive {distractor} is not in split {distractor_split}")
    if distractor in revisit:
        raise BuildError(f"drive {distractor} is revisited: distractors must come from another drive")
    return revisit, distractor


def distractor_runs(moving: Sequence[Source], runs: int, length: int) -> list[list[Source]]:
    """``runs`` runs of ``length`` consecutive moving frames; run k starts at floor(k (M - length) / runs)."""
    if len(moving) < length:
        raise BuildError(f"distractor drive has {len(moving)} moving frames, fewer than a run of {length}")
    starts = [int(k * (len(moving) - length) / runs) for k in range(runs)]
    return [list(moving[s:s + length]) for s in starts]


def build_sequence(revisited: dict[str, list[Source]], runs: list[list[Source]]) -> list[Entry]:
    """First traversals (even moving frames), then the second traversals (odd) in chunks with runs between."""
    first = [Entry(s, "first", k) for m in revisited.values() for k, s in enumerate(m) if k % 2 == 0]
    second = [Entry(s, "second", k) for m in revisited.values() for k, s in enumerate(m) if k % 2 == 1]
    if not second:
        raise BuildError("no second traversal: the revisited drives have fewer than 2 moving frames")
    chunks = [list(c) for c in np.array_split(np.arange(len(second)), len(runs) + 1)]
    order = list(first)
    for i, chunk in enumerate(chunks):
        order += [second[k] for k in chunk]
        if i < len(runs):
            order += [Entry(s, "distractor", -1) for s in runs[i]]
    return order


# ------------------------------------------------------------------------------------------ appearance
def schedule(n: int, rng: np.random.Generator) -> list[Look]:
    """A smoothly changing appearance over n frames: random key values, eased in between."""
    keys = np.linspace(0.0, 1.0, KEYS)
    start = int(rng.integers(2))  # 0: the first key brightens (gamma < 1), 1: it darkens
    extreme = np.log([GAMMA[(k + start) % 2] for k in range(KEYS)])  # alternately brighter, darker
    log_gamma = extreme * rng.uniform(0.4, 1.0, KEYS)
    contrast = rng.uniform(*CONTRAST, KEYS)
    angle = rng.uniform(0.0, 2.0 * np.pi, KEYS)
    plane = np.array([[1.0, -1.0, 0.0], [1.0, 1.0, -2.0]]) / np.sqrt([[2.0], [6.0]])  # zero-mean directions
    direction = np.cos(angle)[:, None] * plane[0] + np.sin(angle)[:, None] * plane[1]  # (KEYS, 3)
    cast = 1.0 + (rng.uniform(*CAST, KEYS)[:, None] * direction).T  # (3, KEYS)
    blur = rng.uniform(*BLUR, KEYS)
    noise = np.exp(rng.uniform(np.log(NOISE[0]), np.log(NOISE[1]), KEYS))

    def at(values: np.ndarray, u: float) -> float:
        j = min(int(u * (KEYS - 1)), KEYS - 2)
        t = (u - keys[j]) / (keys[j + 1] - keys[j])
        t = t * t * (3.0 - 2.0 * t)  # smoothstep: no kinks at the key points
        return float(values[j] + t * (values[j + 1] - values[j]))

    looks = []
    for i in range(n):
        u = i / max(n - 1, 1)
        looks.append(Look(gamma=float(np.exp(at(log_gamma, u))),
                          contrast=at(contrast, u),
                          cast=(at(cast[0], u), at(cast[1], u), at(cast[2], u)),
                          blur=at(blur, u), noise=at(noise, u)))
    return looks


def alter(image: np.ndarray, look: Look, rng: np.random.Generator) -> np.ndarray:
    """Gamma, colour cast, contrast about the mean, blur, then noise (BGR uint8 in and out)."""
    x = np.power(image.astype(np.float32) / 255.0, look.gamma)
    x *= np.asarray(look.cast, np.float32)
    mean = float(x.mean())
    x = ((x - mean) * look.contrast + mean) * 255.0
    x = cv2.GaussianBlur(x, (0, 0), look.blur)
    x += rng.normal(0.0, look.noise, x.shape).astype(np.float32)
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------------------ ground truth
def sift_features(sift: cv2.SIFT, path: Path) -> Features:
    keypoints, descriptors = sift.detectAndCompute(read_grey(path), None)
    points = np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2)
    return Features(points, descriptors)


def shares_view(later: Features, earlier: Features, matcher: cv2.BFMatcher) -> bool:
    """At least MIN_INLIERS ratio-test SIFT matches that fit one RANSAC fundamental matrix."""
    if later.descriptors is None or earlier.descriptors is None:
        return False
    if min(len(later.points), len(earlier.points)) < 2:
        return False
    pairs = matcher.knnMatch(later.descriptors, earlier.descriptors, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
    if len(good) < MIN_INLIERS:
        return False
    a = later.points[[m.queryIdx for m in good]]
    b = earlier.points[[m.trainIdx for m in good]]
    _, mask = cv2.findFundamentalMat(a, b, cv2.FM_RANSAC, RANSAC_PX, RANSAC_CONFIDENCE)
    return mask is not None and int(mask.sum()) >= MIN_INLIERS


def ground_truth(order: Sequence[Entry]) -> np.ndarray:
    """N x N bool: row = a later (second-traversal) frame, column = a first-traversal frame it re-views."""
    gt = np.zeros((len(order), len(order)), bool)
    first: dict[tuple[str, int], int] = {
        (e.source.drive, e.position): i for i, e in enumerate(order) if e.role == "first"
    }
    sift = cv2.SIFT.create()
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    cache: dict[Path, Features] = {}

    def features(src: Source) -> Features:
        if src.image not in cache:
            cache[src.image] = sift_features(sift, src.image)
        return cache[src.image]

    for i, e in enumerate(order):
        if e.role != "second":
            continue
        drive = e.source.drive
        for k in (e.position - 1, e.position + 1):
            if (drive, k) in first:
                gt[i, first[(drive, k)]] = True
        for (d, _), j in first.items():
            if d == drive and not gt[i, j]:
                cv2.setRNGSeed(0)
                gt[i, j] = shares_view(features(e.source), features(order[j].source), matcher)
    return gt


# ------------------------------------------------------------------------------------------ output
def previous_set(out: Path, overwrite: bool) -> list[Path]:
    """The files of a revisit set already in ``out`` (refused without ``overwrite``)."""
    if out.exists() and not out.is_dir():
        raise BuildError(f"{out}: not a folder")
    written = [*out.glob("frames/*.jpg"), *out.glob("labels/*.png"), out / "gt.png", out / "sources.csv"]
    existing = [p for p in written if p.exists()]
    if existing and not overwrite:
        raise BuildError(f"{out}: already holds a revisit set ({len(existing)} files): pass --overwrite")
    return existing


def prepare_out(out: Path, overwrite: bool) -> None:
    """An output folder with empty ``frames/`` and ``labels/`` (only this script's files are removed)."""
    for p in previous_set(out, overwrite):
        p.unlink()
    (out / "frames").mkdir(parents=True, exist_ok=True)
    (out / "labels").mkdir(parents=True, exist_ok=True)


def write_set(out: Path, order: Sequence[Entry], gt: np.ndarray, seed: int) -> None:
    rng = np.random.default_rng(seed)
    start = next(i for i, e in enumerate(order) if e.role != "first")
    looks = schedule(len(order) - start, rng)
    with (out / "sources.csv").open("w", newline="") as fh:
        table = csv.writer(fh, lineterminator="\n")
        table.writerow(["frame", "split", "source"])
        for i, e in enumerate(order):
            name = f"{i + 1:04d}"
            image = read_colour(e.source.image)
            if i >= start:
                image = alter(image, looks[i - start], rng)
            target = out / "frames" / f"{name}.jpg"
            if not cv2.imwrite(str(target), image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]):
                raise BuildError(f"{out / 'frames'}: cannot write {name}.jpg")
            shutil.copyfile(e.source.label, out / "labels" / f"{name}.png")
            table.writerow([f"{name}.jpg", e.source.split, e.source.image.name])
    if not cv2.imwrite(str(out / "gt.png"), gt.astype(np.uint8) * 255):
        raise BuildError(f"{out}: cannot write gt.png")


def build(args: argparse.Namespace) -> str:
    camvid: Path = args.camvid
    drives = read_split(camvid, args.split)
    other = drives if args.distractor_split == args.split else read_split(camvid, args.distractor_split)
    revisit, distractor = choose_drives(args.split, drives, args.distractor_split, other,
                                        args.drives, args.distractor_drive)
    previous_set(args.out, args.overwrite)  # refuse early, before the slow part
    revisited = {d: moving_frames(drives[d], args.still_px) for d in revisit}
    runs = distractor_runs(moving_frames(other[distractor], args.still_px), CHUNKS - 1, RUN_LENGTH)
    order = build_sequence(revisited, runs)
    gt = ground_truth(order)
    prepare_out(args.out, args.overwrite)
    write_set(args.out, order, gt, args.seed)
    roles = [e.role for e in order]
    rows = int(gt.any(axis=1).sum())
    cells = int(gt.sum())
    return (f"{args.out}: {len(order)} frames ({roles.count('first')} first traversal, "
            f"{roles.count('second')} second, {roles.count('distractor')} distractors from "
            f"{args.distractor_split}/{distractor}; revisited {args.split}/{'+'.join(revisit)}), "
            f"{rows} loop rows, {cells} loop cells ({cells / max(rows, 1):.2f} per loop row)")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", required=True, help="CamVid split to revisit (train, val, test)")
    ap.add_argument("--out", type=Path, required=True, help="output folder (outside the repository)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the appearance changes and their noise")
    ap.add_argument("--distractor-split", default="train", help="split the distractor runs come from")
    ap.add_argument("--distractor-drive", default=None, help="drive of the distractor runs (default: above)")
    ap.add_argument("--drives", nargs="+", default=None, help="drives to revisit (default: all)")
    ap.add_argument("--camvid", type=Path, default=DEFAULT_CAMVID,
                    help="CamVid root (<split>/, <split>annot/)")
    ap.add_argument("--still-px", type=float, default=STILL_PX, help="median flow under this: a still frame")
    ap.add_argument("--overwrite", action="store_true", help="replace a revisit set already in --out")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    try:
        print(build(args), flush=True)
    except (BuildError, OSError) as exc:
        print(f"make_revisit_set: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
