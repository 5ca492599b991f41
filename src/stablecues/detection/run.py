"""Running the detector over a whole dataset into a run directory (what ``stablecues run`` does)."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from tqdm import tqdm

from ..config import to_dict
from ..errors import ConfigError, DatasetError
from ..limits import MAX_SIMILARITY_FRAMES
from ..runs import RunWriter, load_run
from ..runs.store import own_file
from ..verification.result import Verification
from .config import DetectorConfig
from .decision import LoopDecision
from .detector import LoopDetector

if TYPE_CHECKING:
    from ..types import Frame
    from ..vocabulary import Vocabulary

log = logging.getLogger(__name__)

STAGES = ("extract", "segment", "mask", "transform", "lift", "query", "verify", "add", "total")


def run_stages(config: DetectorConfig) -> tuple[str, ...]:
    """The stages a run of ``config`` times: :data:`STAGES`, with ``vlad`` (the second retrieval
    vote's encoding) before ``query`` when ``query.vlad`` is on."""
    if config.query.vlad <= 0:
        return STAGES
    at = STAGES.index("query")
    return (*STAGES[:at], "vlad", *STAGES[at:])


class FrameObserver(Protocol):
    """Sees each frame as the run decides it (e.g. :class:`stablecues.viz.RerunLogger`).

    ``observe`` is called after the frame's decision is written and the frame stored in the
    detector's map (``detector.db.entry(decision.entry_id)`` holds its kept features), in frame
    order, for the frames this call processes (a resumed run: those after the resume point).
    """

    def observe(self, frame: Frame, decision: LoopDecision, detector: LoopDetector) -> None: ...


@dataclass
class RunSummary:
    """What a run did, over all its frames (also those of the sessions it resumed).

    Attributes:
        out_dir: the run directory.
        frames: frames in the run.
        loops: loops accepted.
        statuses: frames per status.
        ms_per_frame: mean time per frame, the first timed frame left out when there are others
            (it loads the networks and compiles the kernels: 0.5-10 s); NaN when no frame has a
            time.
        mask_fallbacks: frames where semantic masking fell back to all features.
        pictures: the match pictures saved.
        resumed_from: the frame this session started at (0 for a new run).
        already_complete: the run was complete before this call; nothing was done.
        first_frame_ms: the first timed frame's time (the warm-up), apart; NaN when none.
    """

    out_dir: Path
    frames: int
    loops: int
    statuses: dict[str, int]
    ms_per_frame: float
    mask_fallbacks: int
    pictures: list[Path] = field(default_factory=list)
    resumed_from: int = 0
    already_complete: bool = False
    first_frame_ms: float = float("nan")


class _DeferredCommit:
    """The detector's database with its ``add`` held back until the run has journalled the
    frame's decision: the run directory's record (decisions.csv) and the map then never
    disagree by more than a journalled frame, whatever instant the process is killed at.

    Everything but ``add`` goes straight to the database.
    """

    def __init__(self, db: Any) -> None:
        self._db = db
        self._held: tuple[tuple[Any, ...], dict[str, Any]] | None = None

    def __getattr__(self, name: str) -> Any:
        return getattr(self._db, name)

    def __len__(self) -> int:
        return len(self._db)

    def add(self, *args: Any, **kwargs: Any) -> None:
        if self._held is not None:
            raise RuntimeError("a second database add before the first was committed")
        self._held = (args, kwargs)

    def commit(self) -> dict[str, float]:
        """Add the held entry; milliseconds it took, for the ``add`` and ``total`` stages."""
        if self._held is None:
            return {}
        args, kwargs = self._held
        self._held = None
        t = time.perf_counter()
        self._db.add(*args, **kwargs)
        ms = (time.perf_counter() - t) * 1e3
        return {"add": ms, "total": ms}


def run_dataset(
    dataset: Any,
    config: DetectorConfig,
    out_dir: str | Path,
    *,
    preset_name: str = "custom",
    meta: dict[str, Any] | None = None,
    database: str | Path | None = None,
    resume: bool = False,
    overwrite: bool = True,
    max_frames: int | None = None,
    pictures: int = 4,
    progress: bool = True,
    segmenter: Any | None = None,
    vocabulary: Vocabulary | None = None,
    observers: Sequence[FrameObserver] = (),
) -> RunSummary:
    """Run the loop detector over ``dataset`` and write a run directory.

    A run killed at any instant resumes (``resume=True``) to the decisions an uninterrupted
    run makes: each frame's decision is journalled before the detector's map commits it, and
    the similarity rows are appended frame by frame.

    Args:
        dataset: a :class:`stablecues.datasets.base.Dataset` (frames in order).
        config: the detector settings.
        out_dir: the run directory (decisions.csv, similarity.npy, config.json, meta.json, ...).
        preset_name: the preset's name, recorded in meta.json.
        meta: more to record (dataset path, format, ground truth file).
        database: keep the detector's database in this file (default: ``out_dir/map.sqlite``);
            its folder must exist.
        resume: continue an interrupted run (its database and decisions) instead of starting over.
        overwrite: replace a run already in ``out_dir`` (its own files only); False refuses a
            directory that exists and is not empty.
        max_frames: stop after this many frames (all when None).
        pictures: how many match pictures of accepted loops to save (evenly spread over the run).
        progress: show a progress bar.
        segmenter: replaces the shipped segmentation network (tests, other models).
        vocabulary: the vocabulary (default: the shipped one); a resumed run's database
            refuses another.
        observers: told of each frame as it is decided (see :class:`FrameObserver`).

    Returns:
        a summary of the whole run.

    Raises:
        ConfigError: a similarity matrix larger than :data:`stablecues.limits.MAX_SIMILARITY_FRAMES`.
        DatasetError: an output directory, database or run that cannot be used.
    """
    out = Path(out_dir)
    n = len(dataset) if max_frames is None else max(0, min(len(dataset), max_frames))
    if config.similarity and n > MAX_SIMILARITY_FRAMES:
        raise ConfigError(
            f"{out}: a similarity matrix of {n} x {n} frames is over the {MAX_SIMILARITY_FRAMES} accepted "
            "(stablecues.limits); run with --set similarity=false"
        )
    db_path = _database_path(out, database)
    if not resume and database is not None and db_path.exists():
        _remove_database(db_path, named=True)  # raises: a named database is never deleted
    if resume:
        done = _complete_run(out, n)
        if done is not None:
            return done
    # a database the user named outside the run folder is opened first: one that cannot be
    # used (a damaged entry log, another vocabulary) is refused before the run folder is touched
    early = (database is not None and db_path.parent.is_dir()
             and out.resolve() not in db_path.resolve().parents)
    detector = (LoopDetector(config, vocabulary=vocabulary, database=db_path, segmenter=segmenter)
                if early else None)
    try:
        writer = RunWriter(
            out,
            to_dict(config),
            _run_meta(config, preset_name, n, {"dataset_frames": len(dataset), **(meta or {})}),
            stages=run_stages(config),
            mode="resume" if resume else ("overwrite" if overwrite else "new"),
        )
    except BaseException:
        if detector is not None:
            detector.close(hint=False)
            if not resume:  # the empty map just made for this run
                _remove_database(db_path, named=False)
        raise
    if detector is None:
        if not resume and db_path.exists():
            _remove_database(db_path, named=False)
        detector = LoopDetector(config, vocabulary=vocabulary, database=db_path, segmenter=segmenter)
    deferred = _DeferredCommit(detector.db)
    detector.db = deferred  # type: ignore[assignment]
    decisions: dict[int, LoopDecision] = {}
    try:
        start = writer.reconcile(len(detector))
        _process(dataset, detector, writer, deferred, range(start, n), decisions, progress, preset_name,
                 observers)
        saved = _match_pictures(dataset, detector, writer, decisions, pictures)
    except BaseException:
        writer.release()  # the run can be resumed at once, by this process or another
        raise
    finally:
        detector.close(hint=False)  # the run's summary gives its own hint
    writer.close()
    return _summary(out, saved, start)


def _process(
    dataset: Any,
    detector: LoopDetector,
    writer: RunWriter,
    deferred: _DeferredCommit,
    frames: range,
    decisions: dict[int, LoopDecision],
    progress: bool,
    name: str,
    observers: Sequence[FrameObserver] = (),
) -> None:
    """Detect, journal, commit and write each frame of ``frames`` in order, then tell the observers."""
    similarity = detector.config.similarity
    bar = tqdm(total=frames.stop, initial=frames.start, desc=f"run {name}", unit="frame",
               disable=not progress)
    try:
        for i in frames:
            frame = dataset[i]
            d = detector.process(frame)
            row = detector.last_similarity if similarity else None
            writer.add(
                d.frame_index,
                float(frame.timestamp),
                d.status.value,
                d.candidate_frame,
                d.confidence if d.candidate >= 0 else float("nan"),
                d.raw_score if d.candidate >= 0 else float("nan"),
                d.accepted,
                d.timings,
                d.extras(),
                similarity=None if not similarity else (row if row is not None else np.zeros(0, np.float32)),
                commit=deferred.commit,
            )
            if d.accepted:
                decisions[d.frame_index] = d
            for observer in observers:
                observer.observe(frame, d, detector)
            bar.update(1)
    finally:
        bar.close()


def _database_path(out: Path, database: str | Path | None) -> Path:
    """The database file: the one named (its folder must exist), else ``out/map.sqlite``.

    Raises:
        DatasetError: the named file's folder does not exist, or the default one is a link.
    """
    if database is None:
        return own_file(out / "map.sqlite", "the run's database")
    db = Path(database)
    if not db.parent.is_dir():
        raise DatasetError(f"{db}: the database's folder {db.parent} does not exist (it is not created)")
    return db


def _complete_run(out: Path, n: int) -> RunSummary | None:
    """The summary of a run in ``out`` that is already complete with ``n`` frames or more, else None."""
    if not (out / "meta.json").is_file():
        return None
    run = load_run(out)
    if not run.complete or len(run) < n:
        return None
    return _summary(out, [], len(run), already=True)


def _summary(out: Path, pictures: list[Path], start: int, *, already: bool = False) -> RunSummary:
    """What the whole run did, read back from its directory."""
    run = load_run(out)
    totals = run.stage_ms.get("total", np.zeros(0))
    finite = totals[np.isfinite(totals)]
    fallbacks = sum(1 for e in run.extra() if isinstance(e, dict) and e.get("mask_fallback"))
    first = float(finite[0]) if finite.size else float("nan")
    rest = finite[1:] if finite.size > 1 else finite  # the warm-up apart
    return RunSummary(
        out,
        len(run),
        int(run.accepted.sum()),
        run.status_counts(),
        float(rest.mean()) if rest.size else float("nan"),
        fallbacks,
        pictures if pictures else (run.matches if already else []),
        start,
        already,
        first,
    )


def _remove_database(db_path: Path, *, named: bool) -> None:
    """Delete a previous run's database (its SQLite side files and index files too) before
    starting over.

    Raises:
        DatasetError: the user named the file (``named``): it is never deleted silently.
    """
    if named:
        raise DatasetError(f"{db_path}: database file exists; continue it with --resume or remove it")
    from .. import database

    remover = getattr(database, "remove_database", None)  # the database's own, knowing its files
    if remover is not None:
        remover(db_path)
        return
    for suffix in ("", "-wal", "-shm"):
        Path(str(db_path) + suffix).unlink(missing_ok=True)


def _run_meta(
    config: DetectorConfig, preset_name: str, n: int, meta: dict[str, Any] | None
) -> dict[str, Any]:
    """What ``meta.json`` records about the run, ``meta`` last (it wins)."""
    if config.confidence == "sequence" and config.verification is not None:
        score_column = "geometric inliers x sequence score"
    elif config.confidence == "inliers" and config.verification is not None:
        score_column = "geometric inliers + normalised BoW score"
    else:
        score_column = "normalised BoW score"
    if config.masking is None or config.masking.mode == "none":
        semantics = "no masking"
    else:
        semantics = f"{config.masking.mode} mask from the {config.semantic_source}"
    q = config.query
    # the smallest window the detector may use: with runs, the window after a cut
    exclude = q.exclude_recent if q.run_break is None else min(q.exclude_recent, q.exclude_recent_min)
    return {
        "preset": preset_name,
        "frames": n,
        "exclude": exclude,
        "score_column": score_column,
        "semantics": semantics,
        **(meta or {}),
    }


def _match_pictures(
    dataset: Any,
    detector: LoopDetector,
    writer: RunWriter,
    decisions: dict[int, LoopDecision],
    count: int,
) -> list[Path]:
    """Pictures of a few accepted loops, evenly spread over the whole run (also the part an
    earlier session wrote: those pairs are verified again as the detector verified them)."""
    if count <= 0:
        return []
    try:
        from ..verification.plot import draw_verification
    except ImportError:  # drawing lands with the verification plots
        return []
    run = load_run(writer.path)
    loops = [(int(f), int(c)) for f, c, a in zip(run.frames, run.candidates, run.accepted, strict=True) if a]
    if not loops:
        return []
    picks = [loops[int(i)] for i in np.linspace(0, len(loops) - 1, min(count, len(loops)))]
    saved: list[Path] = []
    for frame, cand in picks:
        try:
            q = dataset[frame]
            c = dataset[cand]
        except (TypeError, IndexError, KeyError):
            return saved
        d = decisions.get(frame)
        verification = d.verification if d is not None else _verify_again(detector, q, cand)
        if verification is None:
            continue
        image = draw_verification(q.image, c.image, verification)
        saved.append(writer.add_match_picture(f"loop_{frame:05d}_{cand:05d}", image))
    return saved


def _verify_again(detector: LoopDetector, frame: Any, candidate: int) -> Verification | None:
    """The verification of an accepted loop of an earlier session, made again through the
    detector's own preparation and verifier (the map's entry ``k`` is frame ``k`` of a run)."""
    if detector.config.verification is None or not 0 <= candidate < len(detector):
        return None
    prep = detector.preparer.prepare(frame)
    verifier = detector.preparer.verifier(prep.calibration)
    result = verifier.verify_entry(prep.view, detector.db.entry(candidate))
    return result if result.accepted else None
