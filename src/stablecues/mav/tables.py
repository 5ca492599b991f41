"""Small CSV helpers shared by the GNSS-track reader and camera time files.

Time columns come in many forms: seconds, milli-, micro- or nanoseconds, since boot or since
the UNIX epoch, or ISO 8601 date-times. :func:`time_column_seconds` turns any of them into
seconds and says whether they are UTC (UNIX) seconds.
"""

from __future__ import annotations

import csv
import re
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..fileio import read_text
from ..limits import MAX_CSV_FIELD_BYTES

# Seconds after 1973-03-03: anything later is taken as a UNIX (UTC) time, anything earlier as
# a time since boot. No autopilot or camera runs 3.4 years without a restart.
EPOCH_THRESHOLD_S = 1.0e8

_UNIT_HINTS: tuple[tuple[str, float], ...] = (
    (r"(nsec|_ns\b|\[ns\]|nanosec)", 1e-9),
    (r"(usec|_us\b|\[us\]|micro)", 1e-6),
    (r"(msec|_ms\b|\[ms\]|milli)", 1e-3),
    (r"(_s\b|\[s\]|sec\b|seconds)", 1.0),
)


def read_csv_table(path: Path, what: str) -> tuple[list[str], list[list[str]]]:
    """Read a CSV file with a header row (comma, semicolon or tab separated).

    A header starting with ``#`` (EuRoC ``#timestamp [ns],filename``) is accepted.

    Returns:
        The stripped column names and the data rows (lists of stripped strings).

    Raises:
        DatasetError: missing or empty file, or rows of the wrong length.
    """
    if not path.is_file():
        raise DatasetError(f"{path}: {what} not found")
    text = read_text(path, what, encoding="utf-8-sig")
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if not lines:
        raise DatasetError(f"{path}: {what} is empty, expected a header row and data rows")
    try:
        dialect: type[csv.Dialect] | csv.Dialect = csv.Sniffer().sniff(lines[0], delimiters=",;\t")
    except csv.Error:
        dialect = csv.excel
    try:
        rows = list(csv.reader(lines, dialect))
    except csv.Error as exc:  # a field over the csv module's limit, a stray quote
        raise DatasetError(
            f"{path}: {what} is not a readable CSV table ({exc}; a field holds at most {MAX_CSV_FIELD_BYTES})"
        ) from None
    header = [h.strip().lstrip("#").strip() for h in rows[0]]
    body = [[c.strip() for c in r] for r in rows[1:]]
    for k, r in enumerate(body):
        if len(r) != len(header):
            raise DatasetError(
                f"{path}: {what} row {k + 2} has {len(r)} fields, the header names {len(header)}"
            )
    return header, body


def find_column(header: list[str], candidates: tuple[str, ...]) -> int | None:
    """Index of the first header name equal (case-insensitively) to one of ``candidates``."""
    lower = [h.lower() for h in header]
    for cand in candidates:
        if cand in lower:
            return lower.index(cand)
    return None


def numbers(path: Path, name: str, values: list[str]) -> np.ndarray:
    """Parse a column of numbers; empty cells become NaN.

    Raises:
        DatasetError: a cell is not a number.
    """
    out = np.empty(len(values), dtype=np.float64)
    for k, v in enumerate(values):
        if v == "" or v.lower() == "nan":
            out[k] = np.nan
            continue
        try:
            out[k] = float(v)
        except ValueError:
            raise DatasetError(
                f"{path}: column {name!r} row {k + 2}: expected a number, found {v!r}"
            ) from None
    return out


def time_column_seconds(path: Path, name: str, values: list[str]) -> tuple[np.ndarray, bool]:
    """Convert a time column to seconds.

    The unit comes from the column name when it says (``utc_usec``, ``timestamp [ns]``,
    ``time_ms``, ``t_s``); otherwise values with a decimal point are seconds, and integers take
    the one of s / ms / us / ns that makes the median interval between rows plausible for a
    sensor or camera stream (5 ms to 20 s). ISO 8601
    date-times are read as UTC when they carry no zone.

    Returns:
        (N,) float64 seconds, and True when they are UNIX (UTC) seconds.

    Raises:
        DatasetError: unparsable values or an undecidable unit.
    """
    if values and not _is_number(values[0]):
        secs = np.array([_parse_datetime(path, name, v) for v in values], dtype=np.float64)
        return secs, True
    raw = numbers(path, name, values)
    scale = None
    for pattern, factor in _UNIT_HINTS:
        if re.search(pattern, name.lower()):
            scale = factor
            break
    if scale is None:
        # fractional values are seconds; integers get the unit that makes their spacing plausible
        scale = 1.0 if any("." in v or "e" in v.lower() for v in values) else _guess_scale(raw)
    secs = raw * scale
    return secs, is_epoch_seconds(secs)


def is_epoch_seconds(secs: np.ndarray) -> bool:
    """True when (N,) seconds are UNIX (UTC) times: their median is past :data:`EPOCH_THRESHOLD_S`."""
    finite = secs[np.isfinite(secs)]
    return bool(finite.size and np.median(finite) > EPOCH_THRESHOLD_S)


def _guess_scale(raw: np.ndarray) -> float:
    finite = raw[np.isfinite(raw)]
    steps = np.diff(np.sort(finite))
    steps = steps[steps > 0]
    if steps.size == 0:
        # a single time: pick the unit that makes it a plausible boot or epoch time
        value = abs(float(finite[0])) if finite.size else 0.0
        for factor in (1.0, 1e-3, 1e-6, 1e-9):
            if value * factor < 3.0e9:
                return factor
        return 1e-9
    step = float(np.median(steps))
    for factor in (1.0, 1e-3, 1e-6, 1e-9):
        if 0.005 <= step * factor <= 20.0:
            return factor
    return 1.0


def _is_number(v: str) -> bool:
    try:
        float(v)
    except ValueError:
        return False
    return True


def _parse_datetime(path: Path, name: str, v: str) -> float:
    try:
        dt = datetime.fromisoformat(v.replace("Z", "+00:00"))
    except ValueError:
        raise DatasetError(
            f"{path}: column {name!r}: expected a number or an ISO 8601 date-time, found {v!r}"
        ) from None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    return dt.timestamp()
