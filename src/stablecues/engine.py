"""Which engine the compiled paths use: ``"auto"``, ``"compiled"`` (numba) or ``"numpy"``.

Several stages have a compiled fast path and a NumPy one that gives identical results (the
vocabulary transform and the matcher, :mod:`stablecues.vocabulary.engine`; the class map of a
segmentation; ORB's keypoint spread, :mod:`stablecues.features.orb`). Each takes an engine
name; ``"auto"`` means the compiled path when numba works here, unless the environment variable
``STABLECUES_ENGINE`` names another engine for the whole process. This module holds only that
choice, so that any package can make it without importing another stage.

**Kernels load in the background.** Importing numba and loading its cached machine code takes
about a second in a fresh process, and compiling the kernels the first time on a machine (the
first run after an install) 10-15 s. Under ``"auto"`` the first use of a stage starts that work
in a thread of its own (:class:`Kernels`) and runs the stage on NumPy meanwhile; the stage
switches to the compiled path once the kernels are there. The two paths give the same results,
so a decision never depends on when the switch happens; only the first frames are a little
slower. ``"compiled"`` (asked for by name) waits for them, and ``STABLECUES_COMPILE=wait`` makes
``"auto"`` wait too (the behaviour before, for measurements of the compiled path alone).
"""

from __future__ import annotations

import gc
import logging
import os
import threading
import weakref
from collections.abc import Callable
from typing import Generic, TypeVar

from .errors import ConfigError

__all__ = ["COMPILE_VARIABLE", "ENGINES", "ENV_VARIABLE", "FREEZE_VARIABLE", "Kernels", "check_engine",
           "load_compiled", "requested"]

log = logging.getLogger(__name__)
T = TypeVar("T")

ENGINES = ("auto", "compiled", "numpy")
ENV_VARIABLE = "STABLECUES_ENGINE"
#: set to 0 to leave Python's garbage collector as it is when the compiled kernels load
FREEZE_VARIABLE = "STABLECUES_GC_FREEZE"
#: set to ``wait`` to load the compiled kernels where they are first needed, not in the background
COMPILE_VARIABLE = "STABLECUES_COMPILE"


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
    # no collection while they load (in the background, beside the first adds of a fresh
    # process): the objects numba's import makes would be walked by every full collection until
    # they are frozen, 39-74 ms each in whichever thread triggered it (a 10^6-entry build: an
    # add of 84 ms among its first hundred)
    pause = _freezing() and gc.isenabled()
    if pause:
        gc.disable()
    try:
        loaded = load()
    except ImportError as exc:
        log.info("numba is not available (%s): %s runs on NumPy", exc, what)
        return None
    except Exception as exc:  # noqa: BLE001 - any compiler failure means: use NumPy
        log.warning("compiling %s failed (%s): using NumPy", what, exc)
        return None
    finally:
        if pause:
            gc.enable()
    _settle_imports()
    return loaded


class Kernels(Generic[T]):
    """Compiled kernels, loaded once per process by ``load`` (see :func:`load_compiled`).

    :meth:`get` with ``wait=False`` starts the load in a daemon thread the first time and
    answers None until it is done (the caller runs NumPy meanwhile); ``wait=True`` loads them
    here, or waits for the thread. The answer is None for good when numba is missing or fails.
    """

    def __init__(self, load: Callable[[], T], what: str) -> None:
        self._load, self.what = load, what
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        self._value: T | None = None
        _ALL_KERNELS.add(self)  # type: ignore[arg-type]

    def get(self, wait: bool = True) -> T | None:
        """The kernels, or None (not loaded yet with ``wait=False``, or unavailable here). The
        load always runs in its own thread, so that a caller that does not wait never blocks
        behind one that does."""
        if self._done.is_set():
            return self._value
        if not wait and os.environ.get(COMPILE_VARIABLE, "").strip().lower() == "wait":
            wait = True
        with self._lock:
            if self._thread is None and not self._done.is_set():
                self._thread = threading.Thread(target=self._run, name=f"stablecues: load {self.what}",
                                                daemon=True)
                self._thread.start()
        if wait:
            self._done.wait()
        return self._value if self._done.is_set() else None

    def _after_fork(self) -> None:
        """In a child forked while the load ran: the thread did not come along; start over."""
        if not self._done.is_set():
            self._lock = threading.Lock()
            self._thread = None

    def loaded(self) -> T | None:
        """The kernels if they are loaded already, else None (never starts a load)."""
        return self._value if self._done.is_set() else None

    def failed(self) -> bool:
        """Whether loading finished without kernels (numba missing or failing here)."""
        return self._done.is_set() and self._value is None

    def _run(self) -> None:
        try:
            self._value = load_compiled(self._load, self.what)
        finally:
            self._done.set()


_ALL_KERNELS: weakref.WeakSet[Kernels[object]] = weakref.WeakSet()


def _reset_after_fork() -> None:
    for kernels in list(_ALL_KERNELS):
        kernels._after_fork()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_reset_after_fork)


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
    if _settled or not _freezing():
        return
    _settled.append(True)
    # frozen without a collection first: one would walk every object numba made (69 ms holding
    # the interpreter, an add waiting on it) and found no garbage (0 of 166,096 objects here);
    # whatever garbage there is in cycles at this moment stays, once
    gc.freeze()


def _freezing() -> bool:
    return os.environ.get(FREEZE_VARIABLE, "1").strip() != "0"
