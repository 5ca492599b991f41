"""The town: a grid of blocks lined with buildings, street furniture, and per-lap traffic and light.

World frame: x east, y north, z up, metres. Streets run along the interior grid lines; a street is
``2 * ROAD_HALF`` wide (a driving lane and a parking strip each way) with a ``SIDEWALK`` on each
side, then the facades. The outer ring of blocks closes the town; each street ends at a tall
building across it at the town's edge.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import textures as tx
from .scene import (
    BICYCLIST,
    BUILDING,
    CAR,
    FENCE,
    LIT_EMISSIVE,
    LIT_FOLIAGE,
    PAVEMENT,
    PEDESTRIAN,
    POLE,
    ROAD,
    SIGN,
    TREE,
    UP,
    Lighting,
    QuadBuilder,
    QuadSet,
    TextureBank,
    ground_quad,
    right_of,
    vertical_quad,
)

ROAD_HALF = 6.0
SIDEWALK = 3.5
SETBACK = ROAD_HALF + SIDEWALK
PARKING = 2.0
DRIVE_LANE = 2.0  # centre of the driving lane from the street centre line
PARK_LANE = ROAD_HALF - PARKING / 2
CHUNK = 4.0

PPM_FACADE = 32.0
PPM_ROAD = 24.0
PPM_WALK = 32.0
PPM_TREE = 40.0
PPM_BARK = 64.0
PPM_POLE = 64.0
PPM_SIGN = 128.0
PPM_FENCE = 48.0
PPM_CAR = 48.0
PPM_PED = 64.0

# seed-key kinds (first element after the user seed)
K_LAYOUT, K_FACADE, K_SIDE, K_WALK, K_ROAD, K_CROSS, K_TREE, K_POLE, K_SIGN, K_FENCE, K_GAP, K_END, K_LAP = (
    range(13)
)

_DIRS = {  # outward normal of each block side; sides run counter-clockwise around the block
    "S": np.array([0.0, -1.0, 0.0]),
    "E": np.array([1.0, 0.0, 0.0]),
    "N": np.array([0.0, 1.0, 0.0]),
    "W": np.array([-1.0, 0.0, 0.0]),
}


def facade_u(n: np.ndarray) -> np.ndarray:
    """Direction of a facade's texture columns: the right hand of a viewer facing the facade."""
    return np.cross(-n, UP)


@dataclass
class Side:
    """A block side facing a street.

    Attributes:
        start: (3,) ground point where the facade line starts.
        u: (3,) unit direction along the side (the facade's texture columns).
        n: (3,) unit outward normal (towards the street).
        length: metres.
        street: (axis, index): axis 0 a street along x = xs[index], axis 1 along y = ys[index].
        buildings: (s0, s1, height) of each building along the side (gaps have height 0).
    """

    start: np.ndarray
    u: np.ndarray
    n: np.ndarray
    length: float
    street: tuple[int, int]
    buildings: list[tuple[float, float, float]] = field(default_factory=list)


@dataclass
class Movers:
    """Objects that move along straight lines (parked ones have speed 0), for one lap.

    ``position(t) = start + direction * ((s0 + speed * t) mod length)``; the object's local x axis
    points along ``direction``, y to its left, z up. ``quads`` are in that local frame, with
    ``obj`` naming the object; ``half`` (K, 2) holds each footprint's half length and half width.
    """

    start: np.ndarray
    direction: np.ndarray
    length: np.ndarray
    s0: np.ndarray
    speed: np.ndarray
    quads: QuadSet
    half: np.ndarray

    def __len__(self) -> int:
        return int(self.start.shape[0])

    def contains(self, t: float, point: np.ndarray, margin: float = 0.4) -> np.ndarray:
        """(K,) bool: objects whose footprint (grown by ``margin``) holds ``point`` (x, y) at time t."""
        d = np.asarray(point, float)[:2] - self.positions(t)[:, :2]
        fwd = self.direction[:, :2]
        along = np.abs((d * fwd).sum(axis=1))
        across = np.abs(d[:, 0] * fwd[:, 1] - d[:, 1] * fwd[:, 0])
        return (along < self.half[:, 0] + margin) & (across < self.half[:, 1] + margin)

    def positions(self, t: float) -> np.ndarray:
        """(K, 3) positions at lap time ``t`` seconds."""
        s = np.mod(self.s0 + self.speed * t, np.maximum(self.length, 1e-9))
        return self.start + self.direction * s[:, None]

    def world_quads(self, t: float, keep: np.ndarray) -> QuadSet:
        """The quads of the objects where ``keep`` (K,) bool is True, placed in the world at time ``t``."""
        sel = keep[self.quads.obj]
        q = self.quads.subset(np.nonzero(sel)[0])
        if not len(q):
            return q
        pos = self.positions(t)[q.obj]
        fwd = self.direction[q.obj]
        left = np.stack([-fwd[:, 1], fwd[:, 0], np.zeros(len(q))], axis=1)

        def rot(a: np.ndarray) -> np.ndarray:
            return a[:, :1] * fwd + a[:, 1:2] * left + a[:, 2:3] * UP[None, :]

        return QuadSet(
            pos + rot(q.origin),
            rot(q.u),
            rot(q.v),
            q.rect,
            q.tex,
            q.label,
            q.two_sided,
            q.lit,
            q.vis,
            q.obj,
            q.lod,
            q.parent,
        )


