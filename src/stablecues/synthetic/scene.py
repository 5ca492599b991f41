"""Textured quads, the texture bank, and lighting: the building blocks of the synthetic town.

A scene is a set of planar rectangles ("quads"), each carrying a window of a procedural texture.
A quad is stored by the world position of its texture's texel (0, 0) and the world displacement of
one texel along the texture's columns (``u``) and rows (``v``), so texel ``(tx, ty)`` lies at
``origin + tx * u + ty * v``; ``rect`` is the part of the texture the quad shows. The front side is
the one a viewer sees with the texture upright and unmirrored: its normal is ``-(u x v)``.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..semantics.classes import CLASS_NAMES, VOID_NAME

# CamVid 11-class ids
SKY, BUILDING, POLE, ROAD, PAVEMENT, TREE, SIGN, FENCE, CAR, PEDESTRIAN, BICYCLIST, UNLABELLED = range(12)
CAMVID_CLASSES = (*CLASS_NAMES, VOID_NAME)  # the 11 classes and void, ids 0..11
#: classes whose surfaces decide the visibility-based ground truth (static, textured, upright)
LANDMARK_CLASSES = (BUILDING, POLE, TREE, SIGN, FENCE)

LIT_NORMAL = 0  # Lambert shading by the quad's normal
LIT_FOLIAGE = 1  # translucent-looking, shaded by the sun's height only
LIT_EMISSIVE = 2  # not shaded by the sun (lamps), only exposure

UP = np.array([0.0, 0.0, 1.0])


def right_of(direction: np.ndarray) -> np.ndarray:
    """The horizontal unit vector to the right of a horizontal direction (seen from above)."""
    return np.array([direction[1], -direction[0], 0.0])


class TextureBank:
    """Textures made on first use from a generator and a seed, kept with their mip levels.

    Each texture is registered as ``(generator, args, seed key)``; generating it again (after it
    was evicted) gives the same pixels. Mip levels are made with ``cv2.pyrDown``: texel ``i`` of
    level ``L`` sits at texel ``i * 2**L`` of level 0.
    """

    def __init__(self, budget_bytes: int = 512 * 2**20) -> None:
        self._specs: list[
            tuple[Callable[..., np.ndarray], tuple[Any, ...], dict[str, Any], tuple[int, ...]]
        ] = []
        self._cache: OrderedDict[int, list[np.ndarray]] = OrderedDict()
        self._bytes = 0
        self.budget = budget_bytes
        self.generated = 0

    def __len__(self) -> int:
        return len(self._specs)

    def register(
        self, fn: Callable[..., np.ndarray], *args: Any, seed: tuple[int, ...], **kwargs: Any
    ) -> int:
        """Register a texture; returns its id. ``fn(rng, *args, **kwargs)`` makes it."""
        self._specs.append((fn, args, kwargs, seed))
        return len(self._specs) - 1

    def levels(self, tex_id: int) -> list[np.ndarray]:
        """The mip pyramid of texture ``tex_id`` (level 0 first), generating it if needed."""
        hit = self._cache.get(tex_id)
        if hit is not None:
            self._cache.move_to_end(tex_id)
            return hit
        fn, args, kwargs, seed = self._specs[tex_id]
        img = np.ascontiguousarray(fn(np.random.default_rng(list(seed)), *args, **kwargs))
        pyramid = [img]
        while min(pyramid[-1].shape[:2]) >= 16 and len(pyramid) < 7:
            pyramid.append(cv2.pyrDown(pyramid[-1]))
        self.generated += 1
        self._cache[tex_id] = pyramid
        self._bytes += sum(p.nbytes for p in pyramid)
        while self._bytes > self.budget and len(self._cache) > 1:
            _, old = self._cache.popitem(last=False)
            self._bytes -= sum(p.nbytes for p in old)
        return pyramid


@dataclass
class QuadSet:
    """Quads as arrays (M of them). See the module docstring for the geometry.

    Attributes:
        origin: (M, 3) float64 world position of texel (0, 0).
        u: (M, 3) float64 world displacement per texel along the texture's columns.
        v: (M, 3) float64 world displacement per texel along the texture's rows.
        rect: (M, 4) float64 texel window ``(tx0, ty0, tx1, ty1)`` shown by the quad.
        tex: (M,) int32 texture ids in the bank.
        label: (M,) uint8 CamVid class id.
        two_sided: (M,) bool; one-sided quads are culled from behind.
        lit: (M,) uint8 shading kind (LIT_*).
        vis: (M,) int32 visibility id (static quads: their index), -1 for dynamic ones.
        obj: (M,) int32 owning object (dynamic quads), -1 for static ones.
        lod: (M,) int8 level of detail: LOD_ALWAYS, LOD_PIECE (a piece of a long quad, drawn
            near the camera) or LOD_WHOLE (the long quad in one piece, drawn far from it).
        parent: (M,) int32 index of the whole quad a piece belongs to (itself for a whole quad),
            -1 for LOD_ALWAYS.
    """

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    rect: np.ndarray
    tex: np.ndarray
    label: np.ndarray
    two_sided: np.ndarray
    lit: np.ndarray
    vis: np.ndarray
    obj: np.ndarray
    lod: np.ndarray
    parent: np.ndarray

    def __len__(self) -> int:
        return int(self.tex.shape[0])

    @staticmethod
    def empty() -> QuadSet:
        z3 = np.zeros((0, 3))
        i32 = np.zeros(0, np.int32)
        return QuadSet(
            z3,
            z3,
            z3,
            np.zeros((0, 4)),
            i32,
            np.zeros(0, np.uint8),
            np.zeros(0, bool),
            np.zeros(0, np.uint8),
            i32,
            i32,
            np.zeros(0, np.int8),
            i32,
        )

    def subset(self, idx: np.ndarray) -> QuadSet:
        return QuadSet(*(getattr(self, f)[idx] for f in _FIELDS))

    @staticmethod
    def concat(parts: list[QuadSet]) -> QuadSet:
        parts = [p for p in parts if len(p)]
        if not parts:
            return QuadSet.empty()
        if len(parts) == 1:
            return parts[0]
        return QuadSet(*(np.concatenate([getattr(p, f) for p in parts]) for f in _FIELDS))

    def corners(self) -> np.ndarray:
        """(M, 4, 3) world corners in the order (tx0,ty0), (tx1,ty0), (tx1,ty1), (tx0,ty1)."""
        r = self.rect
        tx = np.stack([r[:, 0], r[:, 2], r[:, 2], r[:, 0]], axis=1)
        ty = np.stack([r[:, 1], r[:, 1], r[:, 3], r[:, 3]], axis=1)
        return (
            self.origin[:, None, :] + tx[..., None] * self.u[:, None, :] + ty[..., None] * self.v[:, None, :]
        )

    def normals(self) -> np.ndarray:
        """(M, 3) unit front normals ``-(u x v) / |u x v|``."""
        n = -np.cross(self.u, self.v)
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounding spheres: (M, 3) centres and (M,) radii."""
        c = self.corners()
        centre = c.mean(axis=1)
        radius = np.linalg.norm(c - centre[:, None, :], axis=2).max(axis=1)
        return centre, radius


