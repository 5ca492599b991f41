"""Sweeps: a grid of datasets x presets (x overrides), one task each, serially or on a Dask cluster.

Each task is what ``stablecues run DATASET --preset P --set ...`` does (the same
:func:`stablecues.detection.run.run_dataset`), followed by what ``stablecues eval`` does when
the dataset's loop ground truth is known. It writes the run folder
``OUT/<dataset>__<preset>[__<override-tag>]/`` (the tag: 8 hex digits of the overrides' hash)
and returns one row of the merged table, which :func:`run_sweep` writes as ``OUT/sweep.csv``
and ``OUT/sweep.json`` in the grid's order, whichever worker finished first.

A task that fails on bad input (a missing dataset, a malformed ground truth) gives a row with
its one-line ``error`` and leaves the others running; any other exception is a bug and stops
the sweep with its traceback.

On a cluster, the workers need stablecues installed and the datasets and ``OUT`` at the same
paths as the client (a shared file system): paths are made absolute before tasks leave.
"""

from __future__ import annotations

import csv
import hashlib
import itertools
import json
import logging
import math
import os
import socket
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast

from ..errors import ConfigError, DatasetError, StableCuesError

log = logging.getLogger(__name__)

TABLE_CSV = "sweep.csv"
TABLE_JSON = "sweep.json"
Mode = Literal["new", "overwrite", "resume"]

#: the merged table's columns, in order
COLUMNS = (
    "run",
    "dataset",
    "preset",
    "overrides",
    "frames",
    "loops",
    "statuses",
    "protocol",
    "tolerance",
    "exclude",
    "queries",
    "positives",
    "tp",
    "fp",
    "fn",
    "precision",
    "recall",
    "recall_at_100p",
    "auc",
    "gt_file",
    "gt_sha256",
    "ms_per_frame",
    "wall_s",
    "worker",
    "error",
)
#: columns that differ between two runs of the same task (time, place); the rest must not
VOLATILE_COLUMNS = ("ms_per_frame", "wall_s", "worker")
_EVAL_COLUMNS = ("protocol", "tolerance", "exclude", "queries", "positives", "tp", "fp", "fn", "precision",
                 "recall", "recall_at_100p", "auc", "gt_file", "gt_sha256")


@dataclass(frozen=True)
class SweepDataset:
    """One dataset of a sweep.

    Attributes:
        path: the dataset folder.
        name: its name in run folders and in the table (default: the folder's name).
        format: dataset format (see :func:`stablecues.datasets.open_dataset`).
        ground_truth: loop ground truth file; None takes the dataset's own, if any.
    """

    path: Path
    name: str = ""
    format: str = "auto"
    ground_truth: Path | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))
        if self.ground_truth is not None:
            object.__setattr__(self, "ground_truth", Path(self.ground_truth))
        name = self.name or self.path.resolve().name
        if not name or "/" in name or "\\" in name or name in (".", "..") or "__" in name:
            raise ConfigError(f"{self.path}: dataset name {name!r} cannot name a run folder "
                              "(no slashes, no '__', not empty)")
        object.__setattr__(self, "name", name)


@dataclass(frozen=True)
class SweepTask:
    """One cell of the grid.

    Attributes:
        dataset: the dataset.
        preset: the detector preset.
        overrides: settings over the preset, as canonical JSON (``{}`` for none).
    """

    dataset: SweepDataset
    preset: str
    overrides: str = "{}"

    @property
    def override_dict(self) -> dict[str, Any]:
        """The overrides as a nested dict."""
        value: dict[str, Any] = json.loads(self.overrides)
        return value

    @property
    def folder(self) -> str:
        """The run folder's name: ``<dataset>__<preset>[__<override-tag>]``."""
        base = f"{self.dataset.name}__{self.preset}"
        return base if self.overrides == "{}" else f"{base}__{override_tag(self.override_dict)}"


@dataclass(frozen=True)
class SweepOptions:
    """What every task of a sweep does besides its own cell.

    Attributes:
        mode: "new" refuses run folders that exist and are not empty, "overwrite" replaces
            them, "resume" continues interrupted runs (and only re-evaluates complete ones).
        max_frames: stop each run after this many frames (None: all).
        pictures: match pictures of accepted loops to save per run.
        protocol: evaluation protocol ("exact", "tolerance" or "ibow").
        tolerance: +-frames of the tolerant protocols.
        threads: compute threads of each task (OpenCV and the network); 1 by default, so that
            n workers of one thread each use n cores and a serial sweep is the one-thread baseline.
    """

    mode: Mode = "new"
    max_frames: int | None = None
    pictures: int = 0
    protocol: Literal["exact", "tolerance", "ibow"] = "exact"
    tolerance: int = 0
    threads: int = 1

    def __post_init__(self) -> None:
        if self.threads < 1:
            raise ConfigError(f"threads: expected 1 or more, got {self.threads}")
        if self.mode not in ("new", "overwrite", "resume"):
            raise ConfigError(f"sweep mode: expected new, overwrite or resume, got {self.mode!r}")
        if self.protocol not in ("exact", "tolerance", "ibow"):
            raise ConfigError(f"protocol: expected exact, tolerance or ibow, got {self.protocol!r}")
        if self.protocol != "exact" and self.tolerance <= 0:
            raise ConfigError(f"protocol {self.protocol} needs a tolerance of 1 frame or more")
        if self.max_frames is not None and self.max_frames < 1:
            raise ConfigError(f"max_frames: expected 1 or more, got {self.max_frames}")


