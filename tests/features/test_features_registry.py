"""The extractor registry: building by name, settings by name, registering a new extractor."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from stablecues.config import merge, to_dict
from stablecues.detection.config import DetectorConfig
from stablecues.errors import ConfigError
from stablecues.features import (
    ExtractorConfig,
    OrbConfig,
    OrbExtractor,
    SiftConfig,
    SiftExtractor,
    extractor_config,
    extractor_config_class,
    extractor_names,
    make_extractor,
    register_extractor,
    registry,
)
from stablecues.types import DescriptorKind, Features


def textured(h: int = 200, w: int = 260, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.full((h, w), 128, np.uint8)
    for _ in range(120):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        cv2.rectangle(img, (x, y), (x + int(rng.integers(4, 30)), y + int(rng.integers(4, 30))),
                      int(rng.integers(0, 256)), -1)
    return img


@dataclass(frozen=True)
class HalfOrbConfig(ExtractorConfig):
    """A made-up extractor: ORB keypoints with the first 16 bytes of each descriptor."""

    name: str = "half-orb"
    n_features: int = 300


class HalfOrbExtractor:
    def __init__(self, config: HalfOrbConfig) -> None:
        self.config = config
        self._orb = OrbExtractor(OrbConfig(n_features=config.n_features))

    @property
    def descriptor_kind(self) -> DescriptorKind:
        return DescriptorKind("binary", 16)

    @property
    def level_scale(self) -> float:
        return self._orb.level_scale

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        f = self._orb.extract(image, mask)
        return dataclasses.replace(f, descriptors=np.ascontiguousarray(f.descriptors[:, :16]))


@pytest.fixture
def own_registry(monkeypatch: pytest.MonkeyPatch) -> None:
    """Registrations in a test stay in that test."""
    monkeypatch.setattr(registry, "_EXTRACTORS", dict(registry._EXTRACTORS))


def test_builtin_names_default_first() -> None:
    assert extractor_names() == ["orb", "sift", "xfeat"]
    assert extractor_config_class("orb") is OrbConfig and extractor_config_class("sift") is SiftConfig


def test_make_extractor_from_settings_name_or_nothing() -> None:
    cfg = OrbConfig(n_features=150)
    ex = make_extractor(cfg)
    assert isinstance(ex, OrbExtractor) and ex.config is cfg
    default = make_extractor()
    assert isinstance(default, OrbExtractor) and default.config == OrbConfig()
    sift = make_extractor("sift")
    assert isinstance(sift, SiftExtractor) and sift.config == SiftConfig()
    assert sift.descriptor_kind == DescriptorKind("float", 128)
    # the registry builds exactly the extractor one would build by hand
    img = textured()
    np.testing.assert_array_equal(ex.extract(img).descriptors, OrbExtractor(cfg).extract(img).descriptors)


def test_extractor_config_applies_overrides_and_rejects_unknown_ones() -> None:
    assert extractor_config("sift", n_features=500) == SiftConfig(n_features=500)
    assert extractor_config() == OrbConfig()
    with pytest.raises(ConfigError, match="'distribute' for SiftConfig; known: .*n_octave_layers"):
        extractor_config("sift", distribute="none")
    with pytest.raises(ConfigError, match="unknown feature extractor 'surf'; known: orb, sift"):
        extractor_config("surf")
    with pytest.raises(ConfigError, match="surf"):
        make_extractor("surf")


def test_make_extractor_rejects_what_is_not_an_extractor_config() -> None:
    with pytest.raises(ConfigError, match="ExtractorConfig"):
        make_extractor(object())  # type: ignore[arg-type]

    @dataclass(frozen=True)
    class Impostor(ExtractorConfig):
        name: str = "orb"

    with pytest.raises(ConfigError, match="takes OrbConfig settings, got Impostor"):
        make_extractor(Impostor())


@pytest.mark.usefixtures("own_registry")
def test_a_registered_extractor_is_chosen_by_name_everywhere() -> None:
    register_extractor("half-orb", HalfOrbConfig, HalfOrbExtractor)
    register_extractor("half-orb", HalfOrbConfig, HalfOrbExtractor)  # the same again is fine
    assert "half-orb" in extractor_names()
    cfg = merge(DetectorConfig(), {"features": {"name": "half-orb", "n_features": 120}})
    assert cfg.features == HalfOrbConfig(n_features=120)
    assert merge(DetectorConfig(), to_dict(cfg)) == cfg
    ex = make_extractor(cfg.features)
    f = ex.extract(textured())
    assert 0 < len(f) <= 120
    assert f.descriptors.shape == (len(f), 16) and f.descriptor_kind == ex.descriptor_kind


@pytest.mark.usefixtures("own_registry")
def test_malformed_registrations_are_refused() -> None:
    with pytest.raises(ConfigError, match="defaults to 'half-orb'"):
        register_extractor("other", HalfOrbConfig, HalfOrbExtractor)
    with pytest.raises(ConfigError, match="already registered"):
        register_extractor("orb", OrbConfig, HalfOrbExtractor)
    with pytest.raises(ConfigError, match="dataclass deriving from ExtractorConfig"):
        register_extractor("plain", dict, HalfOrbExtractor)  # type: ignore[arg-type]

    @dataclass(frozen=True)
    class NeedsWeights(ExtractorConfig):
        name: str = "needs-weights"
        weights: str = dataclasses.field(kw_only=True)

    with pytest.raises(ConfigError, match="needs defaults for weights"):
        register_extractor("needs-weights", NeedsWeights, HalfOrbExtractor)
    assert extractor_names() == ["orb", "sift", "xfeat"]  # nothing of the above was registered
