"""``stablecues run``: the loop detector over a dataset, into a run directory."""

from __future__ import annotations

import argparse
import json
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .commands import summary
from .options import (
    FOLDER_LAYOUT,
    FORMAT_HELP,
    add_preset_option,
    add_progress_option,
    add_rosbag_options,
    add_vocabulary_option,
    config_with_vocabulary,
    is_rosbag,
    presets_epilog,
    rosbag_options,
    vocabulary_from_args,
)

if TYPE_CHECKING:
    from ..detection import DetectorConfig
    from ..detection.run import RunSummary
    from ..viz import RerunLogger


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "run", help=summary("run"),
        description="Run the loop detector over a dataset's frames in order and write a run directory "
                    "(decisions.csv, similarity matrix, timings, match pictures) for `stablecues eval`.",
        epilog=f"{FOLDER_LAYOUT}\n{presets_epilog()}", formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", type=Path, help="dataset folder or ROS bag")
    p.add_argument("--format", default="auto", help=FORMAT_HELP)
    p.add_argument("--calib", metavar="FILE",
                   help="camera calibration to use instead of the dataset's own (for a folder: in place "
                        "of DIR/calib.yaml): an ORB-SLAM settings yaml, a KITTI calib.txt, an EuRoC "
                        "sensor.yaml (its cam1 found beside it) or a TUM camera name fr1 / fr2 / fr3")
    add_rosbag_options(p)
    add_preset_option(p)
    add_vocabulary_option(p)
    p.add_argument("--out", type=Path, required=True, help="run directory to write")
    p.add_argument("--gt", type=Path, help="loop ground truth file to record with the run")
    p.add_argument("--db", type=Path, help="database file (default: RUN_DIR/map.sqlite)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the run already in --out (its own files only); without it an existing, "
                        "non-empty --out is refused")
    p.add_argument("--max-frames", type=int, help="stop after this many frames")
    p.add_argument("--pictures", type=int, default=4, help="match pictures of accepted loops to save")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a setting, e.g. query.alpha=0.2 or verification.min_agree=3 "
                        "(VALUE is JSON; repeatable)")
    add_progress_option(p)
    g = p.add_argument_group("watching it live (the rerun extra)")
    g.add_argument("--rerun", type=Path, metavar="FILE.rrd",
                   help="log each frame (image, kept keypoints, top scores, accepted loops with their "
                        "matches, trajectory and loop edges when poses are known, stage times) to this "
                        "Rerun recording (replaced if it exists); open it with `rerun FILE.rrd`")
    g.add_argument("--rerun-spawn", action="store_true",
                   help="also stream to a Rerun viewer started now (needs the viewer and a display)")
    return p


def _no_constant(name: str) -> Any:
    raise ValueError(name)


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["query.alpha=0.2", "masking.mode=\\"hard\\""]`` -> nested override dict."""
    from ..errors import ConfigError

    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        try:
            value = json.loads(raw, parse_constant=_no_constant)
        except json.JSONDecodeError:
            value = raw  # bare strings
        except ValueError:  # NaN, Infinity: never a value a setting means
            raise ConfigError(f"--set {item!r}: {raw.strip()} is not a finite number; give a number "
                              "(or null where a setting may be off)") from None
        node = out
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out


def _vocabulary_meta(args: argparse.Namespace, vocabulary: Any, kind: str) -> dict[str, str]:
    """What the run's meta records of its vocabulary (nothing for the shipped one)."""
    if vocabulary is not None:
        return {"vocabulary": str(args.vocab), "vocabulary_fingerprint": vocabulary.info().fingerprint}
    return {"vocabulary": "incremental"} if kind == "incremental" else {}


