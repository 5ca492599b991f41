"""The topological database: inverse index, direct index, keypoints and 3D points per entry."""

from .files import remove_database
from .inverted import InvertedIndex
from .maps import MergeReport, merge_maps
from .store import Database, DatabaseConfig

__all__ = ["Database", "DatabaseConfig", "InvertedIndex", "MergeReport", "merge_maps", "remove_database"]
