"""ORB features through OpenCV, optionally spread over the image as ORB-SLAM does.

OpenCV's ORB keeps the strongest corners of each pyramid level, which clusters them on the
most textured objects. ORB-SLAM instead distributes each level's quota with a quadtree so that
every region of the image contributes; for place recognition and geometric verification that
spread matters more than raw corner strength. ``distribute="quadtree"`` reproduces it:

1. detect with OpenCV's ORB, asking for ``oversample`` times the wanted number, first with the
   FAST threshold ``ini_fast`` and, when that yields too few, again with ``min_fast``
   (ORB-SLAM's two thresholds);
2. split the per-level quota geometrically over the levels (ORB-SLAM's allocation);
3. per level, a breadth-first quadtree: cells are split until there are at least as many
   non-empty cells as the level's quota; each cell keeps its strongest corner, and when there
   are more cells than the quota the strongest cells win;
4. compute descriptors for the kept keypoints.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from operator import attrgetter
from typing import Any, Literal

import cv2
import numpy as np

from .._arrays import distinct
from ..engine import Kernels, requested
from ..errors import ConfigError
from ..imageio import to_grey
from ..types import ORB_DESCRIPTOR, DescriptorKind, Features
from .base import ExtractorConfig, check_mask

log = logging.getLogger(__name__)

#: KeyPoint fields read in C by map(), faster than a comprehension's attribute lookups
_OCTAVE, _ANGLE, _RESPONSE, _SIZE = (attrgetter(a) for a in ("octave", "angle", "response", "size"))


@dataclass(frozen=True)
class OrbConfig(ExtractorConfig):
    """ORB settings.

    Attributes:
        name: "orb", the registry name (see :mod:`stablecues.features.registry`).
        n_features: how many features to keep at most.
        scale_factor: pyramid scale between levels (> 1).
        n_levels: pyramid levels.
        ini_fast: FAST threshold tried first.
        min_fast: lower FAST threshold used when the first gives too few corners.
        distribute: "quadtree" spreads keypoints over each level (ORB-SLAM); "none" keeps
            OpenCV's strongest corners.
        oversample: with "quadtree", how many candidates to detect per wanted feature.
        edge_threshold: border in pixels where no features are detected (>= patch_size).
        patch_size: ORB patch size.
        clahe: illumination normalisation before detection: OpenCV's CLAHE (contrast-limited
            adaptive histogram equalisation, 8 x 8 tiles) with this clip limit; 0: off (every
            preset; measured on the day/night pairings in docs/learned.md).
    """

    name: str = "orb"
    n_features: int = 1000
    scale_factor: float = 1.2
    n_levels: int = 8
    ini_fast: int = 20
    min_fast: int = 7
    distribute: Literal["quadtree", "none"] = "quadtree"
    oversample: float = 2.5
    edge_threshold: int = 19
    patch_size: int = 31
    clahe: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.n_features < 0:
            raise ConfigError(f"n_features must be >= 0, got {self.n_features}")
        if self.scale_factor <= 1.0:
            raise ConfigError(f"scale_factor must be > 1, got {self.scale_factor}")
        if self.n_levels < 1:
            raise ConfigError(f"n_levels must be >= 1, got {self.n_levels}")
        if not 0 < self.min_fast <= self.ini_fast:
            raise ConfigError(f"need 0 < min_fast <= ini_fast, got {self.min_fast}, {self.ini_fast}")
        if self.distribute not in ("quadtree", "none"):
            raise ConfigError(f"distribute must be 'quadtree' or 'none', got {self.distribute!r}")
        if self.oversample < 1.0:
            raise ConfigError(f"oversample must be >= 1, got {self.oversample}")
        if not 0.0 <= self.clahe < 1e3:
            raise ConfigError(f"clahe (CLAHE's clip limit) must be 0 (off) or positive, got {self.clahe}")


def level_quotas(n_features: int, scale_factor: float, n_levels: int) -> np.ndarray:
    """ORB-SLAM's geometric split of ``n_features`` over pyramid levels: (n_levels,) int."""
    f = 1.0 / scale_factor
    quotas = np.zeros(n_levels, np.int64)
    if n_levels == 1:
        quotas[0] = n_features
        return quotas
    per = n_features * (1 - f) / (1 - f**n_levels)
    total = 0
    for level in range(n_levels - 1):
        quotas[level] = round(per)
        total += quotas[level]
        per *= f
    quotas[-1] = max(n_features - total, 0)
    # rounding up the first levels can overshoot a tiny total: take the excess back from the top
    excess = int(quotas.sum()) - n_features
    for level in range(n_levels - 1, -1, -1):
        if excess <= 0:
            break
        cut = min(excess, int(quotas[level]))
        quotas[level] -= cut
        excess -= cut
    return quotas


