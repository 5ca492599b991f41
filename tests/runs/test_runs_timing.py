"""stablecues.runs.timing: per-stage timing tables."""

from __future__ import annotations

import numpy as np

from stablecues.runs import format_timing_table, timing_table


def test_timing_table() -> None:
    table = timing_table({"bow": np.array([1.0, 3.0, np.nan]), "verify": np.array([np.nan, np.nan, np.nan])})
    assert table["bow"] == {"mean": 2.0, "std": 1.0, "min": 1.0, "max": 3.0, "count": 2}
    assert table["verify"]["count"] == 0 and table["verify"]["mean"] is None
    assert table["total"]["mean"] == 2.0 and list(table) == ["bow", "verify", "total"]
    text = format_timing_table(table)
    assert "bow" in text and "2.00" in text
