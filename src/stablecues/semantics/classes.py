"""The CamVid 11-class label set used by the segmentation network.

Ids follow the SegNet release of CamVid: 0 Sky, 1 Building, 2 Pole, 3 Road, 4 Pavement
(sidewalk), 5 Tree, 6 SignSymbol, 7 Fence, 8 Car, 9 Pedestrian, 10 Bicyclist and 11 Unlabelled
(void, ignored by training and by every metric).
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError

CLASS_NAMES: tuple[str, ...] = (
    "Sky",
    "Building",
    "Pole",
    "Road",
    "Pavement",
    "Tree",
    "SignSymbol",
    "Fence",
    "Car",
    "Pedestrian",
    "Bicyclist",
)
NUM_CLASSES = len(CLASS_NAMES)
VOID_ID = 11
VOID_NAME = "Unlabelled"

#: The paper's "meaningful", static classes whose features are kept.
STATIC_CLASSES: frozenset[str] = frozenset({"Building", "Tree", "Fence", "Pole", "SignSymbol", "Pavement"})
#: Classes that move between visits (removed by the ``dynamic`` masking mode).
DYNAMIC_CLASSES: frozenset[str] = frozenset({"Car", "Pedestrian", "Bicyclist"})

#: The usual CamVid colour of each class (RGB), void last.
PALETTE: np.ndarray = np.array(
    [
        (128, 128, 128),
        (128, 0, 0),
        (192, 192, 128),
        (128, 64, 128),
        (60, 40, 222),
        (128, 128, 0),
        (192, 128, 128),
        (64, 64, 128),
        (64, 0, 128),
        (64, 64, 0),
        (0, 128, 192),
        (0, 0, 0),
    ],
    dtype=np.uint8,
)


def class_ids(names: frozenset[str] | set[str] | tuple[str, ...] | list[str]) -> np.ndarray:
    """Sorted (K,) int64 ids of the named classes; an unknown name raises :class:`ConfigError`."""
    ids = []
    for name in names:
        if name not in CLASS_NAMES:
            raise ConfigError(f"unknown CamVid class {name!r}; known: {', '.join(CLASS_NAMES)}")
        ids.append(CLASS_NAMES.index(name))
    return np.array(sorted(ids), dtype=np.int64)


def class_lookup(names: frozenset[str] | set[str] | tuple[str, ...] | list[str]) -> np.ndarray:
    """(12,) bool table, True at the ids of the named classes (void is always False)."""
    table = np.zeros(NUM_CLASSES + 1, dtype=bool)
    table[class_ids(names)] = True
    return table
