"""The camera's drive: laps around a rectangle of blocks, each revisit changed in a known way.

Lap 0 drives clockwise around the route rectangle in the outer part of the lane. Revisit ``k``
(``k >= 1``) cycles through three variants, each at another time of day and with other traffic:

* ``k % 3 == 1``: same direction, closer to the centre line (a different lane offset);
* ``k % 3 == 2``: the opposite direction (counter-clockwise, the other side of the street);
* ``k % 3 == 0``: same direction, a lane offset between the two (variant 3).

Every revisit also makes a detour around one neighbouring block (a different one each time), so
each revisit lap holds new places (queries with no loop) as well as revisited ones. Laps are
separate drives (sessions): the camera starts each one afresh, hours after the previous one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .town import Town

#: lateral offset right of the centre line (metres) for lap 0 and the revisit variants 1, 2, 3
LANE_OFFSETS = (2.6, 1.0, 2.4, 1.8)
BASE_HOURS = (10.0, 17.5, 13.0, 19.0, 8.0, 15.5)


@dataclass(frozen=True)
class Lap:
    """One drive around the route.

    Attributes:
        index: lap number.
        nodes: (K, 2) int grid nodes (street line indices i, j) visited in order, closed (the last
            connects back to the first).
        clockwise: direction around the route rectangle.
        offset: lateral offset of the camera to the right of the street centre line, metres.
        hour: time of day.
        overcast: no direct sun.
        detour: index of the neighbour block side detoured around, or -1.
    """

    index: int
    nodes: np.ndarray
    clockwise: bool
    offset: float
    hour: float
    overcast: bool
    detour: int


def plan_laps(n_laps: int, rect: tuple[int, int, int, int], seed: int) -> list[Lap]:
    """The laps around the rectangle of blocks ``rect = (a, b, w, h)`` (blocks a..a+w-1, b..b+h-1)."""
    a, b, w, h = rect
    rng = np.random.default_rng([seed, 77])
    # clockwise corner loop (seen from above, y north): NW -> NE -> SE -> SW
    ring: list[tuple[int, int]] = []
    for i in range(a, a + w):
        ring.append((i, b + h))
    for j in range(b + h, b, -1):
        ring.append((a + w, j))
    for i in range(a + w, a, -1):
        ring.append((i, b))
    for j in range(b, b + h):
        ring.append((a, j))
    laps: list[Lap] = []
    for k in range(n_laps):
        variant = 0 if k == 0 else (k - 1) % 3 + 1
        clockwise = variant != 2
        nodes = list(ring) if clockwise else [ring[0], *ring[:0:-1]]
        detour = -1
        if k > 0:
            # detour around the outside neighbour of one edge: a different side each revisit
            n_edges = len(nodes)
            side_starts = _side_starts(nodes)
            detour = side_starts[(k - 1) % len(side_starts)]
            p = np.array(nodes[detour])
            q = np.array(nodes[(detour + 1) % n_edges])
            d = q - p
            out = (
                np.array([-d[1], d[0]]) if clockwise else np.array([d[1], -d[0]])
            )  # left of travel if clockwise
            nodes = nodes[: detour + 1] + [tuple(p + out), tuple(q + out)] + nodes[detour + 1 :]
        hour = BASE_HOURS[k % len(BASE_HOURS)] + float(rng.uniform(-0.4, 0.4))
        laps.append(
            Lap(
                index=k,
                nodes=np.array(nodes, dtype=np.int64),
                clockwise=clockwise,
                offset=LANE_OFFSETS[variant],
                hour=hour,
                overcast=(k % 6 == 3),
                detour=detour,
            )
        )
    return laps


def _side_starts(nodes: list[tuple[int, int]]) -> list[int]:
    """Index of the first edge of each straight side of a closed node loop."""
    n = len(nodes)
    out = []
    for e in range(n):
        d_prev = np.subtract(nodes[e], nodes[e - 1])
        d = np.subtract(nodes[(e + 1) % n], nodes[e])
        if not np.array_equal(d_prev, d):
            out.append(e)
    return out


@dataclass(frozen=True)
class Path:
    """A densely sampled closed driving line of one lap.

    Attributes:
        points: (P, 2) float positions (x, y), closed (the last connects to the first).
        s: (P + 1,) cumulative arc length, s[-1] is the loop length.
        start: arc length where the lap starts (middle of the first edge).
    """

    points: np.ndarray
    s: np.ndarray
    start: float

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def sample(self, arc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (n, 2) and headings (n,) radians at arc lengths ``arc`` from the lap start."""
        t = np.mod(np.asarray(arc, float) + self.start, self.length)
        pts = np.vstack([self.points, self.points[:1]])
        k = np.clip(np.searchsorted(self.s, t, side="right") - 1, 0, len(self.points) - 1)
        seg = pts[k + 1] - pts[k]
        seg_len = np.maximum(self.s[k + 1] - self.s[k], 1e-12)
        frac = ((t - self.s[k]) / seg_len)[:, None]
        pos = pts[k] + seg * frac
        heading = np.arctan2(seg[:, 1], seg[:, 0])
        return pos, heading


