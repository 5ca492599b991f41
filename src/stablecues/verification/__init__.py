"""Geometric verification of loop candidates: triangles (the paper), PnP, fundamental matrix."""

from .config import PRESETS, VerificationConfig, preset
from .images import Frame, ImagePairVerifier, PairVerification
from .matching import Matches, hamming_matrix, hamming_pairs, match_features
from .result import Method, Status, Verification
from .verifier import Verifier, View

__all__ = [
    "PRESETS",
    "Frame",
    "ImagePairVerifier",
    "Matches",
    "Method",
    "PairVerification",
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