def distribute_quadtree(
    points: np.ndarray, responses: np.ndarray, quota: int, extent: tuple[float, float]
) -> np.ndarray:
    """Pick up to ``quota`` well-spread points with a breadth-first quadtree.

    Args:
        points: (N, 2) float coordinates (x, y).
        responses: (N,) corner strengths.
        quota: how many points to keep.
        extent: (width, height) of the region the points lie in.

    Returns:
        (M,) int64 indices into ``points``, M <= quota, strongest first.
    """
    n = points.shape[0]
    if quota <= 0 or n == 0:
        return np.zeros(0, np.int64)
    if n <= quota:
        return np.argsort(-responses, kind="stable")
    side = float(max(extent[0], extent[1], 1.0))
    # depths with fewer than ``quota`` cells (4^depth < quota) cannot stop the search: start at
    # the first with enough, unless the cells fall below a pixel before it
    depth = 0
    while (1 << (2 * depth)) < quota and side / (1 << depth) >= 1.0:
        depth += 1
    cells = np.zeros(n, np.int64)
    while True:
        cell = side / (1 << depth)
        cx = np.floor(points[:, 0] / cell).astype(np.int64)
        cy = np.floor(points[:, 1] / cell).astype(np.int64)
        cells = cy * (1 << depth) + cx
        n_cells = distinct(cells).size
        # Stop when there are enough cells, or cells are below a pixel (duplicates remain).
        if n_cells >= quota or cell < 1.0:
            break
        depth += 1
    # strongest point of each cell: sort by (cell, -response), take the first of each run
    order = np.lexsort((-responses, cells))
    first = np.ones(order.size, bool)
    first[1:] = cells[order[1:]] != cells[order[:-1]]
    winners = order[first]
    winners = winners[np.argsort(-responses[winners], kind="stable")]
    return winners[:quota]


def quadtree_kernel(wait: bool = True) -> Any:
    """The compiled per-level quadtree pick (:mod:`stablecues.features._compiled`), or None
    when numba is missing or fails here (then NumPy runs); compiled or loaded once, in the
    background with ``wait=False`` (None until then; see :mod:`stablecues.engine`)."""
    return _PICK.get(wait)


def _load_pick() -> Any:
    from . import _compiled

    pick = _compiled.quadtree_select
    pick(np.zeros((1, 2), np.float32), np.zeros(1, np.float32), np.zeros(1, np.int64),
         np.ones(1, np.int64), 1.0)
    return pick


_PICK: Kernels[Any] = Kernels(_load_pick, "ORB's keypoint spread")


def select_keypoints(
    points: np.ndarray, responses: np.ndarray, octaves: np.ndarray, quotas: np.ndarray,
    extent: tuple[float, float], engine: str = "auto",
) -> np.ndarray:
    """Each pyramid level's :func:`distribute_quadtree` pick, levels in order; a level that
    lacks corners hands its unused quota down to the next.

    Args:
        points: (N, 2) coordinates and (N,) responses, both taken as float32 (as ORB gives
            them); octaves: (N,) int64 levels.
        quotas: (L,) int64 keypoints wanted per level.
        extent: (width, height) of the image.
        engine: ``"auto"``, ``"compiled"`` or ``"numpy"`` (see
            :mod:`stablecues.engine`): one compiled loop over all levels, or NumPy
            per level; the two pick the same keypoints in the same order.

    Returns:
        (M,) int64 indices into ``points``.
    """
    points = np.ascontiguousarray(points, np.float32)
    responses = np.ascontiguousarray(responses, np.float32)
    side = float(max(extent[0], extent[1], 1.0))
    # the compiled loop sorts (cell * n + position) keys in int64: cells stay below 4 side^2
    fits = 4.0 * side * side * max(points.shape[0], 1) < 2.0**62
    choice = requested(engine)
    kernel = quadtree_kernel(wait=choice == "compiled") if fits and choice != "numpy" else None
    if kernel is not None:
        return kernel(points, responses, np.ascontiguousarray(octaves, np.int64),
                      np.ascontiguousarray(quotas, np.int64), side)
    if fits and choice == "compiled":
        raise ImportError("the compiled keypoint spread needs numba, which is missing or failed to compile "
                          "here: pip install numba (or use engine='numpy')")
    keep: list[np.ndarray] = [np.zeros(0, np.int64)]
    carry = 0
    for level in range(len(quotas)):
        idx = np.flatnonzero(octaves == level)
        quota = int(quotas[level]) + carry
        chosen = idx[distribute_quadtree(points[idx], responses[idx], quota, extent)]
        carry = quota - chosen.size
        keep.append(chosen)
    return np.concatenate(keep).astype(np.int64)


