"""The run directory: what ``stablecues run`` writes and ``stablecues eval`` / ``report`` read.

Files of a run directory::

    config.json      the detector configuration used (free-form JSON object)
    meta.json        {"dataset", "format", "preset", "ground_truth" (path or null), "gt_view",
                      "dataset_frames", "exclude", ..., "versions": {...}, "created",
                      "finished", "frames_written", "complete"}
    decisions.csv    one row per processed frame, header
                     frame,timestamp,status,candidate,score,raw_score,accepted,t_<stage>_ms...
                     (candidate -1 and score nan when there is none; accepted 0/1;
                     stage times in milliseconds, nan when the stage did not run)
    extra.jsonl      optional, one JSON object per line {"frame": i, ...} with per-frame extras
    similarity.npy   optional (N, N) float32: score of query i against earlier frame j,
                     0 where not computed; written on close from
    similarity.rows  the rows as they were computed (row i: i float32 values), appended frame
                     by frame while the run is open, so an interrupted run keeps every row
    pending.json     while a frame is being written: its decision, journalled before the
                     caller's own commit (the detector's map), replayed or dropped on resume
    timings.json     {stage: {mean, std, min, max, count}} in ms, written on close
    writer.lock      held (flock) by the one process writing the run: a second writer (two
                     ``--resume`` of one run at once) is refused before it writes anything
    matches/*.png    optional match pictures of sample loops
    eval_<protocol>.json   written by ``stablecues eval``

Rows are flushed one at a time, so a killed run leaves a readable prefix (a partial last line
is dropped on reading); :class:`RunWriter` with ``mode="resume"`` and :meth:`RunWriter.reconcile`
continue such a run, wherever it was killed, to what an uninterrupted run writes.

A run directory's files are its own: none is read, written or deleted through a symbolic link
(or appended to when it has other hard links), temporary files are created afresh, and
replacing a run deletes only the files listed here.
"""

from __future__ import annotations

import contextlib
import csv
import datetime as _dt
import fcntl
import io
import json
import logging
import math
import os
import platform
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np

from ..errors import DatasetError, InputError, reason
from ..fileio import read_npy, read_text
from ..limits import MAX_TEXT_BYTES, check_file_size
from .timing import timing_table

logger = logging.getLogger(__name__)

BASE_COLUMNS = ("frame", "timestamp", "status", "candidate", "score", "raw_score", "accepted")
DECISIONS = "decisions.csv"
EXTRA = "extra.jsonl"
SIMILARITY = "similarity.npy"
SIMILARITY_ROWS = "similarity.rows"
PENDING = "pending.json"
LOCK = "writer.lock"
CONFIG = "config.json"
META = "meta.json"
TIMINGS = "timings.json"
MATCHES = "matches"
_STAGE_RE = re.compile(r"^t_(.+)_ms$")
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
# every file a run writes: none of them may be a symbolic link
RUN_FILES = (CONFIG, META, DECISIONS, EXTRA, SIMILARITY, SIMILARITY_ROWS, TIMINGS, PENDING, MATCHES)


def versions() -> dict[str, str]:
    """Versions of Python, stablecues and the main libraries, for ``meta.json``."""
    from .._version import __version__

    out = {"stablecues": __version__, "python": platform.python_version(), "numpy": np.__version__}
    try:
        import cv2

        out["opencv"] = cv2.__version__
    except ImportError:  # pragma: no cover
        pass
    try:
        import onnxruntime

        out["onnxruntime"] = onnxruntime.__version__
    except ImportError:  # pragma: no cover
        pass
    out["platform"] = platform.platform()
    return out


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def _json_safe(value: Any) -> Any:
    """NaN/inf -> None and NumPy scalars/arrays -> Python, recursively (strict JSON)."""
    if isinstance(value, Mapping):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return _json_safe(value.tolist())
    if isinstance(value, np.generic):
        return _json_safe(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def json_text(data: Mapping[str, Any]) -> str:
    """``data`` as strict JSON text (NaN and infinities as null), as :func:`write_json` writes it."""
    return json.dumps(_json_safe(data), indent=2, allow_nan=False) + "\n"


def _lock_run(path: Path) -> int:
    """An exclusive ``flock`` on the run folder's ``writer.lock`` (never through a link); the
    descriptor. The lock file is never deleted: a new one would not exclude the holder."""
    lock = path / LOCK
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | _NOFOLLOW, 0o644)
    except OSError as exc:
        raise DatasetError(f"{lock}: cannot open the run's lock ({exc.strerror or exc})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise DatasetError(f"{path}: another stablecues process is writing this run (it holds {LOCK}); "
                           "wait for it to finish or stop it, then --resume") from None
    return fd


def write_json(path: Path, data: Mapping[str, Any]) -> None:
    """Write strict JSON atomically (temporary file, then rename).

    The temporary file is created afresh (a file or link planted under its name is removed
    first, never written through), and the rename replaces ``path`` itself, not what a
    symbolic link there points to.
    """
    text = json_text(data)
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW, 0o644)
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        fh.write(text)
    os.replace(tmp, path)


def own_file(path: Path, what: str) -> Path:
    """``path``, after checking it is not a symbolic link: a run directory's files lie in it.

    Raises:
        DatasetError: ``path`` is a symbolic link.
    """
    if path.is_symlink():
        raise DatasetError(
            f"{path}: {what} is a symbolic link; a run directory's files must lie in it (not followed)"
        )
    return path


