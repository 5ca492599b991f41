"""Loop detection: the streaming :class:`LoopDetector`, its decisions and presets, the one
frame-preparation path, and two-image verification built on it."""

from .config import DEFAULT_PRESET, DetectorConfig, QueryConfig, describe_preset, preset, preset_names
from .decision import Island, LoopDecision, Status
from .detector import LoopDetector, compute_islands
from .pair import ImagePairVerifier, PairFrame, PairVerification
from .prepare import FramePreparer, PreparedFrame, Segmenter

__all__ = [
    "DEFAULT_PRESET",
    "DetectorConfig",
    "FramePreparer",
    "ImagePairVerifier",
    "Island",
    "LoopDecision",
    "LoopDetector",
    "PairFrame",
    "PairVerification",
    "PreparedFrame",
    "QueryConfig",
    "Segmenter",
    "Status",
    "compute_islands",
    "describe_preset",
    "preset",
    "preset_names",
]