@dataclass
class SweepResult:
    """What a sweep did.

    Attributes:
        rows: one per task, in the grid's order (see :data:`COLUMNS`).
        csv_path, json_path: the merged table.
        wall_s: seconds from the first task sent to the last row back.
        engine: "serial" or the scheduler's address.
    """

    rows: list[dict[str, Any]]
    csv_path: Path
    json_path: Path
    wall_s: float
    engine: str

    @property
    def failures(self) -> list[dict[str, Any]]:
        """The rows of tasks that failed on bad input (their ``error`` says why)."""
        return [r for r in self.rows if r.get("error")]


def canonical_overrides(overrides: Mapping[str, Any] | None) -> str:
    """Overrides as canonical JSON (sorted keys, no spaces): equal settings, equal text."""
    try:
        return json.dumps(dict(overrides or {}), sort_keys=True, separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"overrides are not plain JSON values: {exc}") from exc


def override_tag(overrides: Mapping[str, Any]) -> str:
    """8 hex digits naming a set of overrides in run folders (SHA-1 of the canonical JSON)."""
    return hashlib.sha1(canonical_overrides(overrides).encode()).hexdigest()[:8]


def flat_overrides(overrides: Mapping[str, Any], prefix: str = "") -> list[str]:
    """``{"query": {"alpha": 0.2}}`` -> ``["query.alpha=0.2"]`` (what ``--set`` takes)."""
    out: list[str] = []
    for key, value in sorted(overrides.items()):
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            out += flat_overrides(value, name + ".")
        else:
            out.append(f"{name}={json.dumps(value, sort_keys=True)}")
    return out


def plan_sweep(
    datasets: Sequence[SweepDataset],
    presets: Sequence[str],
    overrides: Sequence[Mapping[str, Any]] = ({},),
) -> list[SweepTask]:
    """The grid datasets x presets x override sets, in that order; every setting is checked here.

    Raises:
        ConfigError: an empty axis, an unknown preset, an override the preset refuses, two
            datasets of one name, or a cell named twice.
    """
    from ..detection import preset

    if not datasets or not presets or not overrides:
        raise ConfigError("a sweep needs at least one dataset, one preset and one set of overrides")
    names = [d.name for d in datasets]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ConfigError(f"two datasets are named {twice[0]!r}: name them (NAME=PATH)")
    tasks = []
    for ds, name, over in itertools.product(datasets, presets, overrides):
        preset(name, dict(over))  # raises ConfigError: unknown preset, key or value
        tasks.append(SweepTask(ds, name, canonical_overrides(over)))
    folders = [t.folder for t in tasks]
    if len(set(folders)) != len(folders):
        dup = next(f for f in folders if folders.count(f) > 1)
        raise ConfigError(f"the sweep names run folder {dup!r} twice (a preset or override set repeated?)")
    return tasks


def run_task(task: SweepTask, out: str | Path, options: SweepOptions) -> dict[str, Any]:
    """Run one cell (detection, then evaluation when ground truth is known) into
    ``out/<task.folder>``; returns its row of the merged table.

    Bad input (:class:`~stablecues.errors.StableCuesError`) gives a row with ``error`` set.
    """
    import cv2

    from ..semantics import inference

    before = cv2.getNumThreads(), inference.default_threads()
    cv2.setNumThreads(options.threads)
    inference.set_default_threads(options.threads)
    try:
        return _run_task(task, out, options)
    finally:  # a serial sweep runs in the caller's process: leave its settings as they were
        cv2.setNumThreads(before[0])
        inference.set_default_threads(before[1])


def _run_task(task: SweepTask, out: str | Path, options: SweepOptions) -> dict[str, Any]:
    t0 = time.perf_counter()
    run_dir = Path(out) / task.folder
    row: dict[str, Any] = {c: None for c in COLUMNS}
    row.update(run=str(run_dir), dataset=task.dataset.name, preset=task.preset, overrides=task.overrides,
               worker=f"{socket.gethostname()}:{os.getpid()}")
    try:
        row.update(_detect_and_evaluate(task, run_dir, options))
    except StableCuesError as exc:
        row["error"] = " ".join(f"{type(exc).__name__}: {exc}".split())
    row["wall_s"] = round(time.perf_counter() - t0, 3)
    return row


