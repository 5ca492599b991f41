"""Settings as frozen dataclasses: merging overrides that reject unknown keys, and presets.

A field may hold one of several settings classes chosen by a tag inside its value (the feature
extractor's settings are chosen by ``name``). Tag such a field with :func:`select_by`; then
``merge(config, {"features": {"name": "sift", "n_features": 500}})`` switches the field to the
settings class registered for "sift", its defaults first, then the other overrides.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import types
import typing
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

from .errors import ConfigError

T = TypeVar("T")

_SELECT = "stablecues.select_by"


def select_by(key: str, resolve: Callable[[str], Callable[[], object]]) -> dict[str, object]:
    """Field metadata for a settings field whose class is chosen by ``key`` in its value.

    Use as ``field(default_factory=OrbConfig, metadata=select_by("name", extractor_config_class))``.

    Args:
        key: the field of the settings classes that names them ("name").
        resolve: ``value of key -> settings class`` (raising ConfigError for unknown values);
            the class is called without arguments for its defaults.
    """
    return {_SELECT: (key, resolve)}


def merge(config: T, overrides: Mapping[str, Any] | None = None) -> T:
    """Return a copy of a frozen dataclass ``config`` with ``overrides`` applied.

    Nested dataclass fields accept a mapping of their own overrides; a nested field that is
    None takes a mapping as overrides of its settings class's defaults, and a field tagged with
    :func:`select_by` switches class when the mapping names another one. Lists are turned back
    into the tuple or frozenset a field holds, and plain values into its enum, so that
    ``merge(type(c)(), to_dict(c)) == c``. Unknown keys raise :class:`ConfigError` naming the
    key and the known ones, so typos never pass silently; so does a value that is not of the
    field's declared type (``"5"`` for an ``int``, ``"abc"`` for a ``float``; an ``int`` is
    accepted for a ``float``).
    """
    return _merge(config, overrides, "")


def _merge(config: T, overrides: Mapping[str, Any] | None, where: str) -> T:
    if not overrides:
        return config
    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        raise TypeError("merge() expects a dataclass instance")
    if not isinstance(overrides, Mapping):
        name = where or type(config).__name__
        raise ConfigError(f"{name}: expected a mapping of settings, got {overrides!r:.30}")
    fields = {f.name: f for f in dataclasses.fields(config)}
    changes: dict[str, Any] = {}
    for key, value in overrides.items():
        if key not in fields:
            known = ", ".join(sorted(fields))
            raise ConfigError(f"unknown setting {key!r} for {type(config).__name__}; known: {known}")
        changes[key] = _merged_value(config, fields[key], value, f"{where}{key}")
    return dataclasses.replace(config, **changes)  # type: ignore[type-var,unused-ignore]


def _merged_value(config: object, f: dataclasses.Field, value: Any, where: str) -> Any:
    """The new value of field ``f`` of ``config`` given an override ``value``."""
    current = getattr(config, f.name)
    if not isinstance(value, Mapping):
        out = _coerce(current, value, where)
        _check_type(type(config), f.name, out, where)
        return out
    select = f.metadata.get(_SELECT)
    if select is not None:
        key, resolve = select
        if key in value and not isinstance(value[key], str):
            raise ConfigError(f"{where}.{key}: expected a name (text), got {value[key]!r:.40}")
        if key in value and (current is None or getattr(current, key, None) != value[key]):
            return _merge(resolve(value[key])(), value, where + ".")
    if dataclasses.is_dataclass(current) and not isinstance(current, type):
        return _merge(current, value, where + ".")
    if current is None:
        cls = _optional_dataclass(type(config), f.name)
        if cls is not None:
            return _merge(cls(), value, where + ".")
    _check_type(type(config), f.name, value, where)
    return value


def _coerce(current: Any, value: Any, where: str = "") -> Any:
    """``value`` in the form of the field's ``current`` value: a JSON list back into a tuple or
    frozenset, a plain value into the enum."""
    if isinstance(current, tuple | frozenset | set) and isinstance(value, list | tuple | set | frozenset):
        return type(current)(value)
    if isinstance(current, enum.Enum) and not isinstance(value, enum.Enum):
        try:
            return type(current)(value)
        except (ValueError, TypeError):
            known = ", ".join(repr(m.value) for m in type(current))
            raise ConfigError(f"{where + ': ' if where else ''}{value!r}: expected one of {known}") from None
    return value


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except (NameError, TypeError):  # unresolvable annotations: values are not checked
        return {}


def _check_type(cls: type, name: str, value: Any, where: str) -> None:
    """Raise unless ``value`` fits the annotation of field ``name`` of dataclass ``cls``.

    Raises:
        ConfigError: naming the setting, the expected type and the value found.
    """
    hint = _hints(cls).get(name)
    if hint is None or _fits(value, hint):
        return
    raise ConfigError(f"{where}: expected {_type_name(hint)}, got {value!r:.60} ({type(value).__name__})")


def _fits(value: Any, hint: Any) -> bool:  # noqa: PLR0911 - one return per kind of annotation
    """Whether ``value`` is of type ``hint`` (int, float, bool, str, Path, unions, Literal,
    enums, dataclasses, tuple / frozenset / list / dict of those; anything else passes)."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if hint is Any or isinstance(hint, typing.TypeVar):
        return True
    if origin is typing.Union or isinstance(hint, types.UnionType):
        return any(_fits(value, a) for a in args)
    if origin is typing.Literal:
        return any(value == a and type(value) is type(a) for a in args)
    if hint is type(None):
        return value is None
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if origin in (tuple, frozenset, set, list):
        if not isinstance(value, origin):
            return False
        inner = [a for a in args if a is not Ellipsis]
        return len(inner) != 1 or all(_fits(v, inner[0]) for v in value)
    if origin is dict:
        return isinstance(value, dict)
    if isinstance(hint, type):
        return isinstance(value, hint)
    return True


def _type_name(hint: Any) -> str:
    names = {int: "a whole number (int)", float: "a number (float)", bool: "true or false (bool)",
             str: "text (str)", type(None): "null"}  # fmt: skip
    if hint in names:
        return names[hint]
    if typing.get_origin(hint) is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(hint))
    if typing.get_origin(hint) is typing.Union or isinstance(hint, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(hint))
    return getattr(hint, "__name__", str(hint))


def _optional_dataclass(cls: type, name: str) -> type | None:
    """The settings class of an ``X | None`` field ``name`` of dataclass ``cls``, if exactly one."""
    try:
        hint = typing.get_type_hints(cls)[name]
    except (NameError, TypeError):  # unresolvable annotations: leave the value as it is
        return None
    options = [a for a in typing.get_args(hint) if dataclasses.is_dataclass(a) and isinstance(a, type)]
    return options[0] if len(options) == 1 else None


def to_dict(config: object) -> dict[str, Any]:
    """Plain-dict view of a (possibly nested) settings dataclass, for JSON files.

    ``merge(type(config)(), to_dict(config))`` gives ``config`` back.
    """
    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        raise TypeError("to_dict() expects a dataclass instance")
    out: dict[str, Any] = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            value = to_dict(value)
        elif isinstance(value, frozenset | set):
            value = sorted(value, key=str)  # a set's own order changes from run to run
        elif isinstance(value, tuple):
            value = list(value)
        elif hasattr(value, "value") and hasattr(type(value), "__members__"):
            value = value.value
        out[f.name] = value
    return out
