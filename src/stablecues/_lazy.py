"""Package namespaces whose names are imported on first use (PEP 562).

A package ``__init__`` lists its public names by the module that defines them and keeps the
same imports under ``TYPE_CHECKING`` for the type checker::

    if TYPE_CHECKING:
        from .config import preset
    __getattr__, __dir__ = lazy_names(__name__, {"config": ("preset",)})

so that importing one module of the package (``stablecues.detection.config`` for the presets a
``--help`` lists) does not import all of them (the detector, SciPy, numba). Code inside the
``__init__`` itself must import what it uses from the modules directly: a module's own global
lookups do not go through its ``__getattr__``. ``tests/test_layout.py`` resolves every name of
every package's ``__all__``.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping, Sequence


def lazy_names(
    package: str, modules: Mapping[str, Sequence[str]], fallback: Callable[[str], object] | None = None
) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for a package whose names live in its modules.

    Args:
        package: the package's ``__name__``.
        modules: module (relative to the package, without the dot) -> the names it gives.
        fallback: called for a name no module gives (for example names that moved away);
            None: AttributeError.
    """
    where = {name: module for module, names in modules.items() for name in names}

    def __getattr__(name: str) -> object:
        module = where.get(name)
        if module is None:
            if fallback is not None:
                return fallback(name)
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f".{module}", package), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(where))

    return __getattr__, __dir__
