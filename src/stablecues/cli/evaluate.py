"""``stablecues eval``: score a run directory against a loop ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, cast

from .commands import summary
from .options import add_pose_truth_options, loop_rule_from_args

if TYPE_CHECKING:
    from ..groundtruth import GroundTruth
    from ..runs import Run

#: the loop matrix `eval --gt-poses` makes, written into the run's folder
POSE_GT_FILE = "gt_poses.npy"


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "eval",
        help=summary("eval"),
        description="Recall at 100 % precision (swept over every distinct score), the PR curve, its area, "
        "the counts, the loss funnel (for each positive query, the stage where its true loop was lost) "
        "and the per-stage timing of a run. Writes eval_<protocol>.json into the run directory.",
    )
    p.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="directory written by 'stablecues run'")
    p.add_argument(
        "--gt",
        type=Path,
        help="ground truth: .mat, .npy, .npz, image, or VPR-Bench ground_truth_new.npy "
        "(default: the one recorded in the run's meta.json)",
    )
    p.add_argument(
        "--gt-poses",
        type=Path,
        metavar="SOURCE",
        help="make the ground truth from poses instead (the loop rule below): the run's dataset or "
        "another dataset whose frames carry poses, or a trajectory file (TUM, KITTI, EuRoC data.csv) "
        "matched to the run's frames by their timestamps; as `stablecues gt poses` writes it",
    )
    p.add_argument(
        "--protocol",
        choices=("exact", "tolerance", "ibow"),
        default="exact",
        help="when a detection (query i, frame c) is right: exact (default): the ground truth has the "
        "loop (i, c); ibow (iBoW-LCD): row i has a loop within +-N frames of c; tolerance: a loop within "
        "+-N frames of (i, c) on both axes (the demo's report uses tolerance 2)",
    )
    p.add_argument(
        "--tolerance",
        type=int,
        default=None,
        metavar="N",
        help="+-N frames; required by the tolerance and ibow protocols (the README and the demo use 2)",
    )
    p.add_argument(
        "--allow-incomplete",
        action="store_true",
        help="score the frames of an interrupted run (refused otherwise)",
    )
    p.add_argument(
        "--exclude",
        type=int,
        default=None,
        metavar="N",
        help="frames just before a query that are never loops (default: the run's 'exclude', else 0)",
    )
    p.add_argument(
        "--exclude-s", type=float, default=0.0, metavar="S", help="also exclude the last S seconds"
    )
    p.add_argument("--json", type=Path, metavar="OUT", help="also write the results here")
    p.add_argument("--gt-variable", help="variable name inside a .mat / .npz ground truth")
    p.add_argument(
        "--gt-view",
        choices=("all", "left", "right", "pair"),
        default=None,
        help="images of an interleaved left/right release (FAB-MAP) to keep "
        "(default: the run's 'gt_view', else all)",
    )
    p.add_argument(
        "--gt-orientation",
        choices=("auto", "lower", "upper"),
        default="auto",
        help="which half of the matrix holds the loops (auto: detect)",
    )
    p.add_argument(
        "--detections",
        choices=("accepted", "all"),
        default="accepted",
        help="score only accepted loops (default) or every frame's candidate",
    )
    p.add_argument(
        "--score",
        choices=("score", "raw_score"),
        default="score",
        help="the decisions.csv column that ranks detections for the precision-recall sweep: score "
        "(default: the detector's confidence) or raw_score (the BoW similarity before normalisation)",
    )
    add_pose_truth_options(p)
    return p


def format_summary(doc: dict) -> str:
    """The short text table ``stablecues eval`` prints."""
    thr = doc.get("threshold_at_100p")
    lines = [
        f"run          {doc['run']}",
        f"ground truth {doc.get('gt_file')}  sha256 {doc.get('gt_sha256')}",
        f"protocol     {doc['protocol']}  tolerance {doc['tolerance']}  exclude {doc['exclude']} frames"
        + (f" + {doc['exclude_s']} s" if doc.get("exclude_s") else ""),
        f"queries      {doc['queries']}  positives {doc['positives']}  detections {doc['detections']}"
        + (
            f" (+{doc['unscored_detections']} in frames that are not queries: not scored)"
            if doc.get("unscored_detections")
            else ""
        ),
        f"TP {doc['tp']}  FP {doc['fp']}  FN {doc['fn']}  "
        f"precision {doc['precision']:.4f}  recall {doc['recall']:.4f}",
        f"R@100P       {100 * doc['recall_at_100p']:.2f} %"
        + (f"  (score >= {thr:.6g})" if thr is not None else ""),
        f"AUC          {doc['auc']:.4f}",
    ]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from ..errors import ConfigError, DatasetError
    from ..evaluation.evaluate import eval_file_name, evaluate_run, evaluation_funnel, save_evaluation
    from ..evaluation.funnel import format_funnel
    from ..groundtruth import View, fit_view, load_ground_truth
    from ..outputs import check_output, write_output
    from ..runs import format_timing_table, load_run
    from ..runs.store import json_text

    if args.json:
        check_output(args.json, "evaluation")
    if args.protocol != "exact" and args.tolerance is None:
        raise ConfigError(
            f"--protocol {args.protocol} needs --tolerance N (frames either side; README and demo use 2)"
        )
    run_ = load_run(args.run_dir)
    if not run_.complete and not args.allow_incomplete:
        raise DatasetError(
            f"{run_.path}: the run is incomplete ({len(run_)} frames written; interrupted?): resume it with "
            "'stablecues run --resume', or pass --allow-incomplete to score the frames it has"
        )
    n_frames = run_.meta_int("dataset_frames", run_.meta_int("frames"))
    if args.gt_poses is not None:
        if args.gt is not None:
            raise ConfigError("--gt reads a ground-truth file and --gt-poses makes one from poses: give one")
        gt = _pose_truth(args, run_, n_frames)
    else:
        gt_path = args.gt or run_.meta.get("ground_truth")
        if not gt_path or not isinstance(gt_path, str | Path):
            raise ConfigError(f"{args.run_dir}: no ground truth recorded for this run; pass --gt FILE "
                              "(or --gt-poses SOURCE --max-distance M to make one from poses)")
        gt = load_ground_truth(gt_path, variable=args.gt_variable, orientation=args.gt_orientation)
        view = args.gt_view or run_.meta.get("gt_view") or "all"
        if view not in ("all", "left", "right", "pair"):
            raise ConfigError(f"{run_.path}: meta.json gt_view {view!r} is not all, left, right or pair")
        gt = fit_view(gt, cast(View, view), n_frames)
    exclude = args.exclude if args.exclude is not None else run_.meta_int("exclude", 0) or 0
    _, doc = evaluate_run(
        run_,
        gt,
        protocol=args.protocol,
        tolerance=args.tolerance or 0,
        exclude=exclude,
        exclude_s=args.exclude_s,
        detections=args.detections,
        score=args.score,
    )
    inside = save_evaluation(doc, run_.path / eval_file_name(args.protocol, doc["tolerance"]))
    if args.json:
        write_output(args.json, json_text(doc), "evaluation")
    print(format_summary(doc))
    rule = gt.notes.get("from_poses")
    if rule:
        lost = rule["frames_without_pose"]
        print(f"loop rule    {rule['rule']} (poses: {rule['source']})"
              + (f"; {lost} frames without a pose close no loop" if lost else ""))
    funnel = evaluation_funnel(doc)
    if funnel is not None:
        print()
        print(format_funnel(funnel))
    print()
    print(format_timing_table(doc["timing_ms"]))
    print(f"\nwritten: {inside}" + (f", {args.json}" if args.json else ""))
    return 0


def _pose_truth(args: argparse.Namespace, run_: Run, n_frames: int | None) -> GroundTruth:
    """The run's ground truth made from poses (``--gt-poses``): a dataset's own, or a trajectory
    matched to the run's frame times."""
    import numpy as np

    from ..errors import DatasetError
    from ..groundtruth import GroundTruth, sha256_file
    from ..outputs import output_file
    from ..posetruth import frame_poses, pose_ground_truth

    rule = loop_rule_from_args(args, "--gt-poses")
    src = Path(args.gt_poses)
    frame_times = None
    if src.is_file() and src.suffix.lower() not in (".bag", ".db3", ".mcap"):  # a trajectory file
        n = n_frames if n_frames is not None else len(run_)
        if not np.array_equal(run_.frames, np.arange(n)):
            raise DatasetError(f"{run_.path}: --gt-poses with a trajectory file needs the times of every "
                               f"frame 0..{n - 1}, but the run has {len(run_)} frames: give the dataset "
                               "instead")
        frame_times = run_.timestamps
    source = frame_poses(src, frame_times=frame_times, n_frames=n_frames, max_dt=args.max_dt)
    if n_frames is not None and source.poses.shape[0] != n_frames:
        raise DatasetError(f"{src}: poses for {source.poses.shape[0]} frames, but the run's dataset has "
                           f"{n_frames}")
    made = pose_ground_truth(source, rule)
    # kept beside the run, so that `report` and a later `eval` read the same matrix; the pose
    # file and its hash stay in the notes
    target = run_.path / POSE_GT_FILE
    with output_file(target, "ground truth") as tmp:
        np.save(tmp, made.matrix)
    pose_file = None if made.path is None else str(made.path)
    notes = {"from_poses": {**made.notes["from_poses"], "pose_file": pose_file,
                            "pose_file_sha256": made.sha256}}
    return GroundTruth(made.matrix, path=target, sha256=sha256_file(target), notes=notes)
