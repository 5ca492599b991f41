"""Geometric verification of loop candidates: triangles (the paper), PnP, fundamental matrix.

Verification works on prepared features (:class:`View`); preparing frames from images is the
detector's job (:mod:`stablecues.detection.prepare`, :mod:`stablecues.detection.pair`).
"""

from typing import TYPE_CHECKING

from .._compat import moved_name
from .._lazy import lazy_names

if TYPE_CHECKING:
    from .config import PRESETS, VerificationConfig, preset
    from .matching import Matches, hamming_matrix, hamming_pairs, match_features
    from .result import Method, Status, Verification
    from .verifier import Verifier, View

# names that moved up to :mod:`stablecues.detection.pair` are deprecated here (moved_name)
__getattr__, __dir__ = lazy_names(__name__, {
    "config": ("PRESETS", "VerificationConfig", "preset"),
    "matching": ("Matches", "hamming_matrix", "hamming_pairs", "match_features"),
    "result": ("Method", "Status", "Verification"),
    "verifier": ("Verifier", "View"),
}, fallback=lambda name: moved_name(__name__, name))

__all__ = [
    "PRESETS",
    "Matches",
    "Method",
    "Status",
    "Verification",
    "VerificationConfig",
    "Verifier",
    "View",
    "hamming_matrix",
    "hamming_pairs",
    "match_features",
    "preset",
]

