"""The topological database: inverse index, direct index, keypoints and 3D points per entry."""

from .inverted import InvertedIndex
from .store import Database, DatabaseConfig

__all__ = ["Database", "DatabaseConfig", "InvertedIndex"]
