"""Run directories: the results format written by detection and read by evaluation.

:class:`RunWriter` writes one (``stablecues run``), :func:`load_run` reads one back; the
per-stage timing table lives here too because both sides use it. Nothing here knows how a
decision is made or how it is scored.
"""

from __future__ import annotations

from .store import Run, RunWriter, load_run, read_json, versions, write_json
from .timing import format_timing_table, timing_table

__all__ = [
    "Run",
    "RunWriter",
    "format_timing_table",
    "load_run",
    "read_json",
    "timing_table",
    "versions",
    "write_json",
]
