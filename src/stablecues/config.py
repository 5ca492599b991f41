"""Settings as frozen dataclasses: merging overrides that reject unknown keys, and presets."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, TypeVar

from .errors import ConfigError

T = TypeVar("T")


def merge(config: T, overrides: Mapping[str, Any] | None = None) -> T:
    """Return a copy of a frozen dataclass ``config`` with ``overrides`` applied.

    Nested dataclass fields accept a mapping of their own overrides. Unknown keys raise
    :class:`ConfigError` naming the key and the known ones, so typos never pass silently.
    """
    if not overrides:
        return config
    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        raise TypeError("merge() expects a dataclass instance")
    fields = {f.name: f for f in dataclasses.fields(config)}
    changes: dict[str, Any] = {}
    for key, value in overrides.items():
        if key not in fields:
            known = ", ".join(sorted(fields))
            raise ConfigError(f"unknown setting {key!r} for {type(config).__name__}; known: {known}")
        current = getattr(config, key)
        if dataclasses.is_dataclass(current) and isinstance(value, Mapping):
            value = merge(current, value)
        changes[key] = value
    return dataclasses.replace(config, **changes)  # type: ignore[type-var,unused-ignore]


def to_dict(config: object) -> dict[str, Any]:
    """Plain-dict view of a (possibly nested) settings dataclass, for JSON files."""
    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        raise TypeError("to_dict() expects a dataclass instance")
    out: dict[str, Any] = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            value = to_dict(value)
        elif isinstance(value, tuple | frozenset | set):
            value = list(value)
        elif hasattr(value, "value") and hasattr(type(value), "__members__"):
            value = value.value
        out[f.name] = value
    return out
