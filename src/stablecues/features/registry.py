"""Feature extractors by name: ``features.name`` in a configuration picks one.

Each entry pairs a settings class (a frozen dataclass deriving from
:class:`~stablecues.features.base.ExtractorConfig`, whose ``name`` defaults to the entry's
name) with the extractor class built from it::

    make_extractor(OrbConfig(n_features=500))          # an OrbExtractor
    make_extractor(extractor_config("sift", n_features=500))
    register_extractor("mine", MyConfig, MyExtractor)  # then features.name = "mine" works

Every stage that extracts features (the loop detector, pair verification, vocabulary training,
segmentation pictures) builds its extractor with :func:`make_extractor`.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, cast

from ..config import merge
from ..errors import ConfigError

if TYPE_CHECKING:
    from .base import Extractor, ExtractorConfig

__all__ = [
    "DEFAULT_EXTRACTOR",
    "extractor_config",
    "extractor_config_class",
    "extractor_names",
    "make_extractor",
    "register_extractor",
]

#: the extractor used when none is named
DEFAULT_EXTRACTOR = "orb"

ExtractorFactory = Callable[[Any], "Extractor"]

#: the built-in extractors: name -> (module of this package, settings class, extractor class),
#: imported when first used (listing the names for a ``--help`` imports none of them)
_BUILTIN: dict[str, tuple[str, str, str]] = {
    "orb": ("orb", "OrbConfig", "OrbExtractor"),
    "sift": ("sift", "SiftConfig", "SiftExtractor"),
    "xfeat": ("xfeat", "XFeatConfig", "XFeatExtractor"),
}
_EXTRACTORS: dict[str, tuple[type[ExtractorConfig], ExtractorFactory]] = {}


def _entry(name: str) -> tuple[type[ExtractorConfig], ExtractorFactory] | None:
    """The registered classes of ``name`` (a built-in one imported now), or None."""
    entry = _EXTRACTORS.get(name)
    if entry is None and name in _BUILTIN:
        module, config_cls, extractor_cls = _BUILTIN[name]
        mod = importlib.import_module(f".{module}", __package__)
        entry = _EXTRACTORS[name] = (getattr(mod, config_cls), getattr(mod, extractor_cls))
    return entry


def register_extractor(name: str, config_cls: type[ExtractorConfig], extractor_cls: ExtractorFactory) -> None:
    """Make an extractor available as ``features.name = name``.

    Args:
        name: the registry name.
        config_cls: its settings, a frozen dataclass deriving from ``ExtractorConfig`` whose
            ``name`` field defaults to ``name`` and whose other fields all have defaults.
        extractor_cls: called with a ``config_cls`` instance, returns an :class:`Extractor`.

    Raises:
        ConfigError: a malformed settings class, or ``name`` already taken by other classes.
    """
    from .base import ExtractorConfig

    if not (isinstance(config_cls, type) and issubclass(config_cls, ExtractorConfig)
            and dataclasses.is_dataclass(config_cls)):
        raise ConfigError(f"extractor {name!r}: settings must be a dataclass deriving from ExtractorConfig")
    default = config_cls.__dataclass_fields__["name"].default
    if default != name:
        raise ConfigError(f"extractor {name!r}: {config_cls.__name__}.name defaults to {default!r}")
    required = [f.name for f in dataclasses.fields(config_cls)
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    if required:
        raise ConfigError(
            f"extractor {name!r}: {config_cls.__name__} needs defaults for {', '.join(required)}"
        )
    known = _entry(name)
    if known is not None and known != (config_cls, extractor_cls):
        raise ConfigError(f"extractor {name!r} is already registered ({known[0].__name__})")
    _EXTRACTORS[name] = (config_cls, extractor_cls)


def extractor_names() -> list[str]:
    """The registered names, default first."""
    return sorted(set(_EXTRACTORS) | set(_BUILTIN), key=lambda n: (n != DEFAULT_EXTRACTOR, n))


def extractor_config_class(name: str) -> type[ExtractorConfig]:
    """The settings class registered under ``name``.

    Raises:
        ConfigError: an unknown name (the message lists the known ones).
    """
    entry = _entry(name)
    if entry is None:
        raise ConfigError(f"unknown feature extractor {name!r}; known: {', '.join(extractor_names())}")
    return entry[0]


def extractor_config(name: str = DEFAULT_EXTRACTOR, **overrides: Any) -> ExtractorConfig:
    """The settings of extractor ``name``: its defaults with ``overrides`` applied.

    Raises:
        ConfigError: an unknown name, or an override the extractor does not have.
    """
    # every registered class has a default for each field (register_extractor checks it)
    defaults = cast("Callable[[], ExtractorConfig]", extractor_config_class(name))
    return merge(defaults(), overrides)


def make_extractor(config: ExtractorConfig | str | None = None) -> Extractor:
    """Build the extractor that ``config`` describes.

    Args:
        config: an extractor's settings (``DetectorConfig.features``), a registered name (with
            that extractor's default settings), or None for the default extractor (ORB).

    Raises:
        ConfigError: an unknown name, or settings of another class than the name's.
    """
    if config is None or isinstance(config, str):
        config = extractor_config(DEFAULT_EXTRACTOR if config is None else config)
    name = getattr(config, "name", None)
    if not isinstance(name, str):
        raise ConfigError(f"extractor settings: expected an ExtractorConfig, got {type(config).__name__}")
    config_cls = extractor_config_class(name)
    if not isinstance(config, config_cls):
        raise ConfigError(
            f"extractor {name!r} takes {config_cls.__name__} settings, got {type(config).__name__}"
        )
    return _EXTRACTORS[name][1](config)  # registered: extractor_config_class looked it up