@dataclass
class Decals:
    """Cast shadows for one lap: quads lying in receiver planes, darkening what they cover.

    Attributes:
        quads: the shadow shapes (alpha textures give tree-shaped shadows).
        normal: (M, 3) receiver plane normals.
        gain: (M, 3) colour factor applied inside the shadow.
        alpha: (M,) bool, the texture's alpha decides the shape (else the whole quad).
        centre: (M, 3) bounding-sphere centres, for culling.
        radius: (M,) bounding-sphere radii.
    """

    quads: QuadSet
    normal: np.ndarray
    gain: np.ndarray
    alpha: np.ndarray
    centre: np.ndarray
    radius: np.ndarray

    def __len__(self) -> int:
        return len(self.quads)

    def subset(self, idx: np.ndarray) -> Decals:
        return Decals(
            self.quads.subset(idx),
            self.normal[idx],
            self.gain[idx],
            self.alpha[idx],
            self.centre[idx],
            self.radius[idx],
        )

    @staticmethod
    def empty() -> Decals:
        z = np.zeros((0, 3))
        return Decals(QuadSet.empty(), z, z, np.zeros(0, bool), z, np.zeros(0))


class Town:
    """The static town (geometry and textures) plus per-lap traffic, people and shadows.

    Args:
        seed: the user seed; every object's texture and placement derive from it.
        nbx, nby: blocks along x and y (the outer ring closes the town).
        clutter: density multiplier for trees, signs, fences, cars and people (0 = none).
        bank: where textures are registered.
    """

    def __init__(self, seed: int, nbx: int, nby: int, clutter: float, bank: TextureBank) -> None:
        self.seed = int(seed)
        self.nbx, self.nby = nbx, nby
        self.clutter = float(clutter)
        self.bank = bank
        rng = np.random.default_rng([self.seed, K_LAYOUT])
        wx = rng.uniform(38.0, 54.0, nbx)
        wy = rng.uniform(38.0, 54.0, nby)
        self.xs = np.concatenate([[0.0], np.cumsum(wx)])
        self.ys = np.concatenate([[0.0], np.cumsum(wy)])
        self.xs -= self.xs[-1] / 2
        self.ys -= self.ys[-1] / 2
        self.sides: list[Side] = []
        self._occluders: list[tuple[float, float, float, float, float]] = []  # x0, y0, x1, y1, height
        self._wall_heights: list[float] = []
        # building fronts that cast shadows: (top-left, u, width, height, n, facade across the street)
        self._casters: list[tuple[np.ndarray, np.ndarray, float, float, np.ndarray, bool]] = []
        self._prop_casters = QuadBuilder()  # trunks, canopies and poles, for their shadows
        b = QuadBuilder()
        self._build_blocks(b)
        self._build_streets(b)
        self._build_town_edge(b)
        self.static = b.build(static=True)
        self.prop_casters = self._prop_casters.build(static=False)
        self.static_centre, self.static_radius = self.static.spheres()
        self.static_normal = self.static.normals()
        occ = np.array(self._occluders, float).reshape(-1, 5)
        shrink = 0.3
        self.block_lo = np.column_stack([occ[:, 0] + shrink, occ[:, 1] + shrink, np.full(len(occ), -1.0)])
        self.block_hi = np.column_stack([occ[:, 2] - shrink, occ[:, 3] - shrink, occ[:, 4]])

    # ------------------------------------------------------------------ layout helpers

    def street_lines(self) -> list[tuple[int, int]]:
        """(axis, index) of every street: axis 0 runs along y at x = xs[i], axis 1 along x at y = ys[j]."""
        return [(0, i) for i in range(1, self.nbx)] + [(1, j) for j in range(1, self.nby)]

    def node(self, i: int, j: int) -> np.ndarray:
        """Ground point of the crossing of street lines x = xs[i] and y = ys[j]."""
        return np.array([self.xs[i], self.ys[j], 0.0])

    # ------------------------------------------------------------------ blocks

    def _build_blocks(self, b: QuadBuilder) -> None:
        for i in range(self.nbx):
            for j in range(self.nby):
                self._build_block(b, i, j)

    def _build_block(self, b: QuadBuilder, i: int, j: int) -> None:
        rng = np.random.default_rng([self.seed, K_LAYOUT, i, j])
        street = {"W": i > 0, "E": i < self.nbx - 1, "S": j > 0, "N": j < self.nby - 1}
        x0 = self.xs[i] + (SETBACK if street["W"] else 0.0)
        x1 = self.xs[i + 1] - (SETBACK if street["E"] else 0.0)
        y0 = self.ys[j] + (SETBACK if street["S"] else 0.0)
        y1 = self.ys[j + 1] - (SETBACK if street["N"] else 0.0)
        corners = {
            "S": np.array([x0, y0, 0.0]),
            "E": np.array([x1, y0, 0.0]),
            "N": np.array([x1, y1, 0.0]),
            "W": np.array([x0, y1, 0.0]),
        }
        order = ["S", "E", "N", "W"]
        corner_h = rng.uniform(10.0, 24.0, 4)  # corner k is the start of side order[k]
        depth = min(10.0, (x1 - x0) / 2, (y1 - y0) / 2)
        street_of = {"W": (0, i), "E": (0, i + 1), "S": (1, j), "N": (1, j + 1)}
        n_before = len(self.sides)
        walls_before = len(self._wall_heights)
        for k, name in enumerate(order):
            if not street[name]:
                continue
            n = _DIRS[name]
            u = facade_u(n)
            start = corners[name]
            end = corners[order[(k + 1) % 4]]
            length = float(np.linalg.norm(end - start))
            side = Side(start, u, n, length, street_of[name])
            self._build_side(b, side, float(corner_h[k]), float(corner_h[(k + 1) % 4]), depth, (i, j, k), rng)
            self.sides.append(side)
            # sidewalk corner square where this side and the next both face streets
            nxt = order[(k + 1) % 4]
            if street[nxt]:
                tex = self.bank.register(
                    tx.sidewalk, SIDEWALK, SIDEWALK, PPM_WALK, seed=(self.seed, K_WALK, i, j, k, 1)
                )
                ground_quad(b, end, u, SIDEWALK, SIDEWALK, tex, PPM_WALK, PAVEMENT)
        if len(self.sides) > n_before:
            # the block as a solid box for occlusion culling: every sight line into it meets a
            # facade, or a courtyard's fence and then its walls, all at least this high
            h_occ = min(self._wall_heights[walls_before:])
            self._occluders.append((x0, y0, x1, y1, h_occ))

    def _build_side(
        self,
        b: QuadBuilder,
        side: Side,
        h_start: float,
        h_end: float,
        depth: float,
        key: tuple[int, int, int],
        rng: np.random.Generator,
    ) -> None:
        i, j, k = key
        L = side.length
        # partition into buildings
        widths: list[float] = []
        rest = L
        while rest > 0:
            w = float(rng.uniform(6.0, 15.0))
            if rest - w < 6.0:
                w = rest if len(widths) >= 1 or rest < 12.0 else rest / 2
            widths.append(w)
            rest -= w
        if len(widths) == 1 and L >= 12.0:
            widths = [L / 2, L / 2]
        nb = len(widths)
        heights = rng.uniform(9.0, 25.0, nb)
        heights[0] = h_start
        heights[-1] = h_end if nb > 1 else max(h_start, h_end)
        gap = np.zeros(nb, bool)
        if nb > 2:
            gap[1:-1] = rng.random(nb - 2) < 0.15 * min(self.clutter, 2.0)
            gap[1:-1] &= np.array(widths[1:-1]) >= 6.0
        s = 0.0
        for bi, (w, h) in enumerate(zip(widths, heights, strict=True)):
            p0 = side.start + side.u * s
            if gap[bi]:
                self._build_gap(b, side, p0, w, (i, j, k, bi))
                side.buildings.append((s, s + w, 0.0))
            else:
                tex = self.bank.register(tx.facade, w, h, PPM_FACADE, seed=(self.seed, K_FACADE, i, j, k, bi))
                vertical_quad(b, p0, side.u, w, 0.0, h, tex, PPM_FACADE, BUILDING, chunk_m=CHUNK)
                self._casters.append((np.array([p0[0], p0[1], h]), side.u, w, h, side.n, True))
                side.buildings.append((s, s + w, float(h)))
                self._wall_heights.append(float(h))
            s += w
        # side walls where neighbours differ in height (a gap counts as height 0; walls
        # beside a courtyard are as deep as it)
        for bi in range(nb - 1):
            ha = 0.0 if gap[bi] else heights[bi]
            hb = 0.0 if gap[bi + 1] else heights[bi + 1]
            if abs(ha - hb) < 0.3:
                continue
            p = side.start + side.u * float(np.sum(widths[: bi + 1]))
            d = 12.0 if (gap[bi] or gap[bi + 1]) else depth
            lo, hi = min(ha, hb), max(ha, hb)
            tex = self.bank.register(
                tx.facade, d, hi - lo, PPM_FACADE, side=True, seed=(self.seed, K_SIDE, i, j, k, bi)
            )
            if ha > hb:  # wall of building bi, facing +u
                vertical_quad(b, p, -side.n, d, lo, hi, tex, PPM_FACADE, BUILDING, chunk_m=CHUNK)
            else:  # wall of building bi+1, facing -u
                vertical_quad(b, p - side.n * d, side.n, d, lo, hi, tex, PPM_FACADE, BUILDING, chunk_m=CHUNK)
        self._build_sidewalk(b, side, key, rng)

    def _build_gap(self, b: QuadBuilder, side: Side, p0: np.ndarray, w: float, key: tuple[int, ...]) -> None:
        """A courtyard between buildings: a fence on the facade line, gravel, trees, a back wall."""
        rng = np.random.default_rng([self.seed, K_GAP, *key])
        deep = 12.0
        fh = float(rng.uniform(1.2, 2.0))
        tex = self.bank.register(tx.fence, w, fh, PPM_FENCE, seed=(self.seed, K_FENCE, *key))
        vertical_quad(b, p0, side.u, w, 0.0, fh, tex, PPM_FENCE, FENCE, two_sided=True, chunk_m=CHUNK)
        tex = self.bank.register(tx.gravel, w, deep, 24.0, seed=(self.seed, K_GAP, *key, 1))
        ground_quad(b, p0 - side.n * deep, side.u, w, deep, tex, 24.0, PAVEMENT)
        bh = float(rng.uniform(8.0, 16.0))
        self._wall_heights.append(bh)
        tex = self.bank.register(tx.facade, w, bh, PPM_FACADE, side=True, seed=(self.seed, K_GAP, *key, 2))
        back = p0 - side.n * deep
        vertical_quad(b, back, side.u, w, 0.0, bh, tex, PPM_FACADE, BUILDING, chunk_m=CHUNK)
        for t in range(int(rng.integers(1, 3))):
            pos = p0 + side.u * rng.uniform(1.5, max(1.6, w - 1.5)) - side.n * rng.uniform(4.0, 9.0)
            self._tree(b, pos, side.u, (*key, 10 + t), rng)

    def _build_sidewalk(
        self, b: QuadBuilder, side: Side, key: tuple[int, int, int], rng: np.random.Generator
    ) -> None:
        i, j, k = key
        L = side.length
        c = self.clutter
        kerb_off = SIDEWALK - 0.9  # tree pits and poles stand this far from the facade line
        trees: list[float] = []
        if rng.random() < 0.75 and c > 0:
            spacing = float(rng.uniform(8.0, 13.0)) / min(c, 3.0)
            s = float(rng.uniform(2.0, 2.0 + spacing))
            while s < L - 2.0:
                trees.append(s)
                s += spacing * float(rng.uniform(0.8, 1.2))
        tex = self.bank.register(
            tx.sidewalk, L, SIDEWALK, PPM_WALK, features=tuple(trees), seed=(self.seed, K_WALK, i, j, k)
        )
        ground_quad(b, side.start, side.u, L, SIDEWALK, tex, PPM_WALK, PAVEMENT, chunk_m=CHUNK)
        for t, s in enumerate(trees):
            self._tree(b, side.start + side.u * s + side.n * kerb_off, side.u, (i, j, k, t), rng)
        # lamp posts
        if c > 0 and (i + j + k) % 2 == 0:
            s = float(rng.uniform(3.0, 10.0))
            while s < L - 3.0:
                if all(abs(s - t) > 2.0 for t in trees):
                    self._lamp(
                        b, side.start + side.u * s + side.n * (SIDEWALK - 0.5), side.n, (i, j, k, int(s))
                    )
                s += float(rng.uniform(18.0, 26.0))
        # a traffic sign facing the traffic of the adjacent lane (which moves along -u), near the side's start
        if c > 0 and rng.random() < min(0.9, 0.6 * c):
            s = float(rng.uniform(2.5, 6.0))
            self._sign(b, side.start + side.u * s + side.n * (SIDEWALK - 0.45), side.u, (i, j, k, 0), rng)
        if c > 0 and rng.random() < 0.35 * min(c, 2.0):
            s = float(rng.uniform(L * 0.3, L * 0.8))
            self._sign(b, side.start + side.u * s + side.n * (SIDEWALK - 0.45), side.u, (i, j, k, 1), rng)
        # a railing along the kerb
        if c > 0 and rng.random() < 0.2 * min(c, 2.0):
            a = float(rng.uniform(3.0, L / 2))
            ln = float(min(rng.uniform(5.0, 14.0), L - a - 3.0))
            if ln > 2.0:
                p = side.start + side.u * a + side.n * (SIDEWALK - 0.25)
                tex = self.bank.register(tx.fence, ln, 1.1, PPM_FENCE, seed=(self.seed, K_FENCE, i, j, k, 99))
                vertical_quad(
                    b, p, side.u, ln, 0.0, 1.1, tex, PPM_FENCE, FENCE, two_sided=True, chunk_m=CHUNK
                )

    def _tree(
        self, b: QuadBuilder, pos: np.ndarray, u: np.ndarray, key: tuple[int, ...], rng: np.random.Generator
    ) -> None:
        trunk_h = float(rng.uniform(2.2, 3.2))
        cw = float(rng.uniform(3.5, 5.5))
        ch = float(rng.uniform(3.5, 5.5))
        tw = 0.35
        perp = np.array([-u[1], u[0], 0.0])
        bark = self.bank.register(tx.bark, tw, trunk_h + 1.0, PPM_BARK, seed=(self.seed, K_TREE, *key, 0))
        for ax in (u, perp):
            vertical_quad(
                b, pos - ax * tw / 2, ax, tw, 0.0, trunk_h + 1.0, bark, PPM_BARK, TREE, two_sided=True
            )
        vertical_quad(self._prop_casters, pos - u * tw / 2, u, tw, 0.0, trunk_h + 1.0, bark, PPM_BARK, TREE)
        z0 = trunk_h - 0.6
        for a, ax in enumerate((u, perp)):
            tex = self.bank.register(tx.foliage, cw, ch, PPM_TREE, seed=(self.seed, K_TREE, *key, 1 + a))
            vertical_quad(
                b,
                pos - ax * cw / 2,
                ax,
                cw,
                z0,
                z0 + ch,
                tex,
                PPM_TREE,
                TREE,
                two_sided=True,
                lit=LIT_FOLIAGE,
            )
            vertical_quad(
                self._prop_casters,
                pos - ax * cw / 2,
                ax,
                cw,
                z0,
                z0 + ch,
                tex,
                PPM_TREE,
                TREE,
                lit=LIT_FOLIAGE,
            )

    def _lamp(self, b: QuadBuilder, pos: np.ndarray, n: np.ndarray, key: tuple[int, ...]) -> None:
        h = 6.0
        pw = 0.16
        u = facade_u(n)
        tex = self.bank.register(tx.metal, pw, h, PPM_POLE, seed=(self.seed, K_POLE, *key, 0))
        for ax in (u, n):
            vertical_quad(b, pos - ax * pw / 2, ax, pw, 0.0, h, tex, PPM_POLE, POLE, two_sided=True)
        vertical_quad(self._prop_casters, pos - u * pw / 2, u, pw, 0.0, h, tex, PPM_POLE, POLE)
        head = self.bank.register(tx.lamp_head, 1.6, 0.5, PPM_POLE, seed=(self.seed, K_POLE, *key, 1))
        vertical_quad(b, pos, n, 1.6, h - 0.45, h + 0.05, head, PPM_POLE, POLE, two_sided=True)

    def _sign(
        self,
        b: QuadBuilder,
        pos: np.ndarray,
        face: np.ndarray,
        key: tuple[int, ...],
        rng: np.random.Generator,
    ) -> None:
        """A sign on a pole; its face looks along ``face`` (towards the traffic it is for)."""
        h = float(rng.uniform(2.2, 2.6))
        pw = 0.07
        perp = np.array([-face[1], face[0], 0.0])
        pole = self.bank.register(tx.metal, pw, h, PPM_POLE, seed=(self.seed, K_SIGN, *key, 0))
        for ax in (face, perp):
            vertical_quad(b, pos - ax * pw / 2, ax, pw, 0.0, h, pole, PPM_POLE, POLE, two_sided=True)
        kind = rng.random()
        if kind < 0.2:  # traffic light housing
            tw_, th_ = 0.35, 1.0
            lit = int(rng.integers(3))
            tl = self.bank.register(
                tx.traffic_light, tw_, th_, PPM_SIGN, lit, seed=(self.seed, K_SIGN, *key, 1)
            )
            back = self.bank.register(tx.metal, tw_, th_, PPM_SIGN, seed=(self.seed, K_SIGN, *key, 2))
            u = facade_u(face)
            p = pos + face * 0.05
            vertical_quad(b, p - u * tw_ / 2, u, tw_, h, h + th_, tl, PPM_SIGN, SIGN, lit=LIT_EMISSIVE)
            vertical_quad(b, p - face * 0.1 + u * tw_ / 2, -u, tw_, h, h + th_, back, PPM_SIGN, SIGN)
            return
        size = float(rng.uniform(0.55, 0.8))
        plate = self.bank.register(tx.sign_plate, size, PPM_SIGN, seed=(self.seed, K_SIGN, *key, 1))
        back = self.bank.register(_sign_back_of_plate, size, PPM_SIGN, seed=(self.seed, K_SIGN, *key, 1))
        u = facade_u(face)
        p = pos + face * 0.05
        vertical_quad(b, p - u * size / 2, u, size, h - 0.2, h - 0.2 + size, plate, PPM_SIGN, SIGN)
        vertical_quad(
            b, p - face * 0.01 + u * size / 2, -u, size, h - 0.2, h - 0.2 + size, back, PPM_SIGN, SIGN
        )
        if kind > 0.75:  # a street-name plate under it, readable from both sides
            name = self.bank.register(tx.street_name, 1.0, 0.25, PPM_SIGN, seed=(self.seed, K_SIGN, *key, 3))
            vertical_quad(b, p - u * 0.5, u, 1.0, h - 0.6, h - 0.35, name, PPM_SIGN, SIGN, two_sided=True)

    # ------------------------------------------------------------------ streets

    def _build_streets(self, b: QuadBuilder) -> None:
        for axis, idx in self.street_lines():
            cross = self.ys if axis == 0 else self.xs
            pos = (self.xs if axis == 0 else self.ys)[idx]
            u = np.array([0.0, 1.0, 0.0]) if axis == 0 else np.array([1.0, 0.0, 0.0])
            r = right_of(u)
            n_cross = len(cross) - 1
            for seg in range(n_cross):
                a = cross[seg] + (ROAD_HALF if seg > 0 else 0.0)
                e = cross[seg + 1] - (ROAD_HALF if seg < n_cross - 1 else 0.0)
                length = float(e - a)
                start = (np.array([pos, a, 0.0]) if axis == 0 else np.array([a, pos, 0.0])) - r * ROAD_HALF
                tex = self.bank.register(
                    tx.road,
                    length,
                    2 * ROAD_HALF,
                    PPM_ROAD,
                    parking_m=PARKING,
                    zebra=(seg > 0, seg < n_cross - 1),
                    seed=(self.seed, K_ROAD, axis, idx, seg),
                )
                ground_quad(b, start, u, length, 2 * ROAD_HALF, tex, PPM_ROAD, ROAD, chunk_m=CHUNK)
        # crossings
        for i in range(1, self.nbx):
            for j in range(1, self.nby):
                tex = self.bank.register(
                    tx.intersection, 2 * ROAD_HALF, PPM_ROAD, seed=(self.seed, K_CROSS, i, j)
                )
                start = self.node(i, j) + np.array([-ROAD_HALF, ROAD_HALF, 0.0])
                ground_quad(
                    b, start, np.array([1.0, 0.0, 0.0]), 2 * ROAD_HALF, 2 * ROAD_HALF, tex, PPM_ROAD, ROAD
                )

    def _build_town_edge(self, b: QuadBuilder) -> None:
        """A tall building across each street's end, wide enough to hide what lies behind."""
        half = SETBACK + 12.0
        for axis, idx in self.street_lines():
            pos = (self.xs if axis == 0 else self.ys)[idx]
            lo, hi = (self.ys[0], self.ys[-1]) if axis == 0 else (self.xs[0], self.xs[-1])
            for end, (edge, sgn) in enumerate(((lo, 1.0), (hi, -1.0))):
                n = np.array([0.0, sgn, 0.0]) if axis == 0 else np.array([sgn, 0.0, 0.0])
                u = facade_u(n)
                centre = np.array([pos, edge, 0.0]) if axis == 0 else np.array([edge, pos, 0.0])
                rng = np.random.default_rng([self.seed, K_END, axis, idx, end])
                h = float(rng.uniform(18.0, 28.0))
                tex = self.bank.register(
                    tx.facade, 2 * half, h, PPM_FACADE, seed=(self.seed, K_END, axis, idx, end)
                )
                vertical_quad(
                    b, centre - u * half, u, 2 * half, 0.0, h, tex, PPM_FACADE, BUILDING, chunk_m=CHUNK
                )
                self._casters.append((np.array([*(centre - u * half)[:2], h]), u, 2 * half, h, n, False))

    def occluded(
        self, corners: np.ndarray, cameras: list[np.ndarray], skip_within: float = 10.0
    ) -> np.ndarray:
        """Which quads are hidden behind a block from every camera centre given.

        A quad is hidden when the sight lines to all its corners pass through the same block's
        box (its facade rectangle, up to its lowest wall): sight lines into a block always meet
        a wall, so the quad, convex and inside that box's shadow, cannot be seen. Conservative:
        it never hides anything visible.

        Args:
            corners: (M, 4, 3) world corners.
            cameras: camera centres, (3,) each.
            skip_within: quads nearer than this (metres) are not tested (they rarely hide).

        Returns:
            (M,) bool.
        """
        m = corners.shape[0]
        if m == 0 or not len(self.block_lo):
            return np.zeros(m, bool)
        hidden_all = np.ones(m, bool)
        bc = (self.block_lo[:, :2] + self.block_hi[:, :2]) / 2
        br = np.linalg.norm(self.block_hi[:, :2] - self.block_lo[:, :2], axis=1) / 2
        for cam in cameras:
            c = np.asarray(cam, float)
            d = corners - c
            flat = np.sqrt(d[:, :, 0] ** 2 + d[:, :, 1] ** 2)
            test = np.nonzero((flat.min(axis=1) > skip_within) & hidden_all)[0]
            hidden = np.zeros(m, bool)
            if len(test):
                reach = float(flat[test].max())
                blocks = np.nonzero(np.linalg.norm(bc - c[:2], axis=1) - br < reach)[0]
                if len(blocks):
                    dd = d[test].reshape(-1, 3)  # (P, 3) sight vectors, 4 per quad
                    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                        ix, iy = 1.0 / dd[:, 0], 1.0 / dd[:, 1]
                        lo = self.block_lo[blocks] - c
                        hi = self.block_hi[blocks] - c
                        ax, bx = lo[:, :1] * ix, hi[:, :1] * ix
                        ay, by = lo[:, 1:2] * iy, hi[:, 1:2] * iy
                        t_in = np.maximum(np.minimum(ax, bx), np.minimum(ay, by))
                        t_out = np.minimum(np.maximum(ax, bx), np.maximum(ay, by))
                        dz = dd[:, 2][None, :]
                        t_z = np.where(dz > 0, hi[:, 2:3] / dz, np.where(dz < 0, lo[:, 2:3] / dz, np.inf))
                        t_out = np.minimum(t_out, t_z)
                        hit = (t_in > 0.0) & (t_in <= t_out) & (t_out < 1.0)
                    hidden[test] = hit.reshape(len(blocks), len(test), 4).all(axis=2).any(axis=0)
            hidden_all &= hidden
        return hidden_all

    # ------------------------------------------------------------------ per lap

    def lap_movers(self, lap: int, camera_lanes: set[tuple[int, int, int]]) -> Movers:
        """Cars (parked and driving), cyclists and pedestrians of lap ``lap``.

        Args:
            lap: lap index (a different seed per lap: different cars and people each visit).
            camera_lanes: (axis, index, direction sign) of the lanes the camera drives in this
                lap; no car or cyclist drives there (it would run into the camera).
        """
        rng = np.random.default_rng([self.seed, K_LAP, lap])
        found = _MoverList()
        if self.clutter > 0:
            for axis, idx in self.street_lines():
                for sgn in (1, -1):
                    self._lane_traffic(found, rng, lap, (axis, idx, sgn), camera_lanes)
            for si, side in enumerate(self.sides):
                self._pedestrians(found, rng, lap, si, side)
        return found.movers()

    def _lane_traffic(
        self,
        found: _MoverList,
        rng: np.random.Generator,
        lap: int,
        lane: tuple[int, int, int],
        camera_lanes: set[tuple[int, int, int]],
    ) -> None:
        """Parked cars, then (unless the camera drives there) cars and cyclists of one direction of a street.

        ``lane`` is (axis, index, direction sign) as in :meth:`street_lines`.
        """
        axis, idx, sgn = lane
        pos = (self.xs if axis == 0 else self.ys)[idx]
        lo, hi = (self.ys[0], self.ys[-1]) if axis == 0 else (self.xs[0], self.xs[-1])
        along = np.array([0.0, 1.0, 0.0]) if axis == 0 else np.array([1.0, 0.0, 0.0])
        line_len = float(hi - lo)
        d = along * sgn
        r = right_of(d)
        origin = np.array([pos, lo, 0.0]) if axis == 0 else np.array([lo, pos, 0.0])
        if sgn < 0:
            origin = origin + along * line_len
        self._parked_cars(found, rng, lap, axis, pos, d, r)
        if lane in camera_lanes:
            return
        self._through_traffic(found, rng, lap, origin, d, r, line_len)

    def _parked_cars(
        self,
        found: _MoverList,
        rng: np.random.Generator,
        lap: int,
        axis: int,
        pos: float,
        d: np.ndarray,
        r: np.ndarray,
    ) -> None:
        """Cars parked along the parking strip on the right of direction ``d``, block by block."""
        cross = self.ys if axis == 0 else self.xs
        for seg in range(len(cross) - 1):
            a = cross[seg] + (ROAD_HALF + 6.0 if seg > 0 else 3.0)
            e = cross[seg + 1] - (ROAD_HALF + 6.0 if seg < len(cross) - 2 else 3.0)
            s = a
            while s + 5.0 < e:
                if rng.random() < min(0.9, 0.45 * self.clutter):
                    centre_s = s + 2.8 + rng.uniform(-0.3, 0.3)
                    p = (
                        np.array([pos, centre_s, 0.0]) if axis == 0 else np.array([centre_s, pos, 0.0])
                    ) + r * PARK_LANE
                    k = found.add(p, d, 1.0, 0.0, 0.0)
                    found.halves[k] = self._car(found.quads, k, rng, lap)
                s += 6.0

    def _through_traffic(
        self,
        found: _MoverList,
        rng: np.random.Generator,
        lap: int,
        origin: np.ndarray,
        d: np.ndarray,
        r: np.ndarray,
        line_len: float,
    ) -> None:
        """Cars in the driving lane and cyclists beside the parking strip, along direction ``d``."""
        c = self.clutter
        for _ in range(int(rng.poisson(line_len / 70.0 * c))):
            k = found.add(
                origin + r * DRIVE_LANE,
                d,
                line_len,
                float(rng.uniform(0, line_len)),
                float(rng.uniform(6.0, 11.0)),
            )
            found.halves[k] = self._car(found.quads, k, rng, lap)
        for _ in range(int(rng.poisson(line_len / 200.0 * c))):
            k = found.add(
                origin + r * (ROAD_HALF - PARKING - 0.6),
                d,
                line_len,
                float(rng.uniform(0, line_len)),
                float(rng.uniform(3.5, 6.0)),
            )
            found.halves[k] = self._cyclist(found.quads, k, rng, lap)

    def _pedestrians(
        self, found: _MoverList, rng: np.random.Generator, lap: int, si: int, side: Side
    ) -> None:
        """People walking (or standing) either way along the sidewalk of block side ``si``."""
        for _ in range(int(rng.poisson(side.length / 10.0 * self.clutter))):
            fwd = rng.random() < 0.5
            d = side.u if fwd else -side.u
            start = side.start + side.n * float(rng.uniform(0.7, 2.4))
            if not fwd:
                start = start + side.u * side.length
            speed = 0.0 if rng.random() < 0.2 else float(rng.uniform(0.8, 1.6))
            k = found.add(start, d, side.length, float(rng.uniform(0.5, side.length - 0.5)), speed)
            found.halves[k] = self._person(found.quads, k, rng, (lap, si))

    def _car(self, b: QuadBuilder, k: int, rng: np.random.Generator, lap: int) -> tuple[float, float]:
        L = float(rng.uniform(3.9, 4.8))
        W = float(rng.uniform(1.7, 1.9))
        H = float(rng.uniform(1.4, 1.6))
        colour = tx.CAR_COLOURS[int(rng.integers(len(tx.CAR_COLOURS)))]
        key = (self.seed, K_LAP, lap, 1000 + k)
        plate = tx.random_word(rng, 2, 3) + str(int(rng.integers(100, 999)))
        side_l = self.bank.register(tx.car_side, L, H, PPM_CAR, colour, False, seed=key)
        side_r = self.bank.register(tx.car_side, L, H, PPM_CAR, colour, True, seed=key)
        front = self.bank.register(tx.car_end, W, H, PPM_CAR, colour, True, plate, seed=key)
        back = self.bank.register(tx.car_end, W, H, PPM_CAR, colour, False, plate, seed=key)
        roof = self.bank.register(tx.car_roof, 1.9, W - 0.7, PPM_CAR, colour, seed=key)
        x, y = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
        vertical_quad(b, np.array([L / 2, W / 2, 0]), -x, L, 0.0, H, side_l, PPM_CAR, CAR, obj=k)
        vertical_quad(b, np.array([-L / 2, -W / 2, 0]), x, L, 0.0, H, side_r, PPM_CAR, CAR, obj=k)
        vertical_quad(b, np.array([L / 2, -W / 2, 0]), y, W, 0.0, H, front, PPM_CAR, CAR, obj=k)
        vertical_quad(b, np.array([-L / 2, W / 2, 0]), -y, W, 0.0, H, back, PPM_CAR, CAR, obj=k)
        b.add(np.array([L / 2 - 1.55, -W / 2 + 0.35, H]), -x, y, 1.9, W - 0.7, roof, PPM_CAR, CAR, obj=k)
        return L / 2, W / 2

    def _person(
        self, b: QuadBuilder, k: int, rng: np.random.Generator, key: tuple[int, int]
    ) -> tuple[float, float]:
        h = float(rng.uniform(1.55, 1.9))
        tex = self.bank.register(tx.pedestrian, h, PPM_PED, seed=(self.seed, K_LAP, *key, 5000 + k))
        x, y = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
        vertical_quad(
            b, np.array([0.0, -0.3, 0.0]), y, 0.6, 0.0, h, tex, PPM_PED, PEDESTRIAN, two_sided=True, obj=k
        )
        b.add(
            np.array([0.2, 0.0, h]),
            -x,
            -UP,
            0.4,
            h,
            tex,
            PPM_PED * 0.6 / 0.4,
            PEDESTRIAN,
            two_sided=True,
            obj=k,
            ppm_v=PPM_PED,
        )
        return 0.3, 0.3

    def _cyclist(self, b: QuadBuilder, k: int, rng: np.random.Generator, lap: int) -> tuple[float, float]:
        key = (self.seed, K_LAP, lap, 8000 + k)
        side = self.bank.register(tx.bicyclist, PPM_PED, seed=key)
        front = self.bank.register(tx.pedestrian, 1.75, PPM_PED, seed=key)
        x, y = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
        vertical_quad(
            b, np.array([0.9, 0.0, 0.0]), -x, 1.8, 0.0, 1.75, side, PPM_PED, BICYCLIST, two_sided=True, obj=k
        )
        b.add(
            np.array([0.0, -0.25, 1.75]),
            y,
            -UP,
            0.5,
            1.75,
            front,
            PPM_PED * 0.6 / 0.5,
            BICYCLIST,
            two_sided=True,
            obj=k,
            ppm_v=PPM_PED,
        )
        return 0.9, 0.3

    def lap_decals(self, light: Lighting) -> Decals:
        """Cast shadows of buildings (on the ground and the facades across the street) and props."""
        s = light.sun
        if light.overcast or s[2] <= 0.05:
            return Decals.empty()
        found = _DecalList()
        self._building_shadows(found, light)
        self._prop_shadows(found, light)
        return found.decals()

    def _building_shadows(self, found: _DecalList, light: Lighting) -> None:
        """Shadows of the building fronts turned away from the sun: on the ground and across the street."""
        s = light.sun
        ground_n = np.array([0.0, 0.0, 1.0])
        for caster in self._casters:
            top_left, _, _, _, n, across = caster
            if float(n @ s) >= 0.0:  # facing the sun: its shadow falls behind it, out of sight
                continue
            _wall_shadow(found, light, caster, np.zeros(3), ground_n, on_facade=False)
            if across:
                q0 = top_left - np.array([0, 0, top_left[2]]) + n * 2 * SETBACK
                _wall_shadow(found, light, caster, q0, -n, on_facade=True)

    def _prop_shadows(self, found: _DecalList, light: Lighting) -> None:
        """Ground shadows of trunks, canopies and poles (canopies keep their cut-out shape)."""
        s = light.sun
        ground_n = np.array([0.0, 0.0, 1.0])
        pc = self.prop_casters
        if not len(pc):
            return
        pn = pc.normals()
        facing = np.abs(pn @ s)
        for qi in range(len(pc)):
            if facing[qi] < 0.15:  # nearly edge-on to the sun: a sliver of shadow
                continue
            if _weaker_of_canopy_pair(pc.lit, facing, qi):
                continue
            o = pc.origin[qi]
            oo = o - s * (o[2] / s[2])
            uu = pc.u[qi] - s * (pc.u[qi][2] / s[2])
            vv = pc.v[qi] - s * (pc.v[qi][2] / s[2])
            found.quads._rows.append(
                (oo, uu, vv, tuple(pc.rect[qi]), int(pc.tex[qi]), 0, False, 0, -1, 0, -1)
            )
            found.keep(ground_n, bool(pc.lit[qi] == LIT_FOLIAGE), light.shadow_gain(ground_n))