_FIELDS = ("origin", "u", "v", "rect", "tex", "label", "two_sided", "lit", "vis", "obj", "lod", "parent")
LOD_ALWAYS, LOD_PIECE, LOD_WHOLE = 0, 1, 2


class QuadBuilder:
    """Collects quads one by one (lists), then freezes them into a :class:`QuadSet`."""

    def __init__(self) -> None:
        self._rows: list[tuple[Any, ...]] = []

    def __len__(self) -> int:
        return len(self._rows)

    def add(
        self,
        top_left: np.ndarray,
        u_dir: np.ndarray,
        v_dir: np.ndarray,
        width_m: float,
        height_m: float,
        tex: int,
        ppm: float,
        label: int,
        *,
        two_sided: bool = False,
        lit: int = LIT_NORMAL,
        chunk_m: float | None = None,
        tex_offset_m: tuple[float, float] = (0.0, 0.0),
        obj: int = -1,
        ppm_v: float | None = None,
    ) -> None:
        """Add a rectangle ``width_m`` along ``u_dir`` by ``height_m`` along ``v_dir`` from ``top_left``.

        The texture (``ppm`` texels per metre) is laid from ``tex_offset_m`` (metres into the
        texture). ``chunk_m`` splits the rectangle along ``u_dir`` into pieces no longer than that,
        which keeps screen bounding boxes tight and lets each piece choose its own mip level near
        the camera; the whole rectangle is kept too, drawn instead of its pieces when far away.
        ``ppm_v`` sets a different resolution along ``v_dir`` (a texture stretched one way).
        """
        pv = ppm if ppm_v is None else ppm_v
        u = np.asarray(u_dir, float) / ppm
        v = np.asarray(v_dir, float) / pv
        ox, oy = tex_offset_m
        origin = np.asarray(top_left, float) - ox * ppm * u - oy * pv * v
        n = 1 if not chunk_m else max(1, math.ceil(width_m / chunk_m - 1e-9))
        whole = (ox * ppm, oy * pv, (ox + width_m) * ppm, (oy + height_m) * pv)
        if n == 1:
            self._rows.append((origin, u, v, whole, tex, label, two_sided, lit, obj, LOD_ALWAYS, -1))
            return
        parent = len(self._rows)
        self._rows.append((origin, u, v, whole, tex, label, two_sided, lit, obj, LOD_WHOLE, parent))
        edges = np.linspace(0.0, width_m, n + 1)
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            rect = ((ox + a) * ppm, oy * pv, (ox + b) * ppm, (oy + height_m) * pv)
            self._rows.append((origin, u, v, rect, tex, label, two_sided, lit, obj, LOD_PIECE, parent))

    def build(self, static: bool) -> QuadSet:
        if not self._rows:
            return QuadSet.empty()
        origin, u, v, rect, tex, label, two, lit, obj, lod, parent = zip(*self._rows, strict=True)
        m = len(self._rows)
        return QuadSet(
            origin=np.array(origin, float),
            u=np.array(u, float),
            v=np.array(v, float),
            rect=np.array(rect, float),
            tex=np.array(tex, np.int32),
            label=np.array(label, np.uint8),
            two_sided=np.array(two, bool),
            lit=np.array(lit, np.uint8),
            vis=np.arange(m, dtype=np.int32) if static else np.full(m, -1, np.int32),
            obj=np.array(obj, np.int32),
            lod=np.array(lod, np.int8),
            parent=np.array(parent, np.int32),
        )


