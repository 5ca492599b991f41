"""Loop detection: the streaming :class:`LoopDetector`, its decisions and presets, the one
frame-preparation path, and two-image verification built on it."""

from typing import TYPE_CHECKING

from .._lazy import lazy_names

if TYPE_CHECKING:
    from .config import DetectorConfig, QueryConfig, preset
    from .decision import Island, LoopDecision, Status
    from .detector import LoopDetector, compute_islands
    from .pair import ImagePairVerifier, PairFrame, PairVerification
    from .prepare import FramePreparer, PreparedFrame, Segmenter
    from .presets import DEFAULT_PRESET, describe_preset, preset_names

__getattr__, __dir__ = lazy_names(
    __name__,
    {
        "config": (
            "DetectorConfig",
            "QueryConfig",
            "preset",
        ),
        "presets": (
            "DEFAULT_PRESET",
            "describe_preset",
            "preset_names",
        ),
        "decision": (
            "Island",
            "LoopDecision",
            "Status",
        ),
        "detector": (
            "LoopDetector",
            "compute_islands",
        ),
        "pair": (
            "ImagePairVerifier",
            "PairFrame",
            "PairVerification",
        ),
        "prepare": (
            "FramePreparer",
            "PreparedFrame",
            "Segmenter",
        ),
    },
)

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