@dataclass
class _MoverList:
    """The movers of one lap while they are placed: paths, footprints and quads (see :class:`Movers`)."""

    quads: QuadBuilder = field(default_factory=QuadBuilder)
    starts: list[np.ndarray] = field(default_factory=list)
    dirs: list[np.ndarray] = field(default_factory=list)
    lengths: list[float] = field(default_factory=list)
    s0s: list[float] = field(default_factory=list)
    speeds: list[float] = field(default_factory=list)
    halves: list[tuple[float, float]] = field(default_factory=list)

    def add(self, start: np.ndarray, d: np.ndarray, length: float, s0: float, speed: float) -> int:
        """Add an object's path; returns its index (its footprint ``halves[k]`` is set by the caller)."""
        self.starts.append(start)
        self.dirs.append(d)
        self.lengths.append(length)
        self.s0s.append(s0)
        self.speeds.append(speed)
        self.halves.append((0.5, 0.5))
        return len(self.starts) - 1

    def movers(self) -> Movers:
        """The collected movers as arrays."""
        quads = self.quads.build(static=False)
        if not self.starts:
            z = np.zeros((0, 3))
            return Movers(z, z, np.zeros(0), np.zeros(0), np.zeros(0), quads, np.zeros((0, 2)))
        return Movers(
            np.array(self.starts),
            np.array(self.dirs),
            np.array(self.lengths),
            np.array(self.s0s),
            np.array(self.speeds),
            quads,
            np.array(self.halves, float),
        )


