"""Time columns of CSV files: units, clocks, date-times (no shared data)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymap3d")

from stablecues.errors import DatasetError  # noqa: E402
from stablecues.mav.tables import find_column, is_epoch_seconds, time_column_seconds  # noqa: E402


def test_time_columns_units_and_clocks(tmp_path: Path) -> None:
    p = tmp_path / "x.csv"
    t, utc = time_column_seconds(p, "utc_usec", ["1768273457875381", "1768273460875381"])
    assert utc and t[1] - t[0] == pytest.approx(3.0)
    t, utc = time_column_seconds(p, "#timestamp [ns]", ["1403636579763555584", "1403636579813555456"])
    assert utc and t[1] - t[0] == pytest.approx(0.05, abs=1e-6)
    # no unit in the name: the one giving plausible intervals (here 0.125 s in microseconds)
    t, utc = time_column_seconds(p, "timestamp", ["182092193", "182217193", "182342193"])
    assert not utc and t[0] == pytest.approx(182.092193)
    t, utc = time_column_seconds(p, "time", ["1.5", "1.6"])
    assert not utc and t[0] == 1.5
    t, utc = time_column_seconds(p, "utc", ["2026-01-13 03:04:17.875381+00:00", "2026-01-13T03:04:20.875381"])
    assert utc and t[0] == pytest.approx(1768273457.875381) and t[1] - t[0] == pytest.approx(3.0)
    with pytest.raises(DatasetError, match="ISO 8601"):
        time_column_seconds(p, "utc", ["yesterday"])


def test_epoch_detection_and_column_lookup() -> None:
    assert is_epoch_seconds(np.array([1.7e9, np.nan])) and not is_epoch_seconds(np.array([110.0, 120.0]))
    assert not is_epoch_seconds(np.array([np.nan]))
    assert find_column(["Time", "LAT", "lon"], ("latitude", "lat")) == 1
    assert find_column(["a"], ("b",)) is None
