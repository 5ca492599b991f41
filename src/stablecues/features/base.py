"""The protocol every feature extractor follows."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from ..types import Features


class Extractor(Protocol):
    """Turns an image into binary local features.

    ``extract`` takes a uint8 image, grey (H, W) or colour (H, W, 3) BGR, of any size, and an
    optional (H, W) uint8 mask (nonzero = allowed); it returns :class:`Features`, possibly empty.
    """

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features: ...
