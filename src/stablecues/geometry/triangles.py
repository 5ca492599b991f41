"""The triangle check (paper section 3.3): congruent 3D triangles in the two frames.

Matches are taken in rank order (best first). Every three usable matches form a triangle
whose three side lengths are measured in the query frame's camera and in the candidate
frame's camera. Side lengths do not change under a rigid motion, so triangles built from
correct matches agree in both frames, up to measurement noise; triangles with a wrong
match generally do not.

Degenerate triangles are avoided while they are built, a match at a time: a match without a
3D point in either frame, one too close to a vertex already chosen (a side shorter than the
noise can measure), or one that makes the triangle near-collinear is skipped and the next
ranked match takes its place. Each match is used in at most one triangle (matches 1-3 make
triangle 1, 4-6 triangle 2 ... when none is skipped).

Tolerance on each side's difference ``delta = L_query - L_candidate``:

* ``"noise"`` (default): ``|delta| <= k_sigma * sigma_delta``, with ``sigma_delta`` the
  standard deviation of the difference propagated from both endpoints' 3D noise in both
  frames (first order: ``var(L) = sum_p u^T C_p u`` with ``u`` the side's unit vector and
  ``C_p`` the point covariance of :mod:`~.points`). ``k_sigma = 3`` is the usual 3-sigma gate:
  a correct side fails it with probability 0.27 % under Gaussian noise (0.8 % for a
  triangle's three sides).
* ``"relative"`` (the paper, 2 %): ``|delta| <= relative_tolerance * (L_query + L_candidate) / 2``.
  With stereo depth noise of 3-10 % (docs/method.md section 6) it rejects most correct triangles.
* ``"similar"``: similar triangles, for monocular points whose scale is unknown (each frame's
  reconstruction has its own). The triangle's scale ``s = P_query / P_candidate`` (ratio of the
  perimeters) is fitted, and each side must satisfy ``|L_query - s L_candidate| <= k_sigma *
  sqrt(sigma_q**2 + s**2 sigma_c**2)``: the shapes agree. All correct matches share one scale
  (one similarity transform maps the candidate's reconstruction onto the query's), so a triangle
  also agrees only when its ``log s`` is within ``k_sigma`` of its own noise from the median
  ``log s`` of the triangles whose shapes agree.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, InputError
from .points import Points3D

__all__ = ["TriangleConfig", "Triangle", "TriangleCheck", "check_triangles", "side_sigma"]

_TOLERANCES = ("noise", "relative", "similar")


@dataclass(frozen=True)
class TriangleConfig:
    """Settings of the triangle check.

    Attributes:
        n_triangles: T, the number of triangles checked (the paper's user setting).
        tolerance: ``"noise"`` (k-sigma from propagated 3D noise), ``"relative"`` (paper) or
            ``"similar"`` (scale-free shapes with propagated noise, for monocular points).
        k_sigma: gate in standard deviations for the noise tolerance.
        relative_tolerance: allowed relative difference for the relative tolerance (0.02).
        min_angle_deg: smallest interior angle, in both frames; a sliver triangle's sides are
            nearly dependent (one ~ the sum of the other two), and wrong matches along a line
            (an edge, a row of windows) make such slivers.
        min_side_sigma: each side must be at least this many of its own standard deviations
            long in both frames, or its length says nothing (the noise tolerance would pass
            anything). Used in both tolerance modes when sigmas are known.
        min_side: each side must be at least this long, metres (0: no absolute minimum, as a
            scene-scale-free default).
    """

    n_triangles: int = 10
    tolerance: str = "noise"
    k_sigma: float = 3.0
    relative_tolerance: float = 0.02
    min_angle_deg: float = 10.0
    min_side_sigma: float = 3.0
    min_side: float = 0.0

    def __post_init__(self) -> None:
        if self.tolerance not in _TOLERANCES:
            raise ConfigError(
                f"triangle tolerance {self.tolerance!r}: expected one of {', '.join(_TOLERANCES)}"
            )
        if self.n_triangles < 1:
            raise ConfigError(f"n_triangles must be >= 1, got {self.n_triangles}")
        if not (self.k_sigma > 0 and self.relative_tolerance > 0):
            raise ConfigError("k_sigma and relative_tolerance must be positive")
        if not 0 <= self.min_angle_deg < 60:
            raise ConfigError(f"min_angle_deg must be in [0, 60), got {self.min_angle_deg}")


@dataclass(frozen=True)
class Triangle:
    """One checked triangle.

    Attributes:
        matches: positions of its three vertices in the ranked match list.
        sides_query: side lengths (v0v1, v1v2, v2v0) in the query frame, metres.
        sides_candidate: the same sides in the candidate frame, metres.
        allowed: largest allowed ``|difference|`` of each side, metres.
        agree: True when every side's difference is within its allowed difference.
        scale: ``"similar"`` tolerance: the fitted scale candidate -> query (1 otherwise).
        log_scale_sigma: ``"similar"``: standard deviation of ``log(scale)`` (0 otherwise).
    """

    matches: tuple[int, int, int]
    sides_query: tuple[float, float, float]
    sides_candidate: tuple[float, float, float]
    allowed: tuple[float, float, float]
    agree: bool
    scale: float = 1.0
    log_scale_sigma: float = 0.0

    def to_dict(self) -> dict[str, object]:
        return {
            "matches": list(self.matches),
            "sides_query": list(self.sides_query),
            "sides_candidate": list(self.sides_candidate),
            "allowed": list(self.allowed),
            "agree": self.agree,
            "scale": self.scale,
        }


@dataclass(frozen=True)
class TriangleCheck:
    """Outcome of the triangle check.

    Attributes:
        triangles: every checked triangle, in order (at most T).
        n_agree: how many of them agree.
        n_requested: T.
        n_usable: matches with a 3D point in both frames.
        skipped: ``(match position, reason)`` for every usable match that was skipped
            (``"too_close"``, ``"collinear"``).
    """

    triangles: tuple[Triangle, ...]
    n_agree: int
    n_requested: int
    n_usable: int
    skipped: tuple[tuple[int, str], ...]

    @property
    def n_checked(self) -> int:
        return len(self.triangles)


def side_sigma(
    xyz: np.ndarray, sigma_depth: np.ndarray, sigma_lateral: np.ndarray, i: np.ndarray, j: np.ndarray
) -> np.ndarray:
    """Standard deviation of the distances between points ``i`` and ``j`` (vectorised).

    Args:
        xyz: (N, 3) points; sigma_depth, sigma_lateral: (N,) their sigmas (see :mod:`.points`).
        i, j: (M,) index arrays.

    Returns:
        (M,) float64 first-order standard deviation of ``|xyz[i] - xyz[j]|``.
    """
    a = xyz[i].astype(np.float64)
    b = xyz[j].astype(np.float64)
    d = a - b
    length = np.linalg.norm(d, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = d / length[:, None]
        var = np.zeros(len(length))
        for p, idx in ((a, i), (b, j)):
            r = p / p[:, 2:3]
            var += (sigma_depth[idx] ** 2) * np.einsum("ij,ij->i", u, r) ** 2
            var += (sigma_lateral[idx] ** 2) * (u[:, 0] ** 2 + u[:, 1] ** 2)
    return np.sqrt(var)


def _side(
    p: list[float], q: list[float], sp: tuple[float, float], sq: tuple[float, float]
) -> tuple[float, float]:
    """Length and first-order sigma of the side between points p and q."""
    dx, dy, dz = p[0] - q[0], p[1] - q[1], p[2] - q[2]
    length = math.sqrt(dx * dx + dy * dy + dz * dz)
    if length == 0.0:
        return 0.0, math.inf
    ux, uy, uz = dx / length, dy / length, dz / length
    lat = ux * ux + uy * uy
    var = 0.0
    for pt, (sd, sl) in ((p, sp), (q, sq)):
        along = (ux * pt[0] + uy * pt[1]) / pt[2] + uz
        var += sd * sd * along * along + sl * sl * lat
    return length, math.sqrt(var)


def _min_angle_deg(p: list[float], q: list[float], r: list[float]) -> float:
    """Smallest interior angle of triangle pqr in degrees."""
    a = math.dist(q, r)
    b = math.dist(p, r)
    c = math.dist(p, q)
    if min(a, b, c) == 0.0:
        return 0.0
    # angle opposite the shortest side is the smallest
    s = sorted((a, b, c))
    cos_small = (s[1] ** 2 + s[2] ** 2 - s[0] ** 2) / (2.0 * s[1] * s[2])
    return math.degrees(math.acos(max(-1.0, min(1.0, cos_small))))


@dataclass(frozen=True)
class _Vertices:
    """The usable points of one frame as Python lists (fast scalar access in the search loop)."""

    xyz: list[list[float]]
    sigmas: list[tuple[float, float]]  # (sigma_depth, sigma_lateral) per point

    @staticmethod
    def of(points: Points3D, usable: np.ndarray) -> _Vertices:
        sigmas = zip(points.sigma_depth[usable].tolist(), points.sigma_lateral[usable].tolist(), strict=True)
        return _Vertices(points.xyz[usable].tolist(), list(sigmas))

    def side(self, a: int, b: int) -> tuple[float, float]:
        """Length and first-order sigma of the side between points a and b."""
        return _side(self.xyz[a], self.xyz[b], self.sigmas[a], self.sigmas[b])

    def min_angle_deg(self, a: int, b: int, c: int) -> float:
        """Smallest interior angle of the triangle of points a, b, c in degrees."""
        return _min_angle_deg(self.xyz[a], self.xyz[b], self.xyz[c])


def _skip_reason(k: int, current: list[int], q: _Vertices, c: _Vertices, config: TriangleConfig) -> str:
    """Why usable match ``k`` cannot join the triangle being built ("too_close", "collinear"), or ""."""
    for e in current:
        lq, sq = q.side(k, e)
        lc, sc = c.side(k, e)
        if (
            min(lq, lc) <= config.min_side
            or lq < config.min_side_sigma * sq
            or lc < config.min_side_sigma * sc
        ):
            return "too_close"
    if len(current) == 2:
        a, b = current
        if q.min_angle_deg(a, b, k) < config.min_angle_deg or c.min_angle_deg(a, b, k) < config.min_angle_deg:
            return "collinear"
    return ""


def _compare(
    current: list[int], pos: list[int], q: _Vertices, c: _Vertices, config: TriangleConfig
) -> Triangle:
    """The triangle of usable matches ``current`` measured in both frames, its sides compared."""
    pairs = ((current[0], current[1]), (current[1], current[2]), (current[2], current[0]))
    measured = [(q.side(a, b), c.side(a, b)) for a, b in pairs]
    sides_q = [lq for (lq, _), _ in measured]
    sides_c = [lc for _, (lc, _) in measured]
    scale, log_sigma = 1.0, 0.0
    if config.tolerance == "similar":
        pq, pc = sum(sides_q), sum(sides_c)
        scale = pq / pc if pc > 0 else math.inf
        sq_p = math.sqrt(sum(sq * sq for (_, sq), _ in measured))
        sc_p = math.sqrt(sum(sc * sc for _, (_, sc) in measured))
        log_sigma = math.hypot(sq_p / pq, sc_p / pc) if pq > 0 and pc > 0 else math.inf
    allowed: list[float] = []
    agree = math.isfinite(scale)
    for (lq, sq), (lc, sc) in measured:
        if config.tolerance == "noise":
            tol = config.k_sigma * math.sqrt(sq * sq + sc * sc)
        elif config.tolerance == "similar":
            tol = config.k_sigma * math.sqrt(sq * sq + scale * scale * sc * sc)
        else:
            tol = config.relative_tolerance * 0.5 * (lq + lc)
        allowed.append(tol)
        agree = agree and abs(lq - scale * lc) <= tol
    return Triangle(
        matches=(pos[current[0]], pos[current[1]], pos[current[2]]),
        sides_query=(sides_q[0], sides_q[1], sides_q[2]),
        sides_candidate=(sides_c[0], sides_c[1], sides_c[2]),
        allowed=(allowed[0], allowed[1], allowed[2]),
        agree=agree,
        scale=scale,
        log_scale_sigma=log_sigma,
    )


def _common_scale(triangles: list[Triangle], k_sigma: float) -> list[Triangle]:
    """``"similar"``: keep ``agree`` only for triangles whose scale is the shared one (median of
    the scales of the triangles whose shapes agree), within ``k_sigma`` of their noise."""
    logs = [math.log(t.scale) for t in triangles if t.agree and t.scale > 0]
    if not logs:
        return triangles
    centre = float(np.median(logs))
    out = []
    for t in triangles:
        shared = t.agree and abs(math.log(t.scale) - centre) <= k_sigma * t.log_scale_sigma
        out.append(dataclasses.replace(t, agree=shared))
    return out


def check_triangles(
    query: Points3D,
    candidate: Points3D,
    config: TriangleConfig = TriangleConfig(),
    order: np.ndarray | None = None,
) -> TriangleCheck:
    """Check triangles of ranked matches for congruence in the two frames.

    Args:
        query: (M,) 3D points of the query-frame side of the ranked matches, in the query camera.
        candidate: (M,) 3D points of the candidate side of the same matches, same order.
        config: triangle settings.
        order: a permutation of ``0..M-1``, the order in which matches enter triangles (None:
            the order given).

    Returns:
        The checked triangles (positions refer to the ranked match list).
    """
    if len(query) != len(candidate):
        raise InputError(
            f"triangle check: expected equal numbers of points, got {len(query)} and {len(candidate)}"
        )
    valid = query.valid & candidate.valid
    if order is None:
        usable = np.flatnonzero(valid)
    else:
        order = np.asarray(order)
        if order.shape != valid.shape or not np.array_equal(np.sort(order), np.arange(valid.size)):
            raise InputError(f"triangle check: the order must be a permutation of the {valid.size} matches")
        usable = order[valid[order]]
    q = _Vertices.of(query, usable)
    c = _Vertices.of(candidate, usable)
    pos = usable.tolist()

    triangles: list[Triangle] = []
    skipped: list[tuple[int, str]] = []
    current: list[int] = []  # indices into the usable lists
    for k in range(len(pos)):
        if len(triangles) >= config.n_triangles:
            break
        reason = _skip_reason(k, current, q, c, config)
        if reason:
            skipped.append((pos[k], reason))
            continue
        current.append(k)
        if len(current) < 3:
            continue
        triangles.append(_compare(current, pos, q, c, config))
        current = []
    if config.tolerance == "similar":
        triangles = _common_scale(triangles, config.k_sigma)
    return TriangleCheck(
        triangles=tuple(triangles),
        n_agree=sum(t.agree for t in triangles),
        n_requested=config.n_triangles,
        n_usable=int(usable.size),
        skipped=tuple(skipped),
    )
