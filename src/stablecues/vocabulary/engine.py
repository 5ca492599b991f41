"""Where the transform runs: compiled kernels when numba is there, NumPy otherwise.

Two engines compute the same thing, to the last bit:

``"compiled"``
    numba kernels (:mod:`stablecues.vocabulary._compiled`): the greedy descent a group of
    descriptors at a time with hardware popcount (binary words; float words: Euclidean
    distance summed in a fixed order), and the BoW vector and direct index in one pass.
    numba is a dependency, so ``pip install -e .`` brings it. Machine code is cached on disk:
    only the first process on a machine compiles (a few seconds); later ones load it on
    their first transform (numba's import plus the cache, about 0.4 s), or earlier with
    :meth:`Vocabulary.warm_up`.
``"numpy"``
    the vectorised NumPy path, breadth-first over all descriptors at once. The fallback when
    numba cannot be imported or fails to compile, and the reference the compiled engine is
    tested against.

The engine is chosen per vocabulary (:attr:`Vocabulary.engine`): ``"auto"`` (the default) takes
the compiled one when it is available. Set the environment variable ``STABLECUES_ENGINE=numpy``
to make ``"auto"`` mean NumPy in a whole process (it is read when a vocabulary first chooses).
"""

from __future__ import annotations

import logging
from types import ModuleType

import numpy as np

from ..engine import ENGINES, ENV_VARIABLE, Kernels, check_engine, requested

log = logging.getLogger(__name__)

__all__ = ["ENGINES", "ENV_VARIABLE", "check_engine", "compiled_kernels", "resolve"]


def _load() -> ModuleType:
    from . import _compiled

    _warm(_compiled)
    return _compiled


_KERNELS: Kernels[ModuleType] = Kernels(_load, "the vocabulary transform")


def compiled_kernels(wait: bool = True) -> ModuleType | None:
    """The compiled kernels module, or None when numba is missing or does not work here.

    Loading imports numba and compiles (or loads from the cache) the kernels on a tiny input,
    so that a failure shows there, once, and the caller falls back to NumPy. ``wait=False``
    starts that in the background and answers None until it is done (see
    :mod:`stablecues.engine`).
    """
    return _KERNELS.get(wait)


def kernels_failed() -> bool:
    """Whether loading the kernels has finished without them (numba missing or failing here)."""
    return _KERNELS.failed()


def loaded_kernels() -> ModuleType | None:
    """The compiled kernels module if it is loaded already (never loads it: numba's import
    costs about a second in a fresh process)."""
    return _KERNELS.loaded()


def _warm(kernels: ModuleType) -> None:
    """Compile (or load from the cache) every kernel with the argument types used later."""
    q = np.zeros((1, 4), np.uint64)
    blocks = np.zeros((1, 8), np.uint64)
    kids = np.array([[1, 2]], np.int32)
    counts = np.array([2], np.int32)
    row = np.array([0, -1, -1], np.int32)
    out = np.empty(1, np.int32)
    kernels.descend(q, blocks, kids, counts, row, out)
    kernels.descend_words(q, blocks, kids, counts, row, out)
    kernels.descend_float(np.zeros((1, 2), np.float32), np.zeros((1, 4), np.float32), kids, counts, row, out)
    weight = np.array([0.0, 1.0, 1.0])
    word = np.array([-1, 0, 1], np.int32)
    table = np.arange(3, dtype=np.int32)
    fw = np.ones(1)
    kernels.assemble(out, weight, word, table, fw, True, True)
    kernels.transform(q, blocks, kids, counts, row, weight, word, table, fw, False, False)
    one = np.zeros(1, np.int64)
    node = np.zeros(1, np.int32)
    kernels.best_two_binary(q, q, node, one, node, one, 256, one.copy(), one.copy(), one.copy())
    kernels.argmax_channels(np.zeros((1, 1, 2), np.float32), np.zeros((1, 1), np.uint8))
    kernels.scatter_runs(np.zeros(1, "<i8"), np.zeros(1, "<i8"), np.ones(1, np.int64), np.zeros(1, np.int64))
    w32 = np.zeros(1, np.int32)
    mapped = np.zeros(1, np.int32)
    mapped.flags.writeable = False  # the word array of a segment file, memory-mapped read-only
    for words in (w32, mapped):
        kernels.count_words(np.zeros(1, np.int64), words, np.zeros(1, "<i8"), 0, 0, 1)
        kernels.scatter_words(np.zeros(1, "<i8"), np.zeros(1, np.int64), words, np.zeros(1, "<i8"), 0)
    for bits in (11, 20):  # one pass and two
        kernels.radix_words(w32, np.zeros(1, "<i8"), bits, np.zeros(1, np.int32), np.zeros(1, "<i8"),
                            np.zeros(1, np.int32), np.zeros(1, "<i8"))


def resolve(name: str) -> str:
    """The engine that ``name`` means here: ``"compiled"`` or ``"numpy"``.

    Args:
        name: ``"auto"``, ``"compiled"`` or ``"numpy"``.

    Raises:
        ConfigError: an unknown engine name (also in ``STABLECUES_ENGINE``).
        ImportError: ``"compiled"`` asked for explicitly where numba is not available, with
            the command that installs it.
    """
    choice = requested(name)
    if choice == "auto":  # compiled once loaded; NumPy while they load in the background
        return "compiled" if compiled_kernels(wait=False) is not None else "numpy"
    if choice == "compiled" and compiled_kernels() is None:
        raise ImportError(
            "the compiled vocabulary engine needs numba, which is missing or failed to compile "
            "here: pip install numba (or use engine='numpy')"
        )
    return choice