def read_json(path: Path, what: str) -> dict[str, Any]:
    """Read a JSON object file (not through a symbolic link).

    Raises:
        DatasetError: missing file, a symbolic link, invalid JSON, or not an object.
    """
    own_file(path, what)
    if not path.is_file():
        raise DatasetError(f"{path}: {what} not found")
    check_file_size(path, MAX_TEXT_BYTES, what)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise DatasetError(f"{path}: {what} is not valid JSON ({reason(exc)})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: {what} should be a JSON object, found {type(data).__name__}")
    return data


def _fmt(value: float) -> str:
    return "nan" if not math.isfinite(value) else repr(float(value))


def _open_append(path: Path, what: str) -> io.TextIOWrapper:
    """Open one of the run's own files for appending: never through a symbolic link, never a file
    with other hard links (appending would change a file outside the run)."""
    own_file(path, what)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | _NOFOLLOW, 0o644)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot open {what} for writing ({reason(exc)})") from None
    if os.fstat(fd).st_nlink > 1:
        os.close(fd)
        raise DatasetError(f"{path}: {what} has other hard links; a run directory's files must be its own")
    return open(fd, "a", encoding="utf-8", newline="")  # noqa: SIM115 - the writer keeps it open


class RunWriter:
    """Writes a run directory incrementally; every row is flushed as soon as it is added.

    Args:
        out_dir: the run directory (created if needed).
        config: the detector configuration (JSON-serialisable), saved as ``config.json``.
        meta: what was run: ``dataset``, ``format``, ``preset``, ``ground_truth`` (path or None)
            and anything else useful (e.g. ``exclude`` frames of the detector, the default of
            ``stablecues eval --exclude``); versions and times are added.
        stages: the stage names of the timing columns, in order; None takes the stages of the
            first row. A later row naming another stage raises :class:`InputError`.
        mode: "new" (refuse a directory that exists and is not empty), "overwrite" (delete the
            previous run's own files first; refuse a non-empty directory that holds no run) or
            "resume" (append to the run found there, keeping its rows; see :attr:`next_frame`
            and :meth:`reconcile`).

    A run directory's files are its own: none may be a symbolic link (nothing outside the
    directory is read, written, followed or deleted).

    Raises:
        DatasetError: ``mode="new"`` on an existing directory, an unreadable run to resume, or
            a run file that is a symbolic link.
    """

    def __init__(
        self,
        out_dir: str | Path,
        config: Mapping[str, Any],
        meta: Mapping[str, Any],
        *,
        stages: Sequence[str] | None = None,
        mode: Literal["new", "overwrite", "resume"] = "new",
    ) -> None:
        self.path = Path(out_dir)
        if mode not in ("new", "overwrite", "resume"):
            raise InputError(f"mode: expected 'new', 'overwrite' or 'resume', got {mode!r}")
        _check_out_dir(self.path, mode)
        self.path.mkdir(parents=True, exist_ok=True)
        self._lock_fd = _lock_run(self.path)  # before anything is written or deleted
        try:
            self._open(config, meta, stages, mode)
        except BaseException:
            self._unlock()
            raise

    def release(self) -> None:
        """Let go of the run folder without completing the run (a run that failed): another
        process may resume it at once. :meth:`close` releases it too."""
        self._unlock()

    def __del__(self) -> None:  # a writer dropped without close(), as a killed process would
        self._unlock()

    def _unlock(self) -> None:
        if getattr(self, "_lock_fd", -1) >= 0:
            with contextlib.suppress(OSError):
                os.close(self._lock_fd)
            self._lock_fd = -1

    def _open(
        self,
        config: Mapping[str, Any],
        meta: Mapping[str, Any],
        stages: Sequence[str] | None,
        mode: Literal["new", "overwrite", "resume"],
    ) -> None:
        if mode == "overwrite":
            self._clear()  # links among the old run's files are removed, never followed
        for name in RUN_FILES:
            own_file(self.path / name, "run file")
        decisions = self.path / DECISIONS
        self._stages: list[str] | None = list(stages) if stages is not None else None
        self._times: dict[str, list[float]] = {}
        self._last_frame = -1
        self._rows = 0
        self._closed = False
        prior_meta: dict[str, Any] = {}
        if mode == "resume" and not decisions.exists():
            self._clear(keep=(PENDING, SIMILARITY_ROWS))  # a run killed in its first frame
        if mode == "resume" and decisions.exists():
            _truncate_partial_line(decisions)
            run = load_run(self.path)
            self._stages = list(run.stage_ms)
            self._times = {k: v.tolist() for k, v in run.stage_ms.items()}
            self._last_frame = int(run.frames[-1]) if len(run) else -1
            self._rows = len(run)
            prior_meta = run.meta
        write_json(self.path / CONFIG, dict(config))
        self.meta: dict[str, Any] = {
            **prior_meta,
            **dict(meta),
            "versions": versions(),
            "created": prior_meta.get("created", _now()),
            "complete": False,
        }
        self.meta.pop("finished", None)
        if prior_meta:
            self.meta["resumed"] = [*prior_meta.get("resumed", []), _now()]
        write_json(self.path / META, self.meta)
        self._csv: io.TextIOWrapper | None = None
        self._extra: io.TextIOWrapper | None = None
        self._sim: io.BufferedWriter | None = None
        self._reconciled = mode != "resume"
        if mode == "resume" and decisions.exists():
            self._open_csv(write_header=False)

    # -- writing ------------------------------------------------------------------------------

    @property
    def next_frame(self) -> int:
        """The frame index after the last one written (0 for a new run)."""
        return self._last_frame + 1

    @property
    def stages(self) -> list[str] | None:
        """The timing stages, once known."""
        return None if self._stages is None else list(self._stages)

    @property
    def rows(self) -> int:
        """Rows written so far (with those of the run resumed)."""
        return self._rows

    def add(
        self,
        frame_index: int,
        timestamp: float,
        status: str,
        candidate: int,
        score: float,
        raw_score: float,
        accepted: bool,
        stage_ms: Mapping[str, float],
        extra: Mapping[str, Any] | None = None,
        *,
        similarity: np.ndarray | None = None,
        commit: Callable[[], Mapping[str, float]] | None = None,
    ) -> None:
        """Append one frame's decision and flush it to disk.

        Args:
            frame_index: the frame's index in the dataset; strictly increasing.
            timestamp: seconds, NaN when unknown.
            status: the stage that decided (e.g. "accepted", "low_score"); no commas.
            candidate: the candidate frame index, or -1 for none.
            score: normalised score of the candidate (higher = more confident), NaN for none.
            raw_score: the raw similarity score, NaN for none.
            accepted: whether the detector accepted the loop.
            stage_ms: milliseconds per stage for this frame (missing stages are written NaN).
            extra: per-frame extras (JSON-serialisable), appended to ``extra.jsonl``.
            similarity: (frame_index,) float scores of this frame against frames 0 .. i-1,
                appended to ``similarity.rows`` (frames must then run 0, 1, 2, ...); None for none.
            commit: called once the decision is journalled (``pending.json``) and before its
                row is written: the caller's own durable step (the detector's database
                commit). It returns milliseconds to add to stages of this row. A process
                killed between the two leaves a journal that :meth:`reconcile` replays.

        Raises:
            InputError: a frame index not after the previous one, a candidate that is not an
                earlier frame, a status with a comma or newline, or an undeclared stage.
        """
        if self._closed:
            raise InputError(f"{self.path}: run writer is closed")
        if not self._reconciled:
            self.reconcile(None)
        frame_index = int(frame_index)
        candidate = int(candidate)
        status = str(status)
        self._check_row(frame_index, candidate, status, stage_ms, similarity)
        times = {k: float(stage_ms.get(k, math.nan)) for k in self._stages or []}
        row = [
            str(frame_index),
            _fmt(timestamp),
            status,
            str(candidate),
            _fmt(score),
            _fmt(raw_score),
            "1" if accepted else "0",
        ]
        extra_line = None
        if extra:
            extra_line = json.dumps(_json_safe({"frame": frame_index, **extra}))
        if similarity is not None:
            self._append_similarity(frame_index, similarity)
        if commit is not None:
            write_json(self.path / PENDING, {"row": row, "times": times, "extra": extra_line})
            for k, ms in commit().items():
                if k in times:
                    times[k] = times[k] + float(ms) if math.isfinite(times[k]) else float(ms)
        self._write_row(frame_index, row, times, extra_line)
        if commit is not None:
            (self.path / PENDING).unlink(missing_ok=True)

    def _check_row(
        self,
        frame_index: int,
        candidate: int,
        status: str,
        stage_ms: Mapping[str, float],
        similarity: np.ndarray | None,
    ) -> None:
        if frame_index <= self._last_frame:
            raise InputError(f"frame {frame_index}: expected a frame after {self._last_frame}")
        if candidate < -1 or candidate >= frame_index:
            raise InputError(f"frame {frame_index}: candidate {candidate} is not an earlier frame (or -1)")
        if not status or any(ch in status for ch in ',\n\r"'):
            raise InputError(
                f'frame {frame_index}: status {status!r} must be non-empty without , " or newlines'
            )
        if self._stages is None:
            self._stages = list(stage_ms)
        unknown = [k for k in stage_ms if k not in self._stages]
        if unknown:
            raise InputError(
                f"frame {frame_index}: stage {unknown[0]!r} not among the run's stages {self._stages}; "
                "declare every stage when creating the RunWriter"
            )
        if similarity is not None and frame_index != self._rows:
            raise InputError(
                f"frame {frame_index}: similarity rows need frames 0, 1, 2, ... (expected {self._rows})"
            )

    def _write_row(
        self, frame_index: int, row: list[str], times: Mapping[str, float], extra: str | None
    ) -> None:
        """The extras line, then the CSV row (the run's commit record), both flushed."""
        if extra is not None:
            if self._extra is None:
                self._extra = _open_append(self.path / EXTRA, "per-frame extras")
            self._extra.write(extra + "\n")
            self._extra.flush()
        if self._csv is None:
            self._open_csv(write_header=True)
        assert self._csv is not None
        values = [float(times.get(k, math.nan)) for k in self._stages or []]
        self._csv.write(",".join([*row, *(_fmt(t) for t in values)]) + "\n")
        self._csv.flush()
        for k, t in zip(self._stages or [], values, strict=True):
            self._times.setdefault(k, []).append(t)
        self._last_frame = frame_index
        self._rows += 1

    def _append_similarity(self, frame_index: int, row: np.ndarray) -> None:
        values = np.zeros(frame_index, np.float32)
        r = np.asarray(row, dtype=np.float32).ravel()[:frame_index]
        values[: r.size] = np.nan_to_num(r, nan=0.0)
        if self._sim is None:
            path = own_file(self.path / SIMILARITY_ROWS, "similarity rows")
            if not path.is_file() and frame_index > 0:
                self._rows_from_matrix(path, frame_index)
            have = path.stat().st_size if path.is_file() else 0
            if have != 4 * (frame_index * (frame_index - 1) // 2):
                raise DatasetError(
                    f"{path}: holds {have} bytes, not the similarity rows of frames 0..{frame_index - 1}; "
                    "this run cannot continue its similarity matrix (start it again, or turn similarity off)"
                )
            fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | _NOFOLLOW, 0o644)
            self._sim = open(fd, "ab")  # noqa: SIM115 - the writer keeps it open
        self._sim.write(values.tobytes())
        self._sim.flush()

    def _rows_from_matrix(self, path: Path, n: int) -> None:
        """The similarity rows of frames 0..n-1 from ``similarity.npy`` (a closed run being
        continued keeps its matrix, not its rows), when the matrix covers them."""
        matrix_path = own_file(self.path / SIMILARITY, "similarity matrix")
        if not matrix_path.is_file():
            return
        m = read_npy(matrix_path, "similarity matrix", mmap=True)
        if m.ndim != 2 or m.shape[0] < n or m.shape[1] < n:
            return
        tmp = path.with_name(path.name + ".tmp")
        tmp.unlink(missing_ok=True)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW, 0o644)
        with os.fdopen(fd, "wb") as fh:
            for i in range(1, n):
                fh.write(np.asarray(m[i, :i], dtype=np.float32).tobytes())
        os.replace(tmp, path)

    def reconcile(self, committed: int | None = None) -> int:
        """Bring a resumed run in line with the caller's durable state after a kill anywhere.

        The CSV rows are the run's record. A journalled frame (``pending.json``) is replayed
        when ``committed`` (the number of frames the caller's own store holds, e.g. the
        detector's map) says its commit happened, and dropped otherwise; extras and similarity
        rows written past the last row are dropped.

        Args:
            committed: frames the caller's store holds; None when there is none (the
                journal is then dropped).

        Returns:
            The frame to continue from (:attr:`next_frame`).

        Raises:
            DatasetError: the store and the rows disagree by more than the journalled frame.
        """
        pending = self.path / PENDING
        if own_file(pending, "pending decision").is_file():
            journal = _read_journal(pending, len(BASE_COLUMNS))
            if journal is not None and journal[0] == self.next_frame and committed == self._rows + 1:
                frame, row, times, extra = journal
                self._trim_after(frame, frame + 1)  # its similarity row was written before it
                # the commit's own time was not recorded: add and total are unknown for this frame
                times = {k: math.nan if k in ("add", "total") else v for k, v in times.items()}
                self._write_row(frame, row, times, extra)
                logger.warning("%s: frame %d was committed, its row not written: replayed", self.path, frame)
            pending.unlink()
        self._trim_after(self.next_frame)
        self._reconciled = True
        if committed is not None and committed != self._rows:
            raise DatasetError(
                f"{self.path}: the map holds {committed} frames but {DECISIONS} has {self._rows}; "
                "cannot resume this run (start it again without --resume)"
            )
        return self.next_frame

    def _trim_after(self, frame: int, similarity_rows: int | None = None) -> None:
        """Drop extras of frames >= ``frame`` and similarity rows past the first
        ``similarity_rows`` (default ``frame``): what was written past the last row.

        Raises:
            DatasetError: the similarity rows stop short of the decisions.
        """
        extra = own_file(self.path / EXTRA, "per-frame extras")
        if extra.is_file():
            _truncate_partial_line(extra)
            data = extra.read_bytes()
            keep = 0
            for line in data.splitlines(keepends=True):
                try:
                    f = int(json.loads(line).get("frame", -1))
                except (json.JSONDecodeError, AttributeError, TypeError, ValueError, UnicodeDecodeError):
                    break
                if f >= frame:
                    break
                keep += len(line)
            if keep < len(data):
                with extra.open("r+b") as fh:
                    fh.truncate(keep)
        rows = own_file(self.path / SIMILARITY_ROWS, "similarity rows")
        if rows.is_file():
            k = frame if similarity_rows is None else similarity_rows
            size = 4 * (k * (k - 1) // 2)
            if rows.stat().st_size > size:
                with rows.open("r+b") as fh:
                    fh.truncate(size)
            elif rows.stat().st_size < size:
                raise DatasetError(f"{rows}: holds fewer similarity rows than {DECISIONS} has frames ({k})")

    def set_similarity(self, matrix: np.ndarray) -> None:
        """Save the (N, N) similarity matrix as float32 ``similarity.npy`` (atomic; may repeat).

        Args:
            matrix: (N, N) float: score of query i against earlier frame j, 0 where not computed.

        Raises:
            InputError: not a square 2-D numeric array.
        """
        m = np.asarray(matrix)
        if m.ndim != 2 or m.shape[0] != m.shape[1] or m.dtype.kind not in "biuf":
            raise InputError(f"similarity: expected a square N x N numeric matrix, got {m.shape} {m.dtype}")
        tmp = self.path / (SIMILARITY + ".tmp.npy")
        tmp.unlink(missing_ok=True)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW, 0o644)
        with os.fdopen(fd, "wb") as fh:
            np.save(fh, np.nan_to_num(m.astype(np.float32, copy=False), nan=0.0))
        os.replace(tmp, self.path / SIMILARITY)

    def _similarity_from_rows(self) -> None:
        """Write ``similarity.npy`` (N x N float32) from the appended rows, one row at a time."""
        rows = self.path / SIMILARITY_ROWS
        n = self._rows
        tmp = self.path / (SIMILARITY + ".tmp.npy")
        tmp.unlink(missing_ok=True)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW, 0o644)
        with os.fdopen(fd, "wb") as out, rows.open("rb") as src:
            np.lib.format.write_array_header_1_0(
                out, {"descr": "<f4", "fortran_order": False, "shape": (n, n)}
            )
            for i in range(n):
                line = np.zeros(n, np.float32)
                line[:i] = np.frombuffer(src.read(4 * i), np.float32, count=i) if i else line[:0]
                out.write(line.tobytes())
        os.replace(tmp, self.path / SIMILARITY)

    def add_match_picture(self, name: str, png: str | Path | np.ndarray) -> Path:
        """Store a match picture as ``matches/<name>.png``.

        Args:
            name: file stem: letters, digits, ``_ . -`` (e.g. "loop_0153_0012").
            png: a PNG file to copy, or an (H, W) / (H, W, 3) BGR uint8 image to encode.

        Returns:
            The stored file.

        Raises:
            InputError: a bad name, a missing file, or an image that is not uint8.
        """
        if not _NAME_RE.match(name):
            raise InputError(f"match picture name {name!r}: use letters, digits, '_', '.', '-'")
        folder = own_file(self.path / MATCHES, "match pictures folder")
        folder.mkdir(exist_ok=True)
        dest = folder / (name if name.endswith(".png") else name + ".png")
        if isinstance(png, np.ndarray):
            import cv2

            if png.dtype != np.uint8:
                raise InputError(f"match picture {name}: expected a uint8 image, got {png.dtype}")
            ok, buf = cv2.imencode(".png", png)
            if not ok:
                raise InputError(f"match picture {name}: could not encode an image of shape {png.shape}")
            data = buf.tobytes()
        else:
            src = Path(png)
            if not src.is_file():
                raise InputError(f"{src}: match picture not found")
            data = src.read_bytes()
        own_file(dest, "match picture").unlink(missing_ok=True)
        fd = os.open(dest, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW, 0o644)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        return dest

    def close(self) -> None:
        """Write ``timings.json`` (and ``similarity.npy`` from its rows) and mark the run complete."""
        if self._closed:
            return
        if self._csv is None and self._stages is not None:
            self._open_csv(write_header=True)  # an empty run still has a header
        for handle in (self._csv, self._extra, self._sim):
            if handle is not None:
                handle.flush()
                os.fsync(handle.fileno())
                handle.close()
        self._closed = True
        if (self.path / SIMILARITY_ROWS).is_file():
            self._similarity_from_rows()
            (self.path / SIMILARITY_ROWS).unlink()  # the matrix holds them now
        arrays = {k: np.asarray(v, dtype=np.float64) for k, v in self._times.items()}
        write_json(self.path / TIMINGS, timing_table(arrays))
        self.meta.update({"finished": _now(), "frames_written": self._rows, "complete": True})
        write_json(self.path / META, self.meta)
        self._unlock()

    def __enter__(self) -> RunWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- helpers ------------------------------------------------------------------------------

    def _open_csv(self, *, write_header: bool) -> None:
        self._csv = _open_append(self.path / DECISIONS, "per-frame decisions")
        if write_header:
            stages = self._stages or []
            self._csv.write(",".join([*BASE_COLUMNS, *(f"t_{s}_ms" for s in stages)]) + "\n")
            self._csv.flush()

    def _clear(self, keep: tuple[str, ...] = ()) -> None:
        """Delete the run's own files (never a file of the user's, never through a link)."""
        for name in (DECISIONS, EXTRA, SIMILARITY, SIMILARITY_ROWS, TIMINGS, PENDING):
            if name not in keep:
                (self.path / name).unlink(missing_ok=True)
        for p in self.path.glob("eval_*.json"):
            p.unlink()
        folder = self.path / MATCHES
        if folder.is_symlink():
            folder.unlink()
        elif folder.is_dir():
            for p in folder.glob("*.png"):
                if p.is_symlink() or p.is_file():
                    p.unlink()
            if not any(folder.iterdir()):
                folder.rmdir()


