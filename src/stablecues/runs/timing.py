"""Per-stage timing tables (the paper's Table 5): mean, std, min and max in milliseconds."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np


def timing_table(
    stage_ms: Mapping[str, np.ndarray], *, add_total: bool = True
) -> dict[str, dict[str, float | int | None]]:
    """Summarise per-frame stage times.

    Args:
        stage_ms: stage name -> (N,) float milliseconds per frame, NaN where the stage did not
            run for that frame (NaN frames are left out of that stage's figures).
        add_total: when there is no "total" stage, add one: the per-frame sum over stages
            (frames where every stage is NaN left out). Stages that nest inside each other
            would be counted twice; write a ``total`` stage yourself in that case.

    Returns:
        stage -> {"mean", "std", "min", "max", "count"}; the figures are None when the stage
        never ran (``count`` 0). Stages keep their order; "total" comes last.
    """
    table: dict[str, dict[str, float | int | None]] = {}
    arrays = {k: np.asarray(v, dtype=np.float64).ravel() for k, v in stage_ms.items()}
    if add_total and arrays and "total" not in arrays:
        stacked = np.vstack(list(arrays.values()))
        total = np.nansum(stacked, axis=0)
        total[np.all(np.isnan(stacked), axis=0)] = np.nan
        arrays["total"] = total
    for name, values in arrays.items():
        v = values[np.isfinite(values)]
        if v.size == 0:
            table[name] = {"mean": None, "std": None, "min": None, "max": None, "count": 0}
        else:
            table[name] = {
                "mean": float(v.mean()),
                "std": float(v.std()),
                "min": float(v.min()),
                "max": float(v.max()),
                "count": int(v.size),
            }
    return table


def format_timing_table(table: Mapping[str, Mapping[str, float | int | None]]) -> str:
    """Plain-text rendering of :func:`timing_table`'s result, one line per stage."""
    lines = [f"{'stage':<20} {'mean':>9} {'std':>9} {'min':>9} {'max':>9} {'count':>7}  (ms)"]
    for name, row in table.items():
        cells = [
            f"{row[k]:9.2f}" if row.get(k) is not None else f"{'-':>9}" for k in ("mean", "std", "min", "max")
        ]
        lines.append(f"{name:<20} {' '.join(cells)} {int(row.get('count') or 0):>7}")
    return "\n".join(lines)
