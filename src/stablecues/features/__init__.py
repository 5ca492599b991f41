"""Binary local features behind one :class:`Extractor` protocol."""

from .base import Extractor
from .orb import OrbConfig, OrbExtractor, distribute_quadtree

__all__ = ["Extractor", "OrbConfig", "OrbExtractor", "distribute_quadtree"]