def _read_journal(
    path: Path, width: int
) -> tuple[int, list[str], dict[str, float], str | None] | None:
    """(frame, row fields, stage times, extras line) of ``pending.json``; None when malformed."""
    try:
        doc = read_json(path, "pending decision")
    except DatasetError:
        return None
    row, times, extra = doc.get("row"), doc.get("times"), doc.get("extra")
    if not isinstance(row, list) or len(row) != width or not isinstance(times, dict):
        return None
    if not str(row[0]).isdigit() or not (extra is None or isinstance(extra, str)):
        return None
    try:
        stage_ms = {str(k): math.nan if v is None else float(v) for k, v in times.items()}
    except (TypeError, ValueError):
        return None
    return int(row[0]), [str(v) for v in row], stage_ms, extra


def _check_out_dir(path: Path, mode: str) -> None:
    """Refuse an output directory that ``mode`` may not use.

    Raises:
        DatasetError: "new" on a directory that exists and is not empty; "overwrite" or
            "resume" on a non-empty directory that holds no run; a path that is not a directory.
    """
    if not path.exists():
        return
    if not path.is_dir():
        raise DatasetError(f"{path}: exists and is not a directory")
    if not any(path.iterdir()):
        return
    holds_run = any(os.path.lexists(path / name) for name in (DECISIONS, META, CONFIG))
    if mode == "new":
        if (path / DECISIONS).exists():
            raise DatasetError(f"{path}: already holds a run ({DECISIONS}); overwrite or resume it")
        raise DatasetError(f"{path}: exists and is not empty; choose a new run directory (or overwrite it)")
    if not holds_run:
        raise DatasetError(
            f"{path}: not empty and holds no run (no {DECISIONS}, {META}); refusing to {mode} it"
        )