@dataclass
class _DecalList:
    """The cast shadows of one lap while they are made (see :class:`Decals`)."""

    quads: QuadBuilder = field(default_factory=QuadBuilder)
    normals: list[np.ndarray] = field(default_factory=list)
    alpha: list[bool] = field(default_factory=list)
    gains: list[np.ndarray] = field(default_factory=list)

    def keep(self, normal: np.ndarray, alpha: bool, gain: np.ndarray) -> None:
        """Record the receiver normal, cut-out flag and gain of the quad just added to ``quads``."""
        self.normals.append(normal)
        self.alpha.append(alpha)
        self.gains.append(gain)

    def decals(self) -> Decals:
        """The collected shadows with their bounding spheres (:meth:`Decals.empty` when none)."""
        quads = self.quads.build(static=False)
        if not len(quads):
            return Decals.empty()
        centre, radius = quads.spheres()
        return Decals(
            quads, np.array(self.normals), np.array(self.gains), np.array(self.alpha), centre, radius
        )


def _along_sun(point: np.ndarray, sun: np.ndarray, q0: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Where the sun ray through ``point`` meets the plane through ``q0`` with normal ``m``."""
    return point - sun * (float((point - q0) @ m) / float(sun @ m))


def _wall_shadow(
    found: _DecalList,
    light: Lighting,
    caster: tuple[np.ndarray, np.ndarray, float, float, np.ndarray, bool],
    q0: np.ndarray,
    m: np.ndarray,
    *,
    on_facade: bool,
) -> None:
    """The shadow of a building front (a ``Town._casters`` entry) on the plane through q0 with normal m."""
    s = light.sun
    top_left, u, w, h, _, _ = caster
    if float(s @ m) <= 1e-3:
        return
    tl = _along_sun(top_left, s, q0, m)
    if on_facade and tl[2] <= 0.0 and _along_sun(top_left + u * w, s, q0, m)[2] <= 0.0:
        return  # the shadow does not reach the facade across the street
    uu = u - s * (float(u @ m) / float(s @ m))
    vv = -UP - s * (float(-UP @ m) / float(s @ m))
    # a whole-quad (opaque) decal: texture id 0 is never sampled for its colour
    found.quads.add(tl, uu, vv, w, h, 0, 1.0, 0)
    found.keep(m, False, light.shadow_gain(m))


def _weaker_of_canopy_pair(lit: np.ndarray, facing: np.ndarray, qi: int) -> bool:
    """Whether quad ``qi`` is the canopy quad of a crossed pair that faces the sun less (no shadow)."""
    if lit[qi] != LIT_FOLIAGE:
        return False
    if qi + 1 < len(lit) and lit[qi + 1] == LIT_FOLIAGE and facing[qi + 1] > facing[qi]:
        return True
    return bool(qi > 0 and lit[qi - 1] == LIT_FOLIAGE and facing[qi - 1] >= facing[qi])


def _sign_back_of_plate(rng: np.random.Generator, size: float, ppm: float) -> np.ndarray:
    """The back of the sign made by ``sign_plate`` with the same seed (same outline, mirrored)."""
    plate = tx.sign_plate(rng, size, ppm)
    return tx.sign_back(rng, size, ppm, shape=plate[..., 3])


def grid_size_for(route_blocks: tuple[int, int]) -> tuple[int, int]:
    """Blocks of the town around a route rectangle of ``route_blocks``: room for detours and an edge."""
    return route_blocks[0] + 4, route_blocks[1] + 4