def lap_path(town: Town, lap: Lap, spacing: float = 0.2) -> Path:
    """The driving line of a lap: node polyline offset to the right, corners rounded."""
    nodes = lap.nodes
    pts = np.array([[town.xs[i], town.ys[j]] for i, j in nodes], float)
    n = len(pts)
    dirs = np.roll(pts, -1, axis=0) - pts
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    rights = np.stack([dirs[:, 1], -dirs[:, 0]], axis=1)
    off = lap.offset
    dense: list[np.ndarray] = []
    # corner k sits at node k, between edge k-1 (incoming) and edge k (outgoing)
    corners = []
    for k in range(n):
        d_in, d_out = dirs[k - 1], dirs[k]
        if np.allclose(d_in, d_out):
            c = pts[k] + rights[k] * off
            corners.append((c, d_in, d_out, 0.0))
            continue
        c = pts[k] + rights[k - 1] * off + rights[k] * off
        cross = d_in[0] * d_out[1] - d_in[1] * d_out[0]
        radius = 4.5 if cross < 0 else 7.5  # right turns tight, left turns wide
        corners.append((c, d_in, d_out, radius))
    for k in range(n):
        c, d_in, d_out, r = corners[k]
        nxt = corners[(k + 1) % n]
        if r > 0:
            # arc from c - d_in * r to c + d_out * r around centre c - d_in * r + d_out * r
            centre = c - d_in * r + d_out * r
            a0 = math.atan2(*(c - d_in * r - centre)[::-1])
            a1 = math.atan2(*(c + d_out * r - centre)[::-1])
            da = (a1 - a0 + math.pi) % (2 * math.pi) - math.pi
            m = max(2, int(abs(da) * r / spacing))
            ang = a0 + da * np.arange(m) / m
            dense.append(centre + r * np.stack([np.cos(ang), np.sin(ang)], axis=1))
            a = c + d_out * r
        else:
            a = c
        e = nxt[0] - nxt[1] * nxt[3]
        seg = e - a
        m = max(1, int(np.linalg.norm(seg) / spacing))
        dense.append(a + seg * (np.arange(m) / m)[:, None])
    points = np.vstack(dense)
    closed = np.vstack([points, points[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    # start in the middle of the first edge (after the first corner's arc)
    first_edge = corners[0][0] + dirs[0] * (corners[0][3])
    second = corners[1 % n][0] - dirs[0] * corners[1 % n][3]
    mid = (first_edge + second) / 2
    start = float(s[int(np.argmin(np.linalg.norm(points - mid, axis=1)))])
    return Path(points, s, start)


def lap_lanes(lap: Lap) -> set[tuple[int, int, int]]:
    """(axis, index, direction sign) of every street lane this lap drives in."""
    out: set[tuple[int, int, int]] = set()
    nodes = lap.nodes
    for k in range(len(nodes)):
        p, q = nodes[k], nodes[(k + 1) % len(nodes)]
        if p[0] == q[0]:  # along y on street x = xs[p0]
            out.add((0, int(p[0]), int(np.sign(q[1] - p[1]))))
        else:
            out.add((1, int(p[1]), int(np.sign(q[0] - p[0]))))
    return out
