"""What every feature extractor is: a settings class chosen by name and one protocol."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..errors import ConfigError, InputError
from ..types import DescriptorKind, Features


@dataclass(frozen=True)
class ExtractorConfig:
    """Base of every extractor's settings.

    Each extractor's settings are a frozen dataclass deriving from this one; its first field,
    ``name``, defaults to the name the extractor is registered under ("orb", "sift"), and
    ``features.name`` in a detector configuration picks the extractor (see
    :mod:`stablecues.features.registry`).
    """

    name: str

    def __post_init__(self) -> None:
        expected = type(self).__dataclass_fields__["name"].default
        if expected is not dataclasses.MISSING and self.name != expected:
            raise ConfigError(
                f"{type(self).__name__}: name must be {expected!r}, got {self.name!r} "
                "(choose another extractor through its own settings class)"
            )


class Extractor(Protocol):
    """Turns an image into local features.

    ``extract`` takes a uint8 image, grey (H, W) or colour (H, W, 3) BGR, of any size, and an
    optional (H, W) uint8 mask (nonzero = allowed); it returns :class:`Features`, possibly empty,
    whose descriptors are of :attr:`descriptor_kind`.
    """

    @property
    def descriptor_kind(self) -> DescriptorKind:
        """Binary (byte width) or float (dimension): what every descriptor of ``extract`` is."""
        ...

    @property
    def level_scale(self) -> float:
        """Scale between consecutive levels of ``Features.octaves`` (a keypoint of level ``o``
        was found on the image shrunk by ``level_scale ** o``)."""
        ...

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features: ...


def check_mask(mask: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray | None:
    """A detection mask as OpenCV wants it: (H, W) uint8 of 0 and 1, or None.

    Raises:
        InputError: the mask is not an array of the image's ``shape``.
    """
    if mask is None:
        return None
    if not isinstance(mask, np.ndarray) or mask.shape != shape:
        got = getattr(mask, "shape", type(mask).__name__)
        raise InputError(f"mask: expected shape {shape}, got {got}")
    return (mask != 0).astype(np.uint8)
