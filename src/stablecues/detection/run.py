"""Running the detector over a whole dataset into a run directory (what ``stablecues run`` does)."""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ..config import to_dict
from ..errors import DatasetError
from ..runs import RunWriter
from .config import DetectorConfig
from .decision import LoopDecision
from .detector import LoopDetector

log = logging.getLogger(__name__)

STAGES = ("extract", "segment", "mask", "transform", "lift", "query", "verify", "add", "total")


@dataclass
class RunSummary:
    """What a run did: frames, loops, statuses, time per frame, where it is."""

    out_dir: Path
    frames: int
    loops: int
    statuses: dict[str, int]
    ms_per_frame: float
    mask_fallbacks: int
    pictures: list[Path] = field(default_factory=list)


def run_dataset(
    dataset: Any,
    config: DetectorConfig,
    out_dir: str | Path,
    *,
    preset_name: str = "custom",
    meta: dict[str, Any] | None = None,
    database: str | Path | None = None,
    resume: bool = False,
    max_frames: int | None = None,
    pictures: int = 4,
    progress: bool = True,
    segmenter: Any | None = None,
) -> RunSummary:
    """Run the loop detector over ``dataset`` and write a run directory.

    Args:
        dataset: a :class:`stablecues.datasets.base.Dataset` (frames in order).
        config: the detector settings.
        out_dir: the run directory (decisions.csv, similarity.npy, config.json, meta.json, ...).
        preset_name: the preset's name, recorded in meta.json.
        meta: more to record (dataset path, format, ground truth file).
        database: keep the detector's database in this file (default: ``out_dir/map.sqlite``).
        resume: continue an interrupted run (its database and decisions) instead of starting over.
        max_frames: stop after this many frames (all when None).
        pictures: how many match pictures of accepted loops to save (evenly spread).
        progress: show a progress bar.
        segmenter: replaces the shipped segmentation network (tests, other models).

    Returns:
        a summary of the run.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    db_path = Path(database) if database is not None else out / "map.sqlite"
    if not resume and db_path.exists():
        _remove_database(db_path, named=database is not None)
    n = len(dataset) if max_frames is None else min(len(dataset), max_frames)
    writer = RunWriter(
        out,
        to_dict(config),
        _run_meta(config, preset_name, n, meta),
        stages=STAGES,
        mode="resume" if resume else "overwrite",
    )
    detector = LoopDetector(config, database=db_path, segmenter=segmenter)
    start = writer.next_frame
    if len(detector) != start:
        raise_mismatch(out, len(detector), start)
    sim = _initial_similarity(config, n, out / "similarity.npy", resume)
    tally = _Tally()
    bar = tqdm(total=n, initial=start, desc=f"run {preset_name}", unit="frame", disable=not progress)
    try:
        for i, frame in enumerate(dataset):
            if i >= n:
                break
            if i < start:
                continue
            d = detector.process(frame)
            tally.count(d)
            row = detector.last_similarity
            if row is not None:
                sim[i, : min(row.size, i)] = row[: min(row.size, i)]
            _write_decision(writer, d, float(frame.timestamp))
            bar.update(1)
            if config.similarity and (i + 1) % 200 == 0:
                writer.set_similarity(sim[: i + 1, : i + 1])
    finally:
        bar.close()
        if config.similarity:
            writer.set_similarity(sim)
        detector.close()
    saved = _match_pictures(dataset, tally.accepted, writer, pictures, config)
    writer.close()
    return RunSummary(
        out,
        len(tally.totals),
        len(tally.accepted),
        dict(tally.statuses),
        float(np.mean(tally.totals)) if tally.totals else float("nan"),
        tally.fallbacks,
        saved,
    )


@dataclass
class _Tally:
    """What the summary counts over the processed frames."""

    statuses: Counter[str] = field(default_factory=Counter)
    accepted: list[LoopDecision] = field(default_factory=list)
    fallbacks: int = 0
    totals: list[float] = field(default_factory=list)

    def count(self, d: LoopDecision) -> None:
        self.statuses[d.status.value] += 1
        self.fallbacks += int(d.mask_fallback)
        self.totals.append(d.timings["total"])
        if d.accepted:
            self.accepted.append(d)


def _remove_database(db_path: Path, *, named: bool) -> None:
    """Delete a previous run's database (and its SQLite side files) before starting over.

    Raises:
        DatasetError: the user named the file (``named``): it is never deleted silently.
    """
    if named:
        raise DatasetError(f"{db_path}: database file exists; continue it with --resume or remove it")
    for suffix in ("", "-wal", "-shm"):
        Path(str(db_path) + suffix).unlink(missing_ok=True)


def _run_meta(
    config: DetectorConfig, preset_name: str, n: int, meta: dict[str, Any] | None
) -> dict[str, Any]:
    """What ``meta.json`` records about the run, ``meta`` last (it wins)."""
    if config.confidence == "inliers" and config.verification is not None:
        score_column = "geometric inliers + normalised BoW score"
    else:
        score_column = "normalised BoW score"
    if config.masking is None or config.masking.mode == "none":
        semantics = "no masking"
    else:
        semantics = f"{config.masking.mode} mask from the {config.semantic_source}"
    return {
        "preset": preset_name,
        "frames": n,
        "exclude": config.query.exclude_recent,
        "score_column": score_column,
        "semantics": semantics,
        **(meta or {}),
    }


def _initial_similarity(config: DetectorConfig, n: int, sim_path: Path, resume: bool) -> np.ndarray:
    """The (n, n) float32 similarity matrix to fill ((0, 0) when turned off), resumed from the file.

    The matrix takes 4 bytes x n^2: ``config.similarity`` turns it off for very long runs.
    """
    sim = np.zeros((n, n) if config.similarity else (0, 0), np.float32)
    if config.similarity and resume and sim_path.exists():
        old = np.load(sim_path)
        k = min(old.shape[0], n)
        sim[:k, :k] = old[:k, :k]
    return sim


def _write_decision(writer: RunWriter, d: LoopDecision, timestamp: float) -> None:
    """One row of ``decisions.csv`` and its extras (:meth:`LoopDecision.extras`) for ``extra.jsonl``."""
    writer.add(
        d.frame_index,
        timestamp,
        d.status.value,
        d.candidate_frame,
        d.confidence if d.candidate >= 0 else float("nan"),
        d.raw_score if d.candidate >= 0 else float("nan"),
        d.accepted,
        d.timings,
        d.extras(),
    )


def raise_mismatch(out: Path, entries: int, rows: int) -> None:
    """Raise: the run's database and its decisions.csv cover different numbers of frames."""
    raise DatasetError(
        f"{out}: the map holds {entries} frames but decisions.csv has {rows}; "
        "cannot resume this run (start it again without --resume)"
    )


def _match_pictures(
    dataset: Any, accepted: list[LoopDecision], writer: RunWriter, count: int, config: DetectorConfig
) -> list[Path]:
    """Pictures of a few accepted loops (evenly spread), when the drawing module is there."""
    if count <= 0 or not accepted:
        return []
    try:
        from ..verification.plot import draw_verification
    except ImportError:  # drawing lands with the verification plots
        return []
    picks = [accepted[int(i)] for i in np.linspace(0, len(accepted) - 1, min(count, len(accepted)))]
    saved: list[Path] = []
    for d in picks:
        if d.verification is None:
            continue
        try:
            q = dataset[d.frame_index]
            c = dataset[d.candidate_frame]
        except (TypeError, IndexError, KeyError):
            return saved
        image = draw_verification(q.image, c.image, d.verification)
        saved.append(writer.add_match_picture(f"loop_{d.frame_index:05d}_{d.candidate_frame:05d}", image))
    return saved