def _detect_and_evaluate(task: SweepTask, run_dir: Path, options: SweepOptions) -> dict[str, Any]:
    from ..datasets import open_dataset
    from ..detection import preset
    from ..detection.run import run_dataset

    ds = task.dataset
    config = preset(task.preset, task.override_dict)
    dataset = open_dataset(ds.path, format=ds.format)
    gt_path = ds.ground_truth if ds.ground_truth is not None else dataset.ground_truth_path()
    described = dataset.describe() if hasattr(dataset, "describe") else {}
    meta = {**described, "dataset": str(ds.path), "format": getattr(dataset, "format", ds.format),
            "ground_truth": None if gt_path is None else str(gt_path),
            "overrides": flat_overrides(task.override_dict), "sweep_task": task.folder}
    summary = run_dataset(dataset, config, run_dir, preset_name=task.preset, meta=meta,
                          resume=options.mode == "resume", overwrite=options.mode == "overwrite",
                          max_frames=options.max_frames, pictures=options.pictures, progress=False)
    out: dict[str, Any] = {
        "frames": summary.frames,
        "loops": summary.loops,
        "statuses": dict(sorted(summary.statuses.items())),
        "ms_per_frame": None if math.isnan(summary.ms_per_frame) else round(summary.ms_per_frame, 3),
    }
    if gt_path is not None:
        gt = dataset.ground_truth() if ds.ground_truth is None else None
        out.update(evaluate_folder(run_dir, gt_path if gt is None else gt, options))
    return out


def evaluate_folder(run_dir: Path, gt: Any, options: SweepOptions) -> dict[str, Any]:
    """What ``stablecues eval RUN_DIR`` does with the sweep's protocol: writes
    ``eval_<protocol>.json`` into the run folder; returns the table's evaluation columns.

    Args:
        run_dir: a complete run folder.
        gt: a :class:`~stablecues.groundtruth.GroundTruth`, or the path of a ground truth file.
    """
    from ..evaluation.evaluate import eval_file_name, evaluate_run, save_evaluation
    from ..groundtruth import GroundTruth, View, fit_view, load_ground_truth
    from ..runs import load_run

    run = load_run(run_dir)
    if not run.complete:
        raise DatasetError(f"{run_dir}: the run is incomplete; it cannot be evaluated")
    truth = gt if isinstance(gt, GroundTruth) else load_ground_truth(gt)
    view = run.meta.get("gt_view") or "all"
    if view not in ("all", "left", "right", "pair"):
        raise ConfigError(f"{run_dir}: meta.json gt_view {view!r} is not all, left, right or pair")
    truth = fit_view(truth, cast(View, view), run.meta_int("dataset_frames", run.meta_int("frames")))
    _, doc = evaluate_run(run, truth, protocol=options.protocol, tolerance=options.tolerance,
                          exclude=run.meta_int("exclude", 0) or 0)
    save_evaluation(doc, run.path / eval_file_name(options.protocol, doc["tolerance"]))
    return {c: doc.get(c) for c in _EVAL_COLUMNS}


def check_out(tasks: Iterable[SweepTask], out: Path, options: SweepOptions) -> None:
    """Refuse, before anything runs, a new sweep whose run folders exist and are not empty.

    Raises:
        DatasetError: ``out`` is not a folder, or (mode "new") a run folder holds files.
    """
    if out.exists() and not out.is_dir():
        raise DatasetError(f"{out}: exists and is not a folder")
    if options.mode != "new":
        return
    for t in tasks:
        d = out / t.folder
        if d.is_dir() and any(d.iterdir()):
            raise DatasetError(f"{d}: a run folder of this sweep exists and is not empty; "
                               "continue the sweep with --resume or replace it with --overwrite")


def run_sweep(
    tasks: Sequence[SweepTask],
    out: str | Path,
    options: SweepOptions | None = None,
    *,
    client: Any | None = None,
    timeout_s: float | None = None,
    on_row: Callable[[dict[str, Any]], None] | None = None,
) -> SweepResult:
    """Run every task, serially in this process or as tasks of a Dask ``client``, and write
    the merged table.

    Args:
        tasks: from :func:`plan_sweep`.
        out: the sweep's folder (created): run folders and ``sweep.csv`` / ``sweep.json``.
        options: what every task does (default :class:`SweepOptions`).
        client: a ``distributed.Client`` (see :func:`stablecues.distributed.open_client`);
            None runs the tasks one after another here.
        timeout_s: give up waiting for the cluster's rows after this long (None: never).
        on_row: called with each row as it arrives (progress).

    Raises:
        DatasetError: run folders in the way (see :func:`check_out`).
        ClusterError: the cluster lost a task or did not finish in ``timeout_s``.
    """
    options = options or SweepOptions()
    root = Path(out).absolute()
    tasks = [_absolute(t) for t in tasks]
    check_out(tasks, root, options)
    root.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if client is None:
        rows = []
        for t in tasks:
            rows.append(run_task(t, root, options))
            if on_row:
                on_row(rows[-1])
        engine = "serial"
    else:
        rows = _on_cluster(client, tasks, root, options, timeout_s, on_row)
        engine = str(client.scheduler_info().get("address", "dask"))
    wall = time.perf_counter() - t0
    csv_path, json_path = write_table(rows, root)
    return SweepResult(rows, csv_path, json_path, wall, engine)


