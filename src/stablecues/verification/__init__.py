"""Geometric verification of loop candidates: triangles (the paper), PnP, fundamental matrix.

Verification works on prepared features (:class:`View`); preparing frames from images is the
detector's job (:mod:`stablecues.detection.prepare`, :mod:`stablecues.detection.pair`).
"""

from .._compat import moved_name
from .config import PRESETS, VerificationConfig, preset
from .matching import Matches, hamming_matrix, hamming_pairs, match_features
from .result import Method, Status, Verification
from .verifier import Verifier, View

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


def __getattr__(name: str) -> object:
    """Names that moved up to :mod:`stablecues.detection.pair` (deprecated here)."""
    return moved_name(__name__, name)
