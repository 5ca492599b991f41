"""The topological database: inverse index, direct index, keypoints and 3D points per entry."""

from typing import TYPE_CHECKING

from .._lazy import lazy_names

if TYPE_CHECKING:
    from .files import remove_database
    from .inverted import InvertedIndex
    from .maps import MergeReport, merge_maps
    from .store import Database, DatabaseConfig

__getattr__, __dir__ = lazy_names(
    __name__,
    {
        "files": ("remove_database",),
        "inverted": ("InvertedIndex",),
        "maps": (
            "MergeReport",
            "merge_maps",
        ),
        "store": (
            "Database",
            "DatabaseConfig",
        ),
    },
)

__all__ = ["Database", "DatabaseConfig", "InvertedIndex", "MergeReport", "merge_maps", "remove_database"]
