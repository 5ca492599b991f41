"""Watching the detector work: live logging of each frame's decision (Rerun).

The loggers here are frame observers (``observe(frame, decision, detector)``): hand them to
:func:`stablecues.detection.run.run_dataset` (``observers=[...]``), or call them from your own
loop around :meth:`stablecues.detection.LoopDetector.process`. Their backends are optional
extras, imported only when a logger is made.
"""

from .rerun import RerunLogger, find_viewer, keypoint_classes

__all__ = ["RerunLogger", "find_viewer", "keypoint_classes"]
