"""stablecues: place recognition and loop-closure detection with memorable, stable cues.

The public API, everything a SLAM loop needs::

    from stablecues import Frame, LoopDetector, load_calibration, preset

    detector = LoopDetector(preset("default"), database="map.sqlite",
                            calibration=load_calibration("cam.yaml"))
    decision = detector.process(Frame(index=0, name="0", timestamp=0.0, image=image))

The names are imported on first use (PEP 562), so ``import stablecues`` stays cheap and
importing one submodule never pulls in the others.
"""

from __future__ import annotations

import importlib
import logging
from typing import TYPE_CHECKING

from ._version import __version__

if TYPE_CHECKING:
    from .database import Database
    from .datasets import open_dataset
    from .detection import (
        DetectorConfig,
        FramePreparer,
        ImagePairVerifier,
        LoopDecision,
        LoopDetector,
        PreparedFrame,
        Status,
        preset,
        preset_names,
    )
    from .errors import StableCuesError
    from .features import Extractor, ExtractorConfig, make_extractor
    from .geometry import Calibration, PinholeCamera, load_calibration
    from .groundtruth import GroundTruth, load_ground_truth
    from .runs import load_run
    from .types import BowVector, DescriptorKind, Entry, Features, FeatureVector, Frame, QueryResult
    from .verification import Verification, Verifier, View
    from .vocabulary import Vocabulary, default_vocabulary, load_vocabulary

logging.getLogger(__name__).addHandler(logging.NullHandler())

_API: dict[str, str] = {
    # the values a SLAM loop hands in and gets back
    "Frame": "types",
    "Features": "types",
    "BowVector": "types",
    "FeatureVector": "types",
    "QueryResult": "types",
    "Entry": "types",
    "StableCuesError": "errors",
    # the detector and its settings
    "LoopDetector": "detection",
    "LoopDecision": "detection",
    "Status": "detection",
    "DetectorConfig": "detection",
    "preset": "detection",
    "preset_names": "detection",
    "FramePreparer": "detection",
    "PreparedFrame": "detection",
    "ImagePairVerifier": "detection",
    # cameras
    "Calibration": "geometry",
    "PinholeCamera": "geometry",
    "load_calibration": "geometry",
    # features, vocabulary, map
    "Extractor": "features",
    "ExtractorConfig": "features",
    "make_extractor": "features",
    "DescriptorKind": "types",
    "Vocabulary": "vocabulary",
    "default_vocabulary": "vocabulary",
    "load_vocabulary": "vocabulary",
    "Database": "database",
    # verification on prepared features
    "Verifier": "verification",
    "View": "verification",
    "Verification": "verification",
    # data and results
    "open_dataset": "datasets",
    "GroundTruth": "groundtruth",
    "load_ground_truth": "groundtruth",
    "load_run": "runs",
}

__all__ = [
    "__version__",
    "BowVector",
    "Calibration",
    "Database",
    "DescriptorKind",
    "DetectorConfig",
    "Entry",
    "Extractor",
    "ExtractorConfig",
    "FeatureVector",
    "Features",
    "Frame",
    "FramePreparer",
    "GroundTruth",
    "ImagePairVerifier",
    "LoopDecision",
    "LoopDetector",
    "PinholeCamera",
    "PreparedFrame",
    "QueryResult",
    "StableCuesError",
    "Status",
    "Verification",
    "Verifier",
    "View",
    "Vocabulary",
    "default_vocabulary",
    "load_calibration",
    "load_ground_truth",
    "load_run",
    "load_vocabulary",
    "make_extractor",
    "open_dataset",
    "preset",
    "preset_names",
]
"""The public names; each of them but ``__version__`` is a key of ``_API``."""


def __getattr__(name: str) -> object:
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'stablecues' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
