"""Meaningful feature selection: CamVid segmentation with MC-dropout uncertainty, and masking.

Inference needs only onnxruntime (``SegmentationModel``); training and export need the
``train`` extra (torch) and live in :mod:`.train`, :mod:`.model` and :mod:`.export`, which are
imported only when used.
"""

from typing import TYPE_CHECKING

from .._lazy import lazy_names

if TYPE_CHECKING:
    from .classes import CLASS_NAMES, DYNAMIC_CLASSES, NUM_CLASSES, STATIC_CLASSES, VOID_ID
    from .inference import SegmentationModel, SegmentationResult, default_weights_path
    from .masking import MASKING_PRESETS, MaskingConfig, MaskReport, pixel_mask, select_features

__getattr__, __dir__ = lazy_names(
    __name__,
    {
        "classes": (
            "CLASS_NAMES",
            "DYNAMIC_CLASSES",
            "NUM_CLASSES",
            "STATIC_CLASSES",
            "VOID_ID",
        ),
        "inference": (
            "SegmentationModel",
            "SegmentationResult",
            "default_weights_path",
        ),
        "masking": (
            "MASKING_PRESETS",
            "MaskingConfig",
            "MaskReport",
            "pixel_mask",
            "select_features",
        ),
    },
)

__all__ = [
    "CLASS_NAMES",
    "DYNAMIC_CLASSES",
    "MASKING_PRESETS",
    "NUM_CLASSES",
    "STATIC_CLASSES",
    "VOID_ID",
    "MaskReport",
    "MaskingConfig",
    "SegmentationModel",
    "SegmentationResult",
    "default_weights_path",
    "pixel_mask",
    "select_features",
]
