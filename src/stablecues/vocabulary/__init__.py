"""The binary vocabulary: descriptor ops, tree training, transform, weighting, scoring, files."""

from __future__ import annotations

from functools import lru_cache
from importlib import resources
from pathlib import Path

from .io import load_vocabulary, save_vocabulary
from .scoring import Scoring, Weighting, higher_is_better, parse_scoring, parse_weighting, score
from .train import train_vocabulary
from .tree import Vocabulary, VocabularyInfo

DEFAULT_VOCABULARY = "vocab_orb_k10_L5.scv"

__all__ = [
    "DEFAULT_VOCABULARY", "Scoring", "Vocabulary", "VocabularyInfo", "Weighting",
    "default_vocabulary", "default_vocabulary_path", "higher_is_better", "load_vocabulary",
    "parse_scoring", "parse_weighting", "save_vocabulary", "score", "train_vocabulary",
]


def default_vocabulary_path() -> Path:
    """Path of the vocabulary shipped in the package (see ``scripts/make_vocabulary.py``)."""
    return Path(str(resources.files("stablecues") / "data" / DEFAULT_VOCABULARY))


@lru_cache(maxsize=1)
def default_vocabulary() -> Vocabulary:
    """The shipped vocabulary (loaded once per process)."""
    return load_vocabulary(default_vocabulary_path())
