"""stablecues.runs.timing: per-stage timing tables."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues.runs import format_timing_table, timing_table


def test_timing_table() -> None:
    stages = {"bow": np.array([1.0, 3.0, np.nan]), "verify": np.array([np.nan, np.nan, np.nan])}
    table = timing_table(stages, first_apart=False)
    assert table["bow"] == {"mean": 2.0, "std": 1.0, "min": 1.0, "max": 3.0, "count": 2, "first": None}
    assert table["verify"]["count"] == 0 and table["verify"]["mean"] is None
    assert table["total"]["mean"] == 2.0 and list(table) == ["bow", "verify", "total"]
    text = format_timing_table(table)
    assert "bow" in text and "2.00" in text


def test_the_first_frame_is_kept_apart() -> None:
    """The first frame loads the models (0.5-10 s): it is left out of the figures and given as
    ``first`` (issue 35: averaged in, it made a short demo run look ten times slower)."""
    stages = {"extract": np.array([900.0, 10.0, 12.0, np.nan]), "verify": np.array([np.nan, 5, 7, 9])}
    table = timing_table(stages)
    assert table["extract"] == {"mean": 11.0, "std": 1.0, "min": 10.0, "max": 12.0, "count": 2,
                                "first": 900.0}
    assert table["verify"]["first"] is None and table["verify"]["count"] == 3
    assert table["total"]["first"] == 900.0 and table["total"]["mean"] == pytest.approx((15 + 19 + 9) / 3)
    text = format_timing_table(table)
    assert "1st frame" in text and "900.00" in text and "left out of the figures" in text
    single = timing_table({"extract": np.array([900.0])})  # one frame: nothing to keep it apart from
    assert single["extract"]["mean"] == 900.0 and single["extract"]["first"] is None
    assert "left out" not in format_timing_table(single) and "1st frame" not in format_timing_table(single)
