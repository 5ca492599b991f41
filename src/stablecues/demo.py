"""``stablecues demo``: the whole system on built-in data, with nothing to download.

1. Generates a synthetic town drive with revisits (stereo, depth, labels, poses, loop truth);
2. runs the detector with the ``paper`` preset, the ``bow`` baseline and the default;
3. evaluates each run against the sequence's own loop ground truth;
4. writes the HTML report and prints a short summary.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

log = logging.getLogger(__name__)

DEMO_PRESETS = ("paper", "bow", "default")


@dataclass
class DemoResult:
    """What the demo did."""

    sequence: Path
    report: Path
    runs: dict[str, Path]
    r_at_100p: dict[str, float]
    ms_per_frame: dict[str, float]
    semantic_source: str
    semantic_note: str
    seconds: float
    loops: dict[str, int] = field(default_factory=dict)


def network_works_on(
    frames: list[Any], min_accuracy: float = 0.6, precisions: tuple[str, ...] = ("float32",)
) -> tuple[bool, float]:
    """Whether the shipped segmentation network labels these renders well enough.

    Compares its labels with the renderer's on a few frames (pixel accuracy over the classes
    the renderer draws), for the weights of every precision given; returns (usable, the
    lowest accuracy).
    """
    import numpy as np

    from .errors import ModelError

    accuracies = []
    for precision in precisions:
        try:
            from .semantics.inference import SegmentationModel

            model = SegmentationModel.load(precision=precision)
        except (ModelError, ImportError):
            return False, float("nan")
        correct = total = 0
        for f in frames:
            if f.labels is None:
                continue
            pred = model.predict(f.image, 1).labels
            valid = f.labels < 11
            correct += int(np.count_nonzero((pred == f.labels) & valid))
            total += int(np.count_nonzero(valid))
        accuracies.append(correct / total if total else 0.0)
    acc = min(accuracies, default=0.0)
    return acc >= min_accuracy, acc


def run_demo(
    out_dir: str | Path,
    *,
    frames: int = 240,
    seed: int = 0,
    width: int = 384,
    height: int = 288,
    presets: tuple[str, ...] = DEMO_PRESETS,
    progress: bool = True,
) -> DemoResult:
    """Generate, detect, evaluate and report; see the module docstring.

    Args:
        out_dir: folder for the sequence, the runs and the report (created).
        frames: frames of the synthetic drive.
        seed: the town and the drive follow from it.
        width, height: image size.
        presets: detector presets to run.
        progress: progress bars.
    """
    from .datasets import open_dataset
    from .detection import preset
    from .detection.run import run_dataset
    from .evaluation import evaluate_run, load_ground_truth, load_run
    from .evaluation.evaluate import eval_file_name, save_evaluation
    from .evaluation.report import build_report
    from .synthetic import SyntheticTownConfig, write_sequence

    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    seq = out / "sequence"
    cfg = SyntheticTownConfig(frames=frames, seed=seed, width=width, height=height)
    write_sequence(cfg, seq, progress=progress, overwrite=True)
    dataset = open_dataset(seq, format="folder")
    gt = load_ground_truth(seq / "loops.npy")

    sample = [dataset[i] for i in range(0, len(dataset), max(len(dataset) // 6, 1))][:6]
    precisions = tuple(sorted({preset(name).segmentation_precision for name in presets}))
    usable, acc = network_works_on(sample, precisions=precisions)
    if usable:
        source = "network"
        note = f"semantic masks from the shipped network (pixel accuracy {acc:.0%} on these renders)"
    else:
        source = "labels"
        why = "no network weights" if acc != acc else f"its pixel accuracy on these renders is {acc:.0%}"
        note = (f"semantic masks from the renderer's labels, not the shipped network ({why}): "
                "the network is trained on real CamVid frames, not on synthetic renders")

    runs: dict[str, Path] = {}
    r100: dict[str, float] = {}
    ms: dict[str, float] = {}
    loops: dict[str, int] = {}
    exclude = 20
    for name in presets:
        over: dict[str, Any] = {"semantic_source": source, "query": {"exclude_recent": exclude}}
        config = preset(name, over)
        run_dir = out / "runs" / name
        meta = {"dataset": str(seq), "format": "folder", "ground_truth": str(seq / "loops.npy"),
                "semantics": note if config.masking is not None else "no masking"}
        summary = run_dataset(dataset, config, run_dir, preset_name=name, meta=meta, progress=progress)
        run = load_run(run_dir)
        protocols: tuple[tuple[Literal["exact", "tolerance", "ibow"], int], ...] = (
            ("exact", 0), ("tolerance", 2), ("ibow", 2))
        for protocol, tol in protocols:
            ev, doc = evaluate_run(run, gt, protocol=protocol, tolerance=tol, exclude=exclude)
            save_evaluation(doc, run_dir / eval_file_name(protocol, tol))
            if protocol == "tolerance":
                r100[name] = ev.recall_at_100p
        runs[name] = run_dir
        ms[name] = summary.ms_per_frame
        loops[name] = summary.loops
    report = build_report([load_run(p) for p in runs.values()], out / "report.html",
                          protocol="tolerance", tolerance=2,
                          title=f"stablecues demo: synthetic town, {frames} frames (seed {seed})")
    return DemoResult(seq, report, runs, r100, ms, source, note, time.perf_counter() - t0, loops)