def _absolute(task: SweepTask) -> SweepTask:
    ds = task.dataset
    gt = None if ds.ground_truth is None else ds.ground_truth.absolute()
    return SweepTask(SweepDataset(ds.path.absolute(), ds.name, ds.format, gt), task.preset, task.overrides)


def _preset_weight(task: SweepTask) -> int:
    """Rough cost per frame of a cell's settings: the segmentation network about triples it."""
    from ..detection import preset

    cfg = preset(task.preset, task.override_dict)
    network = cfg.semantic_source == "network" and (cfg.masking is not None or cfg.weighting is not None)
    return 3 if network else 1


def _frames_hint(path: Path) -> int:
    """A rough size of a dataset, to start the longest tasks first: files in its folder."""
    try:
        return sum(1 for _ in itertools.islice(path.rglob("*"), 100_000))
    except OSError:
        return 0


def _on_cluster(
    client: Any, tasks: list[SweepTask], root: Path, options: SweepOptions, timeout_s: float | None,
    on_row: Callable[[dict[str, Any]], None] | None,
) -> list[dict[str, Any]]:
    """Submit every task (the costliest first, longest-processing-time order: the last to
    finish is then a short one), collect rows in the grid's order."""
    from distributed import KilledWorker, as_completed

    from .cluster import ClusterError

    sizes = {path: _frames_hint(path) for path in {t.dataset.path for t in tasks}}
    cost = [sizes[t.dataset.path] * _preset_weight(t) for t in tasks]
    order = sorted(range(len(tasks)), key=lambda i: (-cost[i], i))
    futures = [
        client.submit(run_task, tasks[i], root, options, key=f"sweep-{tasks[i].folder}-{os.urandom(4).hex()}",
                      priority=cost[i], pure=False)
        for i in order
    ]
    index = {f.key: i for i, f in zip(order, futures, strict=True)}
    rows: list[dict[str, Any] | None] = [None] * len(tasks)
    try:
        for fut in as_completed(futures, timeout=timeout_s):
            rows[index[fut.key]] = row = fut.result()
            if on_row:
                on_row(row)
    except TimeoutError as exc:
        missing = [tasks[i].folder for i, r in enumerate(rows) if r is None]
        raise ClusterError(f"the cluster did not finish {len(missing)} tasks in {timeout_s} s "
                           f"(first: {missing[0]})") from exc
    except KilledWorker as exc:  # the task's workers died (out of memory, killed) too often
        raise ClusterError(f"a sweep task lost its worker too often: {' '.join(str(exc).split())}") from exc
    except OSError as exc:  # the scheduler is gone
        raise ClusterError(f"the cluster failed: {' '.join(str(exc).split())}") from exc
    finally:
        for f in futures:
            f.release()
    return [r for r in rows if r is not None]


def write_table(rows: Sequence[Mapping[str, Any]], out: Path) -> tuple[Path, Path]:
    """Write ``out/sweep.csv`` (dict columns as JSON text) and ``out/sweep.json``."""
    from ..runs import write_json

    csv_path, json_path = out / TABLE_CSV, out / TABLE_JSON
    write_json(json_path, {"columns": list(COLUMNS), "rows": [dict(r) for r in rows]})
    tmp = csv_path.with_name(csv_path.name + ".tmp")
    with tmp.open("w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(COLUMNS))
        w.writeheader()
        for r in rows:
            w.writerow({c: json.dumps(r.get(c), sort_keys=True) if isinstance(r.get(c), dict) else r.get(c)
                        for c in COLUMNS})
    tmp.replace(csv_path)
    return csv_path, json_path


def read_table(out: str | Path) -> list[dict[str, Any]]:
    """The rows of a sweep's ``sweep.json``.

    Raises:
        DatasetError: missing or malformed file.
    """
    from ..runs import read_json

    path = Path(out) / TABLE_JSON
    doc = read_json(path, "sweep table")
    rows = doc.get("rows")
    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        raise DatasetError(f"{path}: expected an object with a list of 'rows' objects")
    return rows
