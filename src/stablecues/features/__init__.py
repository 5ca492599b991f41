"""Local features behind one :class:`Extractor` protocol, chosen by name (ORB, SIFT, XFeat, ...)."""

from typing import TYPE_CHECKING

from .._lazy import lazy_names

if TYPE_CHECKING:
    from .base import Extractor, ExtractorConfig
    from .orb import OrbConfig, OrbExtractor, distribute_quadtree
    from .registry import (
        DEFAULT_EXTRACTOR,
        extractor_config,
        extractor_config_class,
        extractor_names,
        make_extractor,
        register_extractor,
    )
    from .sift import SiftConfig, SiftExtractor
    from .xfeat import XFeatConfig, XFeatExtractor

__getattr__, __dir__ = lazy_names(
    __name__,
    {
        "base": (
            "Extractor",
            "ExtractorConfig",
        ),
        "orb": (
            "OrbConfig",
            "OrbExtractor",
            "distribute_quadtree",
        ),
        "registry": (
            "DEFAULT_EXTRACTOR",
            "extractor_config",
            "extractor_config_class",
            "extractor_names",
            "make_extractor",
            "register_extractor",
        ),
        "sift": (
            "SiftConfig",
            "SiftExtractor",
        ),
        "xfeat": (
            "XFeatConfig",
            "XFeatExtractor",
        ),
    },
)

__all__ = [
    "DEFAULT_EXTRACTOR",
    "Extractor",
    "ExtractorConfig",
    "OrbConfig",
    "OrbExtractor",
    "SiftConfig",
    "SiftExtractor",
    "XFeatConfig",
    "XFeatExtractor",
    "distribute_quadtree",
    "extractor_config",
    "extractor_config_class",
    "extractor_names",
    "make_extractor",
    "register_extractor",
]