def run(args: argparse.Namespace) -> int:
    from ..datasets import open_dataset
    from ..detection import preset
    from ..detection.run import run_dataset
    from ..errors import ConfigError
    from ..outputs import check_output

    if args.rerun is not None:  # the Rerun SDK writes it: never through a link, over a device, ...
        check_output(args.rerun, "Rerun recording")
    if args.resume and args.overwrite:
        raise ConfigError("--resume continues the run in --out and --overwrite replaces it: give one")
    config = config_with_vocabulary(preset(args.preset, parse_overrides(args.set)), args)
    vocabulary = vocabulary_from_args(args)
    bag = rosbag_options(args) if is_rosbag(args) else {}
    if args.calib is not None:  # read now: a bad file is refused before the run folder is made
        from ..geometry import load_calibration

        load_calibration(args.calib)
        bag["calibration"] = args.calib
    dataset = open_dataset(args.dataset, format=args.format, **bag)
    gt = args.gt if args.gt is not None else dataset.ground_truth_path()
    described = dataset.describe() if hasattr(dataset, "describe") else {}
    meta = {**described, "dataset": str(args.dataset), "format": getattr(dataset, "format", args.format),
            "ground_truth": None if gt is None else str(gt), "overrides": args.set}
    meta.update(_vocabulary_meta(args, vocabulary, config.vocabulary))
    with ExitStack() as stack:
        observers: list[Any] = []
        segmenter = None
        if args.rerun is not None or args.rerun_spawn:
            from ..viz import RerunLogger

            logger = stack.enter_context(RerunLogger(
                args.rerun, spawn=args.rerun_spawn, image_of=lambda i: dataset[i].image))
            observers.append(logger)
            segmenter = _watched_segmenter(config, logger)
        summary = run_dataset(dataset, config, args.out, preset_name=args.preset, meta=meta,
                              database=args.db, resume=args.resume, overwrite=args.overwrite,
                              max_frames=args.max_frames, pictures=args.pictures,
                              progress=not args.no_progress, segmenter=segmenter, vocabulary=vocabulary,
                              observers=observers)
    statuses = ", ".join(f"{k} {v}" for k, v in sorted(summary.statuses.items()))
    if summary.already_complete:
        print(f"{summary.out_dir}: the run is already complete; nothing to resume")
    elif summary.resumed_from:
        print(f"resumed at frame {summary.resumed_from}")
    ms = summary.ms_per_frame
    speed = f"{ms:.1f} ms/frame" if ms == ms else "no frame timed"
    if ms == ms and summary.frames > 1:
        speed += f" (the first, loading, {summary.first_frame_ms:.0f} ms, apart)"
    loops = "1 loop" if summary.loops == 1 else f"{summary.loops} loops"
    print(f"{summary.frames} frames, {loops} accepted, {speed}; {statuses}")
    if summary.mask_fallbacks:
        print(f"semantic masking fell back to all features on {summary.mask_fallbacks} frames")
    hint = exclusion_hint(summary, config)
    if hint:
        print(hint)
    print(f"run written to {summary.out_dir}" + (f" (ground truth: {gt})" if gt else ""))
    if args.rerun is not None:
        print(f"Rerun recording written to {args.rerun} (open it with: rerun {args.rerun})")
    return 0


def exclusion_hint(summary: RunSummary, config: DetectorConfig) -> str | None:
    """Why no loop was found when the exclusion window left (almost) nothing to query, or None.

    A frame is only compared with frames older than the window (``query.exclude_recent`` frames,
    ``query.exclude_recent_s`` seconds): on a sequence not much longer than the window, no frame
    or few have anything to query.
    """
    n, close = summary.frames, summary.statuses.get("close_matches_only", 0)
    if n == 0 or summary.loops or 2 * close < n:
        return None
    q = config.query
    window = f"query.exclude_recent = {q.exclude_recent} frames"
    if q.exclude_recent_s is not None:
        window += f", query.exclude_recent_s = {q.exclude_recent_s:g} s"
    which = "none of the" if close == n else f"{close} of the"
    return (f"hint: {which} {n} frames had an earlier frame outside the exclusion window ({window}) "
            "to compare with; on a short sequence lower it, e.g. "
            f"--set query.exclude_recent={max(1, n // 4)}")


def _watched_segmenter(config: DetectorConfig, logger: RerunLogger) -> Any | None:
    """The shipped segmentation network as the detector would run it, watched by ``logger`` so the
    keypoints are coloured by the classes the detector saw; None when the run segments nothing
    with the network."""
    segments = (config.masking is not None and config.masking.mode != "none") or config.weighting is not None
    if not segments or config.semantic_source != "network":
        return None
    from ..semantics.inference import SegmentationModel

    model = SegmentationModel.load(precision=config.segmentation_precision)
    samples = config.segmentation_samples
    return logger.watch_segmenter(lambda image: model.predict(image, samples))
