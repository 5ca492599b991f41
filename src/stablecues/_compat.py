"""Old import paths kept for one release (0.2.x) after the layout of issue 10.

Each old module file is a two-line shim calling :func:`moved`, which makes the old name an
alias of the new module in ``sys.modules`` (so ``from old.path import X`` and
``import old.path`` both give the new objects, private names included) and warns once.
:data:`MOVED` lists every alias; ``tests/test_layout.py`` imports each through both paths.
"""

from __future__ import annotations

import importlib
import sys
import warnings

MOVED: dict[str, str] = {
    "stablecues.evaluation.groundtruth": "stablecues.groundtruth",
    "stablecues.evaluation.runs": "stablecues.runs.store",
    "stablecues.evaluation.timing": "stablecues.runs.timing",
    "stablecues.verification.images": "stablecues.detection.pair",
}
"""old module name -> new module name."""


DEPRECATED_NAMES: dict[str, dict[str, str]] = {
    "stablecues.verification": {
        "Frame": "stablecues.detection.pair:PairFrame",
        "ImagePairVerifier": "stablecues.detection.pair:ImagePairVerifier",
        "PairVerification": "stablecues.detection.pair:PairVerification",
    },
}
"""package -> {old name: "new.module:name"}: names a package exported that now live above it."""


def moved_name(package: str, name: str) -> object:
    """A package's ``__getattr__`` for :data:`DEPRECATED_NAMES` (PEP 562), with a warning."""
    target = DEPRECATED_NAMES.get(package, {}).get(name)
    if target is None:
        raise AttributeError(f"module {package!r} has no attribute {name!r}")
    module, attr = target.split(":")
    warnings.warn(f"{package}.{name} moved to {module}.{attr}; the old name goes in 0.3",
                  DeprecationWarning, stacklevel=3)
    return getattr(importlib.import_module(module), attr)


def moved(old: str) -> None:
    """Replace the module ``old`` (being imported) by its new home, with a DeprecationWarning."""
    new = MOVED[old]
    warnings.warn(f"{old} moved to {new}; the old path goes in 0.3", DeprecationWarning, stacklevel=3)
    sys.modules[old] = importlib.import_module(new)