def _truncate_partial_line(path: Path) -> None:
    data = own_file(path, "run file").read_bytes()
    if data and not data.endswith(b"\n"):
        cut = data.rfind(b"\n") + 1
        with path.open("r+b") as fh:
            fh.truncate(cut)


@dataclass(frozen=True, eq=False)
class Run:
    """A run directory, read and checked.

    Attributes:
        path: the directory.
        config: ``config.json``.
        meta: ``meta.json``.
        frames: (M,) int64 frame indices, strictly increasing.
        timestamps: (M,) float64 seconds (NaN unknown).
        status: (M,) object array of status strings.
        candidates: (M,) int64 candidate frame, -1 for none.
        scores: (M,) float64 normalised scores (NaN for none).
        raw_scores: (M,) float64 raw scores.
        accepted: (M,) bool.
        stage_ms: stage -> (M,) float64 milliseconds.
        truncated: True when a partial last line (a killed run) was dropped.
    """

    path: Path
    config: dict[str, Any]
    meta: dict[str, Any]
    frames: np.ndarray
    timestamps: np.ndarray
    status: np.ndarray
    candidates: np.ndarray
    scores: np.ndarray
    raw_scores: np.ndarray
    accepted: np.ndarray
    stage_ms: dict[str, np.ndarray]
    truncated: bool = False
    _similarity: list[np.ndarray | None] = field(default_factory=list, repr=False)

    def __len__(self) -> int:
        return int(self.frames.size)

    @property
    def name(self) -> str:
        """A label for tables: the directory's name."""
        return self.path.name

    @property
    def complete(self) -> bool:
        """Whether the run was closed properly."""
        return self.meta.get("complete", False) is True  # "no", 1, "true": not a completed run

    @property
    def similarity(self) -> np.ndarray | None:
        """(N, N) float32 similarity matrix (memory-mapped), or None when the run has none."""
        if not self._similarity:
            self._similarity.append(_load_similarity(self.path / SIMILARITY, self.frames))
        return self._similarity[0]

    @property
    def matches(self) -> list[Path]:
        """Match pictures, sorted by name: regular files in ``matches/`` only (a symbolic link,
        which could point anywhere, is left out with a warning)."""
        folder = self.path / MATCHES
        if folder.is_symlink() or not folder.is_dir():
            if folder.is_symlink():
                logger.warning("%s: is a symbolic link; its pictures are not shown", folder)
            return []
        out = []
        for p in sorted(folder.glob("*.png")):
            if p.is_symlink() or not p.is_file():
                logger.warning("%s: not a regular file in the run (a symbolic link?); left out", p)
                continue
            out.append(p)
        return out

    def meta_int(self, key: str, default: int | None = None) -> int | None:
        """``meta.json``'s integer ``key`` (``default`` when absent or null).

        Raises:
            DatasetError: the value is not a whole number.
        """
        value = self.meta.get(key)
        if value is None:
            return default
        if isinstance(value, bool) or not isinstance(value, int | float) or value != int(value):
            raise DatasetError(f"{self.path / META}: {key!r} should be a whole number, found {value!r:.40}")
        return int(value)

    def extra(self) -> list[dict[str, Any]]:
        """Rows of ``extra.jsonl`` (empty when there is none); a partial last line is dropped."""
        p = own_file(self.path / EXTRA, "per-frame extras")
        if not p.is_file():
            return []
        out = []
        lines = read_text(p, "per-frame extras").splitlines()
        if len(lines) > len(self) + 1:
            raise DatasetError(f"{p}: {len(lines)} lines for the {len(self)} frames of {DECISIONS}")
        for lineno, line in enumerate(lines, 1):
            if len(line) > MAX_EXTRA_LINE_CHARS:  # a decision's record is a few kB
                raise DatasetError(f"{p}: line {lineno} is {len(line)} characters long, more than the "
                                   f"{MAX_EXTRA_LINE_CHARS} a frame's record may take")
            try:
                value = json.loads(line)
            except json.JSONDecodeError:
                if lineno == len(lines):  # the partial last line of a killed run
                    break
                raise DatasetError(f"{p}: line {lineno} is not valid JSON") from None
            except RecursionError:
                raise DatasetError(f"{p}: line {lineno} is nested too deeply") from None
            out.append(_checked_extra(value, p, lineno))
        return out

    def timings(self) -> dict[str, dict[str, Any]]:
        """The per-stage timing table, the first frame apart (from ``timings.json``, else computed
        from the rows)."""
        p = own_file(self.path / TIMINGS, "timings")
        if p.is_file() and self.complete:
            table = read_json(p, "timings")
            for stage, row in table.items():
                if not _is_timing_row(row):
                    raise DatasetError(f"{p}: stage {stage!r} should map to numbers (mean, std, ...)")
            if all("first" in row for row in table.values()):
                return table
            # written before the first frame was kept apart: computed again from the rows
        return timing_table(self.stage_ms)

    def status_counts(self) -> dict[str, int]:
        """How many frames ended with each status (e.g. how many each stage rejected)."""
        if not len(self):
            return {}
        names, counts = np.unique(self.status.astype(str), return_counts=True)
        return {str(k): int(v) for k, v in zip(names.tolist(), counts.tolist(), strict=True)}

    def evaluations(self) -> dict[str, dict[str, Any]]:
        """The ``eval_*.json`` files of the run: file stem -> contents."""
        return {p.stem: read_json(p, "evaluation") for p in sorted(self.path.glob("eval_*.json"))}