class OrbExtractor:
    """ORB keypoints and 32-byte binary descriptors (see the module docstring for the spread)."""

    def __init__(self, config: OrbConfig | None = None) -> None:
        self.config = config or OrbConfig()

    @property
    def descriptor_kind(self) -> DescriptorKind:
        """32-byte binary (256-bit BRIEF)."""
        return ORB_DESCRIPTOR

    @property
    def level_scale(self) -> float:
        """The pyramid's ``scale_factor``."""
        return self.config.scale_factor

    def _orb(self, n: int, fast: int) -> cv2.ORB:
        c = self.config
        return cv2.ORB.create(
            nfeatures=max(int(n), 1),
            scaleFactor=c.scale_factor,
            nlevels=c.n_levels,
            edgeThreshold=c.edge_threshold,
            firstLevel=0,
            WTA_K=2,
            scoreType=cv2.ORB_HARRIS_SCORE,
            patchSize=c.patch_size,
            fastThreshold=fast,
        )

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        """Detect and describe ORB features.

        Args:
            image: (H, W) grey or (H, W, 3) BGR uint8 image, any size.
            mask: optional (H, W) uint8 mask; keypoints only where it is nonzero.

        Returns:
            Features, at most ``n_features`` of them, possibly none.
        """
        grey = to_grey(image)
        h, w = grey.shape
        size = (int(w), int(h))
        mask = check_mask(mask, grey.shape)
        c = self.config
        if c.clahe > 0 and grey.size:
            grey = cv2.createCLAHE(clipLimit=c.clahe, tileGridSize=(8, 8)).apply(np.ascontiguousarray(grey))
        if c.n_features == 0 or min(h, w) <= 2 * c.edge_threshold:
            return Features.empty(size)
        if c.distribute == "none":
            orb = self._orb(c.n_features, c.ini_fast)
            kps, desc = orb.detectAndCompute(grey, mask)
            return _to_features(kps, desc, size)
        want = int(np.ceil(c.n_features * c.oversample))
        orb = self._orb(want, c.ini_fast)
        kps = list(orb.detect(grey, mask))
        if len(kps) < c.n_features:
            extra = self._orb(want, c.min_fast).detect(grey, mask)
            kps = _merge_keypoints(kps, list(extra))
        if not kps:
            return Features.empty(size)
        pts = np.asarray(cv2.KeyPoint.convert(kps), np.float32).reshape(-1, 2)
        resp = np.fromiter(map(_RESPONSE, kps), np.float32, len(kps))
        octv = np.fromiter(map(_OCTAVE, kps), np.int64, len(kps))
        quotas = level_quotas(c.n_features, c.scale_factor, c.n_levels)
        picked = select_keypoints(pts, resp, octv, quotas, (w, h))
        selected = [kps[i] for i in picked]
        described, desc = orb.compute(grey, selected)
        return _to_features(described, desc, size)


def _merge_keypoints(a: Sequence[cv2.KeyPoint], b: Sequence[cv2.KeyPoint]) -> list[cv2.KeyPoint]:
    """Union of two detections, dropping from ``b`` points already in ``a`` (same level, < 1 px)."""
    if not a:
        return list(b)
    seen = {(k.octave, round(k.pt[0]), round(k.pt[1])) for k in a}
    return list(a) + [k for k in b if (k.octave, round(k.pt[0]), round(k.pt[1])) not in seen]


def _to_features(
    kps: Sequence[cv2.KeyPoint], desc: np.ndarray | None, size: tuple[int, int]
) -> Features:
    if desc is None or len(kps) == 0:
        return Features.empty(size)
    n = len(kps)
    return Features(
        keypoints=np.asarray(cv2.KeyPoint.convert(kps), np.float32).reshape(-1, 2),
        descriptors=np.ascontiguousarray(desc, dtype=np.uint8),
        octaves=np.fromiter(map(_OCTAVE, kps), np.int16, n),
        angles=np.fromiter(map(_ANGLE, kps), np.float32, n),
        responses=np.fromiter(map(_RESPONSE, kps), np.float32, n),
        sizes=np.fromiter(map(_SIZE, kps), np.float32, n),
        image_size=size,
    )
