"""Loop detection: the streaming :class:`LoopDetector`, its decisions and presets."""

from .config import DEFAULT_PRESET, DetectorConfig, QueryConfig, describe_preset, preset, preset_names
from .decision import Island, LoopDecision, Status
from .detector import LoopDetector, compute_islands

__all__ = [
    "DEFAULT_PRESET", "DetectorConfig", "Island", "LoopDecision", "LoopDetector", "QueryConfig",
    "Status", "compute_islands", "describe_preset", "preset", "preset_names",
]