#: the largest frame index a run may hold (exact in float64, and in every int column)
MAX_FRAME = 2**53
#: the longest ``extra.jsonl`` line read (a frame's record: its results, islands and checks)
MAX_EXTRA_LINE_CHARS = 1 << 20

#: the lists of an ``extra.jsonl`` record that the loss funnel reads, and how long each item is
_EXTRA_LISTS = {"results": 2, "islands": 4, "checked": 3}


def _whole(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and -1 <= value <= MAX_FRAME


def _number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _checked_extra(value: object, path: Path, lineno: int) -> dict[str, Any]:
    """One ``extra.jsonl`` record, checked for what readers take from it: an object whose
    ``frame`` is a whole number in range and whose ``results`` / ``islands`` / ``checked`` are
    lists of lists that start with a frame (and hold numbers where a score is read)."""
    where = f"{path}: line {lineno}"
    if not isinstance(value, dict):
        raise DatasetError(f"{where}: expected a JSON object, got {type(value).__name__}")
    frame = value.get("frame")
    if not _whole(frame) or frame < 0:  # type: ignore[operator]
        raise DatasetError(f"{where}: 'frame' must be a whole number in 0..{MAX_FRAME}, got {frame!r:.40}")
    for key, least in _EXTRA_LISTS.items():
        items = value.get(key)
        if items is None:
            continue
        if not isinstance(items, list) or not all(
                isinstance(it, list) and len(it) >= least and _whole(it[0]) for it in items):
            raise DatasetError(f"{where}: '{key}' must be a list of lists of at least {least} values "
                               "starting with a frame")
        if key in ("results", "islands") and not all(all(_number(v) for v in it) for it in items):
            raise DatasetError(f"{where}: '{key}' must hold numbers only")
    return value


def load_run(path: str | Path) -> Run:
    """Read and check a run directory.

    Raises:
        DatasetError: missing directory or file, bad header, malformed row, frames not
            increasing, or a similarity matrix that is not square.
    """
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(f"{root}: run directory not found")
    config = read_json(root / CONFIG, "run configuration")
    meta = read_json(root / META, "run metadata")
    decisions = root / DECISIONS
    lines, truncated = _decision_lines(decisions)
    stages = _stage_columns(decisions, lines[0])
    planned = [v for k in ("frames", "dataset_frames") if isinstance(v := meta.get(k), int)
               and not isinstance(v, bool) and v >= 0]
    if planned and len(lines) - 1 > max(planned):  # checked before the rows are parsed
        raise DatasetError(f"{decisions}: {len(lines) - 1} rows, but {root / META} gives the run "
                           f"{max(planned)} frames")
    rows = _parse_rows(decisions, lines[1:], len(BASE_COLUMNS) + len(stages))
    _check_frame_order(decisions, rows.frames, rows.candidates)
    return Run(
        path=root,
        config=config,
        meta=meta,
        frames=rows.frames,
        timestamps=rows.timestamps,
        status=rows.status,
        candidates=rows.candidates,
        scores=rows.scores,
        raw_scores=rows.raw_scores,
        accepted=rows.accepted,
        stage_ms={s: rows.stage_ms[i] for i, s in enumerate(stages)},
        truncated=truncated,
    )


class _Rows(NamedTuple):
    """The columns of ``decisions.csv``'s rows (see :class:`Run`); stage_ms is (S, M)."""

    frames: np.ndarray
    timestamps: np.ndarray
    status: np.ndarray
    candidates: np.ndarray
    scores: np.ndarray
    raw_scores: np.ndarray
    accepted: np.ndarray
    stage_ms: np.ndarray


def _decision_lines(decisions: Path) -> tuple[list[str], bool]:
    """The non-blank lines of ``decisions.csv`` (header first) and whether a partial last line was dropped.

    Raises:
        DatasetError: the file is missing or holds no header.
    """
    own_file(decisions, "per-frame decisions")
    if not decisions.is_file():
        raise DatasetError(f"{decisions}: per-frame decisions not found")
    text = read_text(decisions, "per-frame decisions")
    truncated = bool(text) and not text.endswith("\n")
    lines = text.split("\n")
    if truncated:
        logger.warning("%s: dropping a partial last line (the run was interrupted)", decisions)
        lines = lines[:-1]
    lines = [ln for ln in lines if ln.strip()]
    if not lines:
        raise DatasetError(f"{decisions}: expected a header line, found an empty file")
    return lines, truncated


def _stage_columns(decisions: Path, header_line: str) -> list[str]:
    """The stage names of the header's ``t_<stage>_ms`` columns, after the base columns.

    Raises:
        DatasetError: a header not starting with the base columns, or another column name.
    """
    try:
        header = next(csv.reader([header_line]))
    except csv.Error as exc:
        raise DatasetError(f"{decisions}: the header line is not CSV ({exc})") from None
    if tuple(header[: len(BASE_COLUMNS)]) != BASE_COLUMNS:
        raise DatasetError(
            f"{decisions}: expected the header to start {','.join(BASE_COLUMNS)}, found {header_line[:80]}"
        )
    stages = []
    for col in header[len(BASE_COLUMNS) :]:
        m = _STAGE_RE.match(col)
        if not m:
            raise DatasetError(f"{decisions}: expected timing columns named t_<stage>_ms, found {col!r}")
        stages.append(m.group(1))
    return stages


def _parse_rows(decisions: Path, lines: list[str], width: int) -> _Rows:
    """Parse the data lines (line ``k`` of ``lines`` is line ``k + 2`` of the file).

    Raises:
        DatasetError: a line without ``width`` fields or with a malformed value.
    """
    m_rows = len(lines)
    rows = _Rows(
        frames=np.empty(m_rows, np.int64),
        timestamps=np.empty(m_rows, np.float64),
        status=np.empty(m_rows, dtype=object),
        candidates=np.empty(m_rows, np.int64),
        scores=np.empty(m_rows, np.float64),
        raw_scores=np.empty(m_rows, np.float64),
        accepted=np.empty(m_rows, bool),
        stage_ms=np.empty((width - len(BASE_COLUMNS), m_rows), np.float64),
    )
    for k, line in enumerate(lines):
        parts = line.split(",")
        if len(parts) != width:
            raise DatasetError(f"{decisions}: line {k + 2} has {len(parts)} fields, expected {width}")
        try:
            rows.frames[k] = int(parts[0])
            rows.timestamps[k] = float(parts[1])
            rows.status[k] = parts[2]
            rows.candidates[k] = int(parts[3])
            rows.scores[k] = float(parts[4])
            rows.raw_scores[k] = float(parts[5])
            if parts[6] not in ("0", "1"):
                raise ValueError(parts[6])
            rows.accepted[k] = parts[6] == "1"
            rows.stage_ms[:, k] = [float(v) for v in parts[7:]]
        except (ValueError, OverflowError) as exc:  # 2**70 does not fit an int64 frame
            raise DatasetError(f"{decisions}: line {k + 2} has a malformed value ({exc})") from None
    if rows.frames.size and (rows.frames.min() < 0 or rows.frames.max() > MAX_FRAME):
        k = int(np.flatnonzero((rows.frames < 0) | (rows.frames > MAX_FRAME))[0])
        raise DatasetError(f"{decisions}: line {k + 2}: frame {rows.frames[k]} is not in 0..{MAX_FRAME}")
    return rows


def _check_frame_order(decisions: Path, frames: np.ndarray, cands: np.ndarray) -> None:
    """Raise unless frames strictly increase and every candidate is an earlier frame (or -1).

    Raises:
        DatasetError: naming the first offending line.
    """
    if frames.size > 1 and np.any(np.diff(frames) <= 0):
        k = int(np.flatnonzero(np.diff(frames) <= 0)[0])
        raise DatasetError(
            f"{decisions}: frames must increase, line {k + 3} has frame {frames[k + 1]} after {frames[k]}"
        )
    bad = (cands < -1) | (cands >= frames)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise DatasetError(
            f"{decisions}: line {k + 2}: candidate {cands[k]} is not an earlier frame than {frames[k]}"
        )


def _load_similarity(path: Path, frames: np.ndarray) -> np.ndarray | None:
    own_file(path, "similarity matrix")
    if not path.is_file():
        return _similarity_rows(path.with_name(SIMILARITY_ROWS), int(frames.size))
    # a row per frame at most: a matrix larger than the run's frames is refused from its header,
    # before its data is touched (a sparse 20000^2 file under a 40-frame run cost 1.7 GB)
    side = int(frames[-1]) + 1 if frames.size else 0
    m = read_npy(path, "similarity matrix", mmap=True, max_side=side)
    if m.ndim != 2 or m.shape[0] != m.shape[1] or m.dtype.kind != "f":
        raise DatasetError(
            f"{path}: expected a square float N x N similarity matrix, found {m.shape} {m.dtype}"
        )
    if frames.size and m.shape[0] <= frames[-1]:
        # a run killed between two similarity checkpoints: the matrix covers a prefix
        logger.warning(
            "%s: %d x %d covers frames up to %d only", path, m.shape[0], m.shape[0], m.shape[0] - 1
        )
    return np.asarray(m)


def _is_timing_row(row: object) -> bool:
    return isinstance(row, dict) and all(
        v is None or (isinstance(v, int | float) and not isinstance(v, bool)) for v in row.values()
    )


def _similarity_rows(path: Path, n: int) -> np.ndarray | None:
    """The (n, n) similarity matrix of a run that was not closed, from its appended rows."""
    if not own_file(path, "similarity rows").is_file():
        return None
    rows = min(n, _rows_in(path.stat().st_size))
    flat = np.fromfile(path, dtype=np.float32, count=rows * (rows - 1) // 2)
    out = np.zeros((rows, rows), np.float32)
    for i in range(1, rows):
        start = i * (i - 1) // 2
        out[i, :i] = flat[start : start + i]
    return out


def _rows_in(size: int) -> int:
    """Whole rows in a similarity-rows file of ``size`` bytes (row i holds i float32 values)."""
    k = int((1 + math.isqrt(1 + 8 * (size // 4))) // 2)
    while k * (k - 1) // 2 > size // 4:
        k -= 1
    return k
