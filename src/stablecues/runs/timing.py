"""Per-stage timing tables (the paper's Table 5): mean, std, min and max in milliseconds."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np


def timing_table(
    stage_ms: Mapping[str, np.ndarray], *, add_total: bool = True, first_apart: bool = True
) -> dict[str, dict[str, float | int | None]]:
    """Summarise per-frame stage times.

    Args:
        stage_ms: stage name -> (N,) float milliseconds per frame, NaN where the stage did not
            run for that frame (NaN frames are left out of that stage's figures).
        add_total: when there is no "total" stage, add one: the per-frame sum over stages
            (frames where every stage is NaN left out). Stages that nest inside each other
            would be counted twice; write a ``total`` stage yourself in that case.
        first_apart: leave the first frame out of the figures (it loads the networks, the
            vocabulary's compiled code, ...: 0.5-10 s that would swamp the mean of a short
            run) and give its time as ``first`` (when there are at least two frames).

    Returns:
        stage -> {"mean", "std", "min", "max", "count", "first"}; the figures are None when the
        stage never ran (``count`` 0), ``first`` None when the first frame is not apart or did
        not run the stage. Stages keep their order; "total" comes last.
    """
    table: dict[str, dict[str, float | int | None]] = {}
    arrays = {k: np.asarray(v, dtype=np.float64).ravel() for k, v in stage_ms.items()}
    if add_total and arrays and "total" not in arrays:
        stacked = np.vstack(list(arrays.values()))
        total = np.nansum(stacked, axis=0)
        total[np.all(np.isnan(stacked), axis=0)] = np.nan
        arrays["total"] = total
    for name, values in arrays.items():
        first: float | None = None
        if first_apart and values.size > 1:
            first = float(values[0]) if np.isfinite(values[0]) else None
            values = values[1:]
        v = values[np.isfinite(values)]
        if v.size == 0:
            table[name] = {"mean": None, "std": None, "min": None, "max": None, "count": 0, "first": first}
        else:
            table[name] = {
                "mean": float(v.mean()),
                "std": float(v.std()),
                "min": float(v.min()),
                "max": float(v.max()),
                "count": int(v.size),
                "first": first,
            }
    return table


def format_timing_table(table: Mapping[str, Mapping[str, float | int | None]]) -> str:
    """Plain-text rendering of :func:`timing_table`'s result, one line per stage; the first
    frame's warm-up (``first``) in a column of its own when the table keeps it apart."""
    apart = any(row.get("first") is not None for row in table.values())
    lines = [f"{'stage':<20} {'mean':>9} {'std':>9} {'min':>9} {'max':>9} {'count':>7}"
             + (f" {'1st frame':>10}" if apart else "") + "  (ms)"]
    for name, row in table.items():
        cells = [
            f"{row[k]:9.2f}" if row.get(k) is not None else f"{'-':>9}" for k in ("mean", "std", "min", "max")
        ]
        line = f"{name:<20} {' '.join(cells)} {int(row.get('count') or 0):>7}"
        if apart:
            first = row.get("first")
            line += f" {first:10.2f}" if first is not None else f" {'-':>10}"
        lines.append(line)
    if apart:
        lines.append("(the first frame, which loads models and compiled code, is left out of the figures)")
    return "\n".join(lines)
