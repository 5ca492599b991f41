"""Settings: merging overrides, choosing a settings class by name, and the to_dict round trip."""

from __future__ import annotations

import enum
import json
from dataclasses import dataclass, field

import pytest

from stablecues.config import merge, select_by, to_dict
from stablecues.detection.config import DetectorConfig, preset, preset_names
from stablecues.errors import ConfigError
from stablecues.features import OrbConfig, SiftConfig
from stablecues.semantics.masking import MaskingConfig


class Colour(enum.Enum):
    RED = "red"
    BLUE = "blue"


@dataclass(frozen=True)
class Circle:
    kind: str = "circle"
    radius: float = 1.0


@dataclass(frozen=True)
class Square:
    kind: str = "square"
    side: float = 2.0
    corners: tuple[int, ...] = (0, 1, 2, 3)


def shape_class(name: str) -> type:
    shapes: dict[str, type] = {"circle": Circle, "square": Square}
    if name not in shapes:
        raise ConfigError(f"unknown shape {name!r}; known: circle, square")
    return shapes[name]


@dataclass(frozen=True)
class Drawing:
    shape: Circle | Square = field(default_factory=Circle, metadata=select_by("kind", shape_class))
    colour: Colour = Colour.RED
    tags: frozenset[str] = frozenset({"b", "a"})
    outline: Circle | None = None
    width: int = 1


def test_merge_overrides_nested_settings_and_rejects_unknown_keys() -> None:
    d = Drawing()
    assert merge(d, None) is d and merge(d, {}) is d
    assert merge(d, {"width": 3, "shape": {"radius": 5.0}}) == Drawing(shape=Circle(radius=5.0), width=3)
    with pytest.raises(ConfigError, match="unknown setting 'widht' for Drawing; known: colour, outline"):
        merge(d, {"widht": 3})
    with pytest.raises(ConfigError, match="unknown setting 'side' for Circle; known: kind, radius"):
        merge(d, {"shape": {"side": 3.0}})
    with pytest.raises(TypeError):
        merge({"width": 1}, {"width": 2})


def test_a_tagged_field_switches_class_by_name() -> None:
    d = merge(Drawing(), {"shape": {"kind": "square", "side": 7.0}})
    assert d.shape == Square(side=7.0)
    # the same name keeps the current settings; another name starts from that class's defaults
    same = merge(d, {"shape": {"kind": "square", "corners": [3, 2]}})
    assert same.shape == Square(side=7.0, corners=(3, 2))
    assert merge(d, {"shape": {"kind": "circle"}}).shape == Circle()
    with pytest.raises(ConfigError, match="unknown shape 'hexagon'"):
        merge(d, {"shape": {"kind": "hexagon"}})
    with pytest.raises(ConfigError, match="unknown setting 'radius' for Square"):
        merge(Drawing(), {"shape": {"kind": "square", "radius": 1.0}})


def test_json_values_come_back_in_the_field_s_form() -> None:
    d = merge(Drawing(), {"colour": "blue", "tags": ["x", "y"], "outline": {"radius": 0.5}})
    assert d.colour is Colour.BLUE and d.tags == frozenset({"x", "y"}) and d.outline == Circle(radius=0.5)
    with pytest.raises(ConfigError, match="'green': expected one of 'red', 'blue'"):
        merge(Drawing(), {"colour": "green"})
    # to_dict writes plain JSON (sets sorted, so the file is the same on every run) and reads back
    doc = to_dict(d)
    assert doc["tags"] == ["x", "y"] and doc["colour"] == "blue"
    assert doc["shape"] == {"kind": "circle", "radius": 1.0}
    assert merge(Drawing(), json.loads(json.dumps(doc))) == d


def test_detector_features_switch_to_sift_by_name() -> None:
    cfg = merge(DetectorConfig(), {"features": {"name": "sift", "n_features": 500}})
    assert cfg.features == SiftConfig(n_features=500)
    assert cfg.query == DetectorConfig().query  # the rest is untouched
    back = merge(cfg, {"features": {"name": "orb"}})
    assert back.features == OrbConfig()
    tuned = preset("default", {"features": {"n_features": 400}})
    kept = merge(tuned, {"features": {"name": "orb", "n_levels": 4}})
    assert kept.features == OrbConfig(n_features=400, n_levels=4)
    with pytest.raises(ConfigError, match="'distribute' for SiftConfig; known: contrast_threshold"):
        merge(DetectorConfig(), {"features": {"name": "sift", "distribute": "none"}})
    with pytest.raises(ConfigError, match="unknown feature extractor .surf.; known: orb, sift, xfeat"):
        preset("default", {"features": {"name": "surf"}})


@pytest.mark.parametrize("name", preset_names())
def test_every_preset_round_trips_through_its_json(name: str) -> None:
    for overrides in (None, {"features": {"name": "sift", "sigma": 1.2}}):
        if overrides and name == "learned-glue":  # LighterGlue matches XFeat features only
            with pytest.raises(ConfigError, match="lighterglue"):
                preset(name, overrides)
            continue
        cfg = preset(name, overrides)
        doc = json.loads(json.dumps(to_dict(cfg)))
        assert doc["features"]["name"] == cfg.features.name
        assert merge(DetectorConfig(), doc) == cfg


def test_a_none_section_takes_overrides_of_its_defaults() -> None:
    cfg = preset("bow")
    assert cfg.masking is None
    masked = merge(cfg, {"masking": {"mode": "hard", "static_classes": ["Building", "Road"]}})
    assert masked.masking == MaskingConfig(mode="hard", static_classes=frozenset({"Building", "Road"}))
    assert merge(masked, {"masking": None}).masking is None


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"query": {"exclude_recent": "5"}}, r"query\.exclude_recent: expected a whole number \(int\)"),
        ({"query": {"alpha": "abc"}}, r"query\.alpha: expected a number \(float\), got 'abc'"),
        ({"query": {"exclude_recent": 5.5}}, r"query\.exclude_recent: expected a whole number"),
        ({"query": {"use_nss": 1}}, r"query\.use_nss: expected true or false \(bool\), got 1"),
        ({"semantic_source": "camera"}, r"semantic_source: expected one of 'network', 'labels'"),
        ({"query": 5}, r"query: expected QueryConfig, got 5"),
        ({"features": {"n_features": "many"}}, r"features\.n_features: expected a whole number"),
    ],
)
def test_values_are_checked_against_the_field_types(overrides: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        preset("default", overrides)


def test_ints_for_floats_and_none_for_optionals_are_kept() -> None:
    cfg = preset("default", {"query": {"alpha": 1, "exclude_recent_s": None}})
    assert cfg.query.alpha == 1 and type(cfg.query.alpha) is int and cfg.query.exclude_recent_s is None
    cfg = preset("default", {"query": {"exclude_recent_s": 2.5}})
    assert cfg.query.exclude_recent_s == 2.5
