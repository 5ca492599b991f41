"""Which engine the compiled paths use: ``"auto"``, ``"compiled"`` (numba) or ``"numpy"``.

Several stages have a compiled fast path and a NumPy one that gives identical results (the
vocabulary transform and the matcher, :mod:`stablecues.vocabulary.engine`; the class map of a
segmentation; ORB's keypoint spread, :mod:`stablecues.features.orb`). Each takes an engine
name; ``"auto"`` means the compiled path when numba works here, unless the environment variable
``STABLECUES_ENGINE`` names another engine for the whole process. This module holds only that
choice, so that any package can make it without importing another stage.
"""

from __future__ import annotations

import gc
import logging
import os
from collections.abc import Callable
from typing import TypeVar

from .errors import ConfigError

__all__ = ["ENGINES", "ENV_VARIABLE", "FREEZE_VARIABLE", "check_engine", "load_compiled", "requested"]

log = logging.getLogger(__name__)
T = TypeVar("T")

ENGINES = ("auto", "compiled", "numpy")
ENV_VARIABLE = "STABLECUES_ENGINE"
#: set to 0 to leave Python's garbage collector as it is when the compiled kernels load
FREEZE_VARIABLE = "STABLECUES_GC_FREEZE"


def check_engine(name: str) -> None:
    """Raise ConfigError unless ``name`` is one of :data:`ENGINES`."""
    if name not in ENGINES:
        raise ConfigError(f"vocabulary engine {name!r}: expected one of {', '.join(ENGINES)}")


def requested(name: str) -> str:
    """The engine ``name`` asks for once ``STABLECUES_ENGINE`` is applied to ``"auto"``:
    ``"auto"`` (take the compiled path when it works), ``"compiled"`` or ``"numpy"``.

    Raises:
        ConfigError: an unknown engine name, also in the environment variable.
    """
    check_engine(name)
    if name != "auto":
        return name
    env = os.environ.get(ENV_VARIABLE, "auto").strip().lower() or "auto"
    if env not in ENGINES:
        raise ConfigError(f"{ENV_VARIABLE}={env!r}: expected one of {', '.join(ENGINES)}")
    return env


def load_compiled(load: Callable[[], T], what: str) -> T | None:
    """``load()``, which imports numba and compiles (or loads from the disk cache) some kernels
    on a tiny input, or None when numba is missing or fails here: then ``what`` runs on NumPy
    (logged once by the caller's cache of the answer)."""
    try:
        loaded = load()
    except ImportError as exc:
        log.info("numba is not available (%s): %s runs on NumPy", exc, what)
        return None
    except Exception as exc:  # noqa: BLE001 - any compiler failure means: use NumPy
        log.warning("compiling %s failed (%s): using NumPy", what, exc)
        return None
    _settle_imports()
    return loaded


_settled: list[bool] = []


def _settle_imports() -> None:
    """Once numba is imported, move every object alive to the garbage collector's permanent
    generation (``gc.freeze``), unless ``STABLECUES_GC_FREEZE=0``.

    numba's import leaves about 86,000 tracked objects (modules, functions, types) that live as
    long as the process. Every full collection walks them all: 15-34 ms on this project's
    machine (5 ms before the import), in whichever thread allocates the object that triggers
    it, often the one adding to a map (an add of 29.7 ms, 17 ms of it CPU, in an instrumented
    10^6-entry build). Frozen objects are still freed by reference counting; only a cycle
    among them that becomes garbage later stays, as it would for a module. ``gc.unfreeze()``
    undoes it.
    """
    if _settled or os.environ.get(FREEZE_VARIABLE, "1").strip() == "0":
        return
    _settled.append(True)
    gc.collect()  # what is garbage now is freed, not frozen
    gc.freeze()
