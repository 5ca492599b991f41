"""The vocabulary: descriptor ops, tree training, transform, weighting, scoring, files.

Words are binary (ORB's 32 bytes, or any width) or float (SIFT's 128 dimensions, or a learned
model's); one vocabulary holds one kind. The package ships one vocabulary per built-in
extractor (:data:`DEFAULT_VOCABULARIES`).
"""

from __future__ import annotations

from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

from .._lazy import lazy_names
from ..errors import ConfigError

if TYPE_CHECKING:
    from .io import load_vocabulary, save_vocabulary
    from .scoring import Scoring, Weighting, higher_is_better, parse_scoring, parse_weighting, score
    from .train import train_vocabulary
    from .tree import Vocabulary, VocabularyInfo

__getattr__, __dir__ = lazy_names(__name__, {
    "io": ("load_vocabulary", "save_vocabulary"),
    "scoring": ("Scoring", "Weighting", "higher_is_better", "parse_scoring", "parse_weighting", "score"),
    "train": ("train_vocabulary",),
    "tree": ("Vocabulary", "VocabularyInfo"),
})

DEFAULT_VOCABULARY = "vocab_orb_k10_L5.scv"
#: extractor name -> the vocabulary shipped for its descriptors (see ``src/stablecues/data``)
DEFAULT_VOCABULARIES = {"orb": DEFAULT_VOCABULARY, "sift": "vocab_sift_k10_L4.scv",
                        "xfeat": "vocab_xfeat_k10_L4.scv"}

__all__ = [
    "DEFAULT_VOCABULARIES", "DEFAULT_VOCABULARY", "Scoring", "Vocabulary", "VocabularyInfo",
    "Weighting", "default_vocabulary", "default_vocabulary_path", "higher_is_better",
    "load_vocabulary", "parse_scoring", "parse_weighting", "save_vocabulary", "score",
    "train_vocabulary",
]


def default_vocabulary_path(features: str = "orb") -> Path:
    """Path of the vocabulary shipped in the package for the extractor named ``features``
    ("orb": ``scripts/make_vocabulary.py``, "sift": ``scripts/make_sift_vocabulary.py``,
    "xfeat": ``scripts/make_xfeat_vocabulary.py``).

    Raises:
        ConfigError: no vocabulary is shipped for that extractor.
    """
    name = DEFAULT_VOCABULARIES.get(features)
    if name is None:
        raise ConfigError(
            f"no vocabulary is shipped for features {features!r} (only for "
            f"{', '.join(DEFAULT_VOCABULARIES)}): train one with 'stablecues vocab train "
            f"--features {features}' and pass it"
        )
    return Path(str(resources.files("stablecues") / "data" / name))


def default_vocabulary(features: str = "orb") -> Vocabulary:
    """The vocabulary shipped for the extractor named ``features`` (loaded once per process).

    ``default_vocabulary()`` is ORB's; ``default_vocabulary(config.features.name)`` the one
    matching a detector configuration's extractor.

    Raises:
        ConfigError: no vocabulary is shipped for that extractor.
    """
    return _load_default(features)


@lru_cache(maxsize=4)
def _load_default(features: str) -> Vocabulary:
    from .io import load_vocabulary

    return load_vocabulary(default_vocabulary_path(features), mmap=True)  # checked on first use
