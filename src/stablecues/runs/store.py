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
                     0 where not computed (may cover only a prefix of an interrupted run)
    timings.json     {stage: {mean, std, min, max, count}} in ms, written on close
    matches/*.png    optional match pictures of sample loops
    eval_<protocol>.json   written by ``stablecues eval``

Rows are flushed one at a time, so a killed run leaves a readable prefix (a partial last line
is dropped on reading); :class:`RunWriter` with ``mode="resume"`` continues such a run.
"""

from __future__ import annotations

import csv
import datetime as _dt
import io
import json
import logging
import math
import os
import platform
import re
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np

from ..errors import DatasetError, InputError
from .timing import timing_table

logger = logging.getLogger(__name__)

BASE_COLUMNS = ("frame", "timestamp", "status", "candidate", "score", "raw_score", "accepted")
DECISIONS = "decisions.csv"
EXTRA = "extra.jsonl"
SIMILARITY = "similarity.npy"
CONFIG = "config.json"
META = "meta.json"
TIMINGS = "timings.json"
MATCHES = "matches"
_STAGE_RE = re.compile(r"^t_(.+)_ms$")
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


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


def write_json(path: Path, data: Mapping[str, Any]) -> None:
    """Write strict JSON atomically (temporary file, then rename)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(_json_safe(data), indent=2, allow_nan=False) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def read_json(path: Path, what: str) -> dict[str, Any]:
    """Read a JSON object file.

    Raises:
        DatasetError: missing file, invalid JSON, or not an object.
    """
    if not path.is_file():
        raise DatasetError(f"{path}: {what} not found")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: {what} is not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: {what} should be a JSON object, found {type(data).__name__}")
    return data


def _fmt(value: float) -> str:
    return "nan" if not math.isfinite(value) else repr(float(value))


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
        mode: "new" (refuse a directory that already holds a run), "overwrite" (delete the
            previous run's files first) or "resume" (append to the run found there, keeping
            its rows; see :attr:`next_frame`).

    Raises:
        DatasetError: ``mode="new"`` on an existing run, or an unreadable run to resume.
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
        self.path.mkdir(parents=True, exist_ok=True)
        decisions = self.path / DECISIONS
        self._stages: list[str] | None = list(stages) if stages is not None else None
        self._times: dict[str, list[float]] = {}
        self._last_frame = -1
        self._rows = 0
        self._closed = False
        prior_meta: dict[str, Any] = {}
        if mode == "new" and decisions.exists():
            raise DatasetError(f"{self.path}: already holds a run ({DECISIONS}); overwrite or resume it")
        if mode == "overwrite" or (mode == "resume" and not decisions.exists()):
            self._clear()
        if mode == "resume" and decisions.exists():
            run = load_run(self.path)
            self._stages = list(run.stage_ms)
            self._times = {k: v.tolist() for k, v in run.stage_ms.items()}
            self._last_frame = int(run.frames[-1]) if len(run) else -1
            self._rows = len(run)
            prior_meta = run.meta
            _truncate_partial_line(decisions)
            if (self.path / EXTRA).exists():
                _truncate_partial_line(self.path / EXTRA)
        write_json(self.path / CONFIG, dict(config))
        self.meta: dict[str, Any] = {
            **prior_meta,
            **dict(meta),
            "versions": versions(),
            "created": prior_meta.get("created", _now()),
            "complete": False,
        }
        if prior_meta:
            self.meta["resumed"] = [*prior_meta.get("resumed", []), _now()]
        write_json(self.path / META, self.meta)
        self._csv: io.TextIOWrapper | None = None
        self._writer: Any = None
        self._extra: io.TextIOWrapper | None = None
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

        Raises:
            InputError: a frame index not after the previous one, a candidate that is not an
                earlier frame, a status with a comma or newline, or an undeclared stage.
        """
        if self._closed:
            raise InputError(f"{self.path}: run writer is closed")
        frame_index = int(frame_index)
        if frame_index <= self._last_frame:
            raise InputError(f"frame {frame_index}: expected a frame after {self._last_frame}")
        candidate = int(candidate)
        if candidate < -1 or candidate >= frame_index:
            raise InputError(f"frame {frame_index}: candidate {candidate} is not an earlier frame (or -1)")
        status = str(status)
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
        if self._csv is None:
            self._open_csv(write_header=True)
        times = [float(stage_ms.get(k, math.nan)) for k in self._stages]
        row = [
            str(frame_index),
            _fmt(timestamp),
            status,
            str(candidate),
            _fmt(score),
            _fmt(raw_score),
            "1" if accepted else "0",
            *(_fmt(t) for t in times),
        ]
        assert self._csv is not None
        self._csv.write(",".join(row) + "\n")
        self._csv.flush()
        for k, t in zip(self._stages, times, strict=True):
            self._times.setdefault(k, []).append(t)
        if extra:
            if self._extra is None:
                self._extra = (self.path / EXTRA).open("a", encoding="utf-8")
            self._extra.write(json.dumps(_json_safe({"frame": frame_index, **extra})) + "\n")
            self._extra.flush()
        self._last_frame = frame_index
        self._rows += 1

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
        np.save(tmp, np.nan_to_num(m.astype(np.float32, copy=False), nan=0.0))
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
        folder = self.path / MATCHES
        folder.mkdir(exist_ok=True)
        dest = folder / (name if name.endswith(".png") else name + ".png")
        if isinstance(png, np.ndarray):
            import cv2

            if png.dtype != np.uint8:
                raise InputError(f"match picture {name}: expected a uint8 image, got {png.dtype}")
            ok, buf = cv2.imencode(".png", png)
            if not ok:
                raise InputError(f"match picture {name}: could not encode an image of shape {png.shape}")
            dest.write_bytes(buf.tobytes())
        else:
            src = Path(png)
            if not src.is_file():
                raise InputError(f"{src}: match picture not found")
            shutil.copyfile(src, dest)
        return dest

    def close(self) -> None:
        """Write ``timings.json`` and mark the run complete in ``meta.json``."""
        if self._closed:
            return
        if self._csv is None and self._stages is not None:
            self._open_csv(write_header=True)  # an empty run still has a header
        for handle in (self._csv, self._extra):
            if handle is not None:
                handle.flush()
                os.fsync(handle.fileno())
                handle.close()
        self._closed = True
        arrays = {k: np.asarray(v, dtype=np.float64) for k, v in self._times.items()}
        write_json(self.path / TIMINGS, timing_table(arrays))
        self.meta.update({"finished": _now(), "frames_written": self._rows, "complete": True})
        write_json(self.path / META, self.meta)

    def __enter__(self) -> RunWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- helpers ------------------------------------------------------------------------------

    def _open_csv(self, *, write_header: bool) -> None:
        self._csv = (self.path / DECISIONS).open("a", encoding="utf-8", newline="")
        if write_header:
            stages = self._stages or []
            self._csv.write(",".join([*BASE_COLUMNS, *(f"t_{s}_ms" for s in stages)]) + "\n")
            self._csv.flush()

    def _clear(self) -> None:
        for name in (DECISIONS, EXTRA, SIMILARITY, TIMINGS):
            (self.path / name).unlink(missing_ok=True)
        for p in self.path.glob("eval_*.json"):
            p.unlink()
        if (self.path / MATCHES).is_dir():
            shutil.rmtree(self.path / MATCHES)


def _truncate_partial_line(path: Path) -> None:
    data = path.read_bytes()
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
        return bool(self.meta.get("complete", False))

    @property
    def similarity(self) -> np.ndarray | None:
        """(N, N) float32 similarity matrix (memory-mapped), or None when the run has none."""
        if not self._similarity:
            self._similarity.append(_load_similarity(self.path / SIMILARITY, self.frames))
        return self._similarity[0]

    @property
    def matches(self) -> list[Path]:
        """Match pictures, sorted by name."""
        folder = self.path / MATCHES
        return sorted(folder.glob("*.png")) if folder.is_dir() else []

    def extra(self) -> list[dict[str, Any]]:
        """Rows of ``extra.jsonl`` (empty when there is none); a partial last line is dropped."""
        p = self.path / EXTRA
        if not p.is_file():
            return []
        out = []
        lines = p.read_text(encoding="utf-8").splitlines()
        for lineno, line in enumerate(lines, 1):
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                if lineno == len(lines):  # the partial last line of a killed run
                    break
                raise DatasetError(f"{p}: line {lineno} is not valid JSON") from None
        return out

    def timings(self) -> dict[str, dict[str, Any]]:
        """The per-stage timing table (from ``timings.json``, else computed from the rows)."""
        p = self.path / TIMINGS
        if p.is_file() and self.complete:
            return read_json(p, "timings")
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
    if not decisions.is_file():
        raise DatasetError(f"{decisions}: per-frame decisions not found")
    text = decisions.read_text(encoding="utf-8")
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
    header = next(csv.reader([header_line]))
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
        except ValueError as exc:
            raise DatasetError(f"{decisions}: line {k + 2} has a malformed value ({exc})") from None
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
    if not path.is_file():
        return None
    try:
        m = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise DatasetError(f"{path}: not a readable .npy file ({exc})") from None
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