def vertical_quad(
    b: QuadBuilder,
    start: np.ndarray,
    u_dir: np.ndarray,
    width_m: float,
    z0: float,
    z1: float,
    tex: int,
    ppm: float,
    label: int,
    **kwargs: Any,
) -> None:
    """An upright rectangle from ground point ``start`` along horizontal ``u_dir``, heights z0..z1."""
    tl = np.array([start[0], start[1], z1])
    b.add(tl, u_dir, -UP, width_m, z1 - z0, tex, ppm, label, **kwargs)


def ground_quad(
    b: QuadBuilder,
    start: np.ndarray,
    u_dir: np.ndarray,
    length_m: float,
    width_m: float,
    tex: int,
    ppm: float,
    label: int,
    z: float = 0.0,
    **kwargs: Any,
) -> None:
    """A ground rectangle seen from above: ``length_m`` along ``u_dir``, ``width_m`` to its right."""
    tl = np.array([start[0], start[1], z])
    b.add(tl, u_dir, right_of(u_dir), length_m, width_m, tex, ppm, label, **kwargs)


# --------------------------------------------------------------------------------------- lighting


@dataclass(frozen=True)
class Lighting:
    """The light of one lap (one time of day).

    Attributes:
        hour: local solar time in hours.
        sun: (3,) unit vector towards the sun (world, z up).
        sun_bgr: (3,) sun strength per channel.
        ambient_bgr: (3,) sky light per channel.
        exposure: overall gain.
        overcast: no direct sun (no cast shadows).
        sky_tex: texture id of the sky panorama.
    """

    hour: float
    sun: np.ndarray
    sun_bgr: np.ndarray
    ambient_bgr: np.ndarray
    exposure: float
    overcast: bool
    sky_tex: int

    def gains(self, normals: np.ndarray, lit: np.ndarray) -> np.ndarray:
        """(M, 3) per-channel colour gains for quads with front ``normals`` (M, 3) and ``lit`` kinds."""
        cos = np.clip(normals @ self.sun, 0.0, None)
        cos = np.where(lit == LIT_FOLIAGE, 0.55 * max(self.sun[2], 0.0) + 0.15, cos)
        g = self.ambient_bgr[None, :] + cos[:, None] * self.sun_bgr[None, :]
        g = np.where((lit == LIT_EMISSIVE)[:, None], 1.0, g)
        return g * self.exposure

    def shadow_gain(self, receiver_normal: np.ndarray) -> np.ndarray:
        """(3,) factor that turns a sun-lit receiver into a shadowed one."""
        cos = max(float(receiver_normal @ self.sun), 0.0)
        lit = self.ambient_bgr + cos * self.sun_bgr
        return self.ambient_bgr / np.maximum(lit, 1e-6)


