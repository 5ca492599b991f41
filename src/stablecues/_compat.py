"""Old import paths kept for one release (0.2.x) after the layout of issue 10.

Each old module file is a two-line shim calling :func:`moved`, which makes the old name an
alias of the new module in ``sys.modules`` (so ``from old.path import X`` and
``import old.path`` both give the new objects, private names included) and warns once.
:data:`MOVED` lists every alias; ``tests/test_layout.py`` imports each through both paths.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import warnings
from collections.abc import Sequence
from importlib.machinery import ModuleSpec
from types import ModuleType

MOVED: dict[str, str] = {
    "stablecues.evaluation.groundtruth": "stablecues.groundtruth",
    "stablecues.evaluation.runs": "stablecues.runs.store",
    "stablecues.evaluation.timing": "stablecues.runs.timing",
    "stablecues.verification.images": "stablecues.detection.pair",
    "stablecues.datasets.synthetic": "stablecues.synthetic",
    "stablecues.datasets.synthetic.config": "stablecues.synthetic.config",
    "stablecues.datasets.synthetic.render": "stablecues.synthetic.render",
    "stablecues.datasets.synthetic.route": "stablecues.synthetic.route",
    "stablecues.datasets.synthetic.scene": "stablecues.synthetic.scene",
    "stablecues.datasets.synthetic.sequence": "stablecues.synthetic.sequence",
    "stablecues.datasets.synthetic.textures": "stablecues.synthetic.textures",
    "stablecues.datasets.synthetic.truth": "stablecues.synthetic.truth",
    "stablecues.datasets.synthetic.town": "stablecues.synthetic.town",
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


_OLD_PACKAGES: dict[str, list[str]] = {}
"""old package name -> the folder of its shims (its name now points at the new package)."""


class _OldPackageFinder(importlib.abc.MetaPathFinder):
    """Sends ``import old.sub`` of a moved package to the old folder's ``sub.py`` shim.

    Without it, once ``old`` names the new package, ``old.sub`` would be searched in the new
    package's folder and its module loaded a second time under the old name.
    """

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> ModuleSpec | None:
        folder = _OLD_PACKAGES.get(fullname.rpartition(".")[0])
        return None if folder is None else importlib.machinery.PathFinder.find_spec(fullname, folder)


_FINDER = _OldPackageFinder()


def moved(old: str) -> None:
    """Replace the module ``old`` (being imported) by its new home, with a DeprecationWarning."""
    new = MOVED[old]
    warnings.warn(f"{old} moved to {new}; the old path goes in 0.3", DeprecationWarning, stacklevel=3)
    shim_path = getattr(sys.modules.get(old), "__path__", None)
    if shim_path is not None:  # a package: keep its submodules' shims reachable
        _OLD_PACKAGES[old] = list(shim_path)
        if _FINDER not in sys.meta_path:
            sys.meta_path.insert(0, _FINDER)
    sys.modules[old] = importlib.import_module(new)