def make_lighting(hour: float, overcast: bool, sky_tex: int) -> Lighting:
    """Sun position and colours for a time of day (a simple mid-latitude model, sun south at noon)."""
    elev = math.radians(max(4.0, 60.0 * math.sin(math.pi * (hour - 6.0) / 13.0)))
    az = math.radians(180.0 + (hour - 12.0) * 15.0)  # from north, clockwise
    sun = np.array([math.sin(az) * math.cos(elev), math.cos(az) * math.cos(elev), math.sin(elev)])
    warm = float(np.clip(1.0 - math.degrees(elev) / 35.0, 0.0, 1.0))
    if overcast:
        sun_bgr = np.array([0.08, 0.08, 0.08])
        ambient = np.array([0.86, 0.86, 0.84])
        exposure = 0.95
    else:
        sun_bgr = np.array([1.0 - 0.55 * warm, 1.0 - 0.3 * warm, 1.0]) * 0.62
        ambient = np.array([0.62, 0.55, 0.5]) * (0.6 + 0.4 * (1.0 - warm))
        exposure = 1.12 - 0.1 * warm
    return Lighting(hour, sun, sun_bgr, ambient, exposure, overcast, sky_tex)


def sky_colours(
    hour: float, overcast: bool
) -> tuple[tuple[float, float, float], tuple[float, float, float], float, tuple[float, float, float]]:
    """(horizon BGR, zenith BGR, cloud cover, cloud BGR) for a time of day."""
    elev = max(4.0, 60.0 * math.sin(math.pi * (hour - 6.0) / 13.0))
    warm = float(np.clip(1.0 - elev / 35.0, 0.0, 1.0))
    if overcast:
        return (200.0, 200.0, 195.0), (170.0, 165.0, 160.0), 0.9, (215.0, 215.0, 212.0)
    horizon = (235.0 - 90 * warm, 215.0 - 40 * warm, 200.0 + 40 * warm)
    zenith = (215.0 - 40 * warm, 150.0 - 40 * warm, 90.0 - 20 * warm)
    return horizon, zenith, 0.35, (240.0 - 60 * warm, 240.0 - 30 * warm, 245.0)
