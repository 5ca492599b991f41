"""Procedural textures of the synthetic town: facades, roads, pavements, trees, signs, cars, people.

Every generator takes a ``numpy.random.Generator`` (seeded per object by the caller, so the same
object always gets the same texture and two objects never share one) and sizes in metres with a
resolution in pixels per metre. Opaque textures are ``(H, W, 3) uint8`` BGR; cut-outs (foliage,
fences, signs, people, car profiles) are ``(H, W, 4) uint8`` BGRA whose alpha is 0 or 255.

The textures are drawn to give ORB plenty of stable corners (window frames, sills, shop-sign
lettering, paving joints, road markings) while staying unique per place (colours, layouts,
lettering, wear and per-window curtains all come from the object's own seed).
"""

from __future__ import annotations

import string
from dataclasses import dataclass

import cv2
import numpy as np

Rng = np.random.Generator

_LETTERS = string.ascii_uppercase
_FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
)

# BGR palettes
WALL_COLOURS = (
    (70, 90, 150),  # red brick
    (95, 120, 165),  # light brick
    (150, 175, 200),  # beige
    (185, 195, 205),  # off-white
    (140, 140, 135),  # grey
    (120, 165, 200),  # ochre
    (150, 150, 110),  # teal grey
    (110, 130, 125),  # olive grey
    (170, 160, 190),  # pink
    (200, 185, 160),  # light blue
    (90, 105, 115),  # dark stone
    (125, 155, 185),  # sand
)
FRAME_COLOURS = ((235, 235, 235), (40, 45, 50), (70, 90, 110), (60, 90, 60), (150, 150, 150), (30, 60, 120))
CLOTH_COLOURS = (
    (40, 40, 160),
    (160, 60, 40),
    (40, 140, 40),
    (30, 30, 30),
    (200, 200, 200),
    (40, 160, 200),
    (120, 50, 120),
    (100, 100, 100),
    (60, 90, 140),
    (20, 60, 90),
    (180, 140, 60),
)
CAR_COLOURS = (
    (30, 30, 30),
    (220, 220, 220),
    (150, 150, 150),
    (40, 40, 170),
    (150, 60, 30),
    (40, 110, 40),
    (30, 150, 210),
    (90, 60, 40),
    (200, 190, 170),
    (60, 60, 100),
)
SKIN_COLOURS = ((140, 170, 220), (100, 140, 190), (70, 100, 150), (50, 70, 110), (150, 180, 230))


def _col(rng: Rng, palette: tuple[tuple[int, int, int], ...], jitter: float = 12.0) -> tuple[int, int, int]:
    base = np.array(palette[int(rng.integers(len(palette)))], dtype=np.float64)
    c = np.clip(base + rng.normal(0.0, jitter, 3), 0, 255)
    return (int(c[0]), int(c[1]), int(c[2]))


def _shade(c: tuple[int, int, int], f: float) -> tuple[int, int, int]:
    return (int(min(255, c[0] * f)), int(min(255, c[1] * f)), int(min(255, c[2] * f)))


def value_noise(rng: Rng, h: int, w: int, cell: float, octaves: int = 3) -> np.ndarray:
    """Smooth multi-octave noise, (h, w) float32 with standard deviation about 1."""
    # octaves are summed at half resolution (they are smooth), then scaled up once
    hh, ww = max(2, (h + 1) // 2), max(2, (w + 1) // 2)
    out = np.zeros((hh, ww), np.float32)
    amp, total = 1.0, 0.0
    for _ in range(octaves):
        gh = max(2, int(h / max(cell, 1.0)) + 2)
        gw = max(2, int(w / max(cell, 1.0)) + 2)
        small = rng.standard_normal((gh, gw)).astype(np.float32)
        out += np.float32(amp) * cv2.resize(small, (ww, hh), interpolation=cv2.INTER_CUBIC)
        total += amp * amp
        amp *= 0.5
        cell /= 2.0
    out *= np.float32(1.0 / np.sqrt(total))
    return cv2.resize(out, (w, h), interpolation=cv2.INTER_LINEAR)


def _add_tone(img: np.ndarray, tone: np.ndarray) -> np.ndarray:
    """Add a (h, w) float brightness field to a colour image, saturating."""
    t = np.ascontiguousarray(tone, dtype=np.float32)
    return cv2.add(img, cv2.cvtColor(t, cv2.COLOR_GRAY2BGR), dtype=cv2.CV_8U)


def random_word(rng: Rng, lo: int = 3, hi: int = 9) -> str:
    n = int(rng.integers(lo, hi + 1))
    return "".join(_LETTERS[int(i)] for i in rng.integers(0, len(_LETTERS), n))


def put_text_box(
    img: np.ndarray,
    text: str,
    x0: int,
    y0: int,
    x1: int,
    y1: int,
    colour: tuple[int, ...],
    font: int = cv2.FONT_HERSHEY_DUPLEX,
    thickness_frac: float = 0.12,
) -> None:
    """Write ``text`` as large as it fits, centred in the box [x0, x1) x [y0, y1) (in place)."""
    bw, bh = x1 - x0, y1 - y0
    if bw < 4 or bh < 4 or not text:
        return
    (tw, th), _ = cv2.getTextSize(text, font, 1.0, 1)
    scale = min(0.9 * bw / max(tw, 1), 0.75 * bh / max(th, 1))
    if scale <= 0.05:
        return
    thick = max(1, int(round(th * scale * thickness_frac)))
    (tw, th), base = cv2.getTextSize(text, font, scale, thick)
    org = (x0 + (bw - tw) // 2, y0 + (bh + th) // 2)
    cv2.putText(img, text, org, font, scale, colour, thick, cv2.LINE_AA)


# --------------------------------------------------------------------------------------- walls


def _wall(rng: Rng, h: int, w: int, ppm: float, colour: tuple[int, int, int], material: str) -> np.ndarray:
    img = np.empty((h, w, 3), np.uint8)
    img[:] = colour
    tone = (
        value_noise(rng, h, w, cell=3.0 * ppm) * 10.0
        + value_noise(rng, h, w, cell=0.3 * ppm, octaves=2) * 4.0
    )
    if material in ("brick", "stone"):
        course = max(3, int(round((0.09 if material == "brick" else 0.32) * ppm)))
        length = max(6, int(round((0.25 if material == "brick" else 0.7) * ppm)))
        ys = np.arange(h, dtype=np.int32)[:, None]
        xs = np.arange(w, dtype=np.int32)[None, :]
        row = ys // course
        shifted = xs + (row % 2) * (length // 2)
        col = shifted // length
        per = rng.normal(0.0, 9.0 if material == "brick" else 6.0, (h // course + 1, w // length + 2))
        tone += per.astype(np.float32)[row, col]
        mortar = ((ys % course) == 0) | ((shifted % length) == 0)
        tone[mortar] += np.float32(25.0 if material == "brick" else -22.0)
    elif material == "panel":
        pw = max(8, int(round(rng.uniform(1.0, 1.6) * ppm)))
        ph = max(8, int(round(rng.uniform(0.8, 1.5) * ppm)))
        ys = np.arange(h, dtype=np.int32)[:, None]
        xs = np.arange(w, dtype=np.int32)[None, :]
        seam = ((xs % pw) == 0) | ((ys % ph) == 0)
        per = rng.normal(0.0, 5.0, (h // ph + 2, w // pw + 2))
        tone += per.astype(np.float32)[ys // ph, xs // pw]
        tone[seam] -= np.float32(30.0)
    return _add_tone(img, tone)


Colour = tuple[int, int, int]


@dataclass(frozen=True)
class _Sheet:
    """A texture drawn in metres: ``ppm`` pixels per metre, ``w`` x ``h`` pixels, row 0 at the top."""

    ppm: float
    w: int
    h: int

    def px(self, m: float) -> int:
        """Metres -> pixels."""
        return int(round(m * self.ppm))

    def row(self, z: float) -> int:
        """Metres above the bottom edge -> texture row."""
        return self.h - self.px(z)


@dataclass(frozen=True)
class _WindowStyle:
    """What every window of one building shares.

    Attributes:
        frame: BGR colour of the frames.
        t: frame thickness, pixels.
        mullion: 0 none, 1 vertical, 2 horizontal, 3 both.
        sill: draw a sill under each window.
        shutters: BGR colour of the shutters, or None for none.
        wall: BGR colour of the wall (sills and ledges are shades of it).
    """

    frame: Colour
    t: int
    mullion: int
    sill: bool
    shutters: Colour | None
    wall: Colour


@dataclass(frozen=True)
class _FloorPlan:
    """Where a facade's floors and window columns lie, in metres.

    Attributes:
        gf: height of the ground floor.
        fh: height of each upper floor.
        n_floors: number of upper floors.
        win_w, win_h: window size.
        spacing: distance between window columns.
        n_cols: number of window columns.
        x_first: centre of the first column from the facade's left edge.
        cornice: a ledge at the foot of each upper floor.
        balcony_floors: upper floors (0: the first) with balconies.
    """

    gf: float
    fh: float
    n_floors: int
    win_w: float
    win_h: float
    spacing: float
    n_cols: int
    x_first: float
    cornice: bool
    balcony_floors: set[int]


def _window(img: np.ndarray, x0: int, y0: int, x1: int, y1: int, rng: Rng, style: _WindowStyle) -> None:
    """Draw one window (shutters, glass, curtains or blinds, frame, mullions, sill) in place."""
    x0, y0 = max(0, x0), max(0, y0)
    x1, y1 = min(img.shape[1], x1), min(img.shape[0], y1)
    if y1 - y0 < 4 or x1 - x0 < 4:
        return
    if style.shutters is not None:
        _shutters(img, x0, y0, x1, y1, style.shutters)
    _glass(img, x0, y0, x1, y1, rng)
    _window_dressing(img, x0, y0, x1, y1, rng)
    _window_frame(img, x0, y0, x1, y1, style)


def _shutters(img: np.ndarray, x0: int, y0: int, x1: int, y1: int, colour: Colour) -> None:
    """Louvred shutters either side of the window [x0, x1) x [y0, y1)."""
    h, w = y1 - y0, x1 - x0
    sw = max(2, w // 2 - 1)
    for sx0 in (x0 - sw - 1, x1 + 1):
        cv2.rectangle(img, (sx0, y0), (sx0 + sw, y1), colour, -1)
        for yy in range(y0 + 2, y1, max(2, h // 10)):
            cv2.line(img, (sx0, yy), (sx0 + sw, yy), _shade(colour, 0.7), 1)


def _glass(img: np.ndarray, x0: int, y0: int, x1: int, y1: int, rng: Rng) -> None:
    """Fill the window with dark glass and a diagonal reflection band, different in every window."""
    h, w = y1 - y0, x1 - x0
    top = np.array(_col(rng, ((70, 60, 50), (90, 80, 60), (60, 55, 55), (110, 100, 85)), 10), np.float32)
    grad = np.linspace(1.15, 0.75, h, dtype=np.float32)[:, None, None]
    glass = np.clip(top[None, None, :] * grad + np.zeros((1, w, 1), np.float32), 0, 255)
    ys, xs = np.mgrid[0:h, 0:w]
    k = rng.uniform(0.3, 1.5)
    off = rng.uniform(-0.5, 1.0) * w
    band = np.abs(xs + k * ys - off) < rng.uniform(0.08, 0.25) * w
    glass[band] = np.clip(glass[band] * 1.6 + 25, 0, 255)
    img[y0:y1, x0:x1] = glass.astype(np.uint8)


def _window_dressing(img: np.ndarray, x0: int, y0: int, x1: int, y1: int, rng: Rng) -> None:
    """Side curtains, a blind pulled down part way, a pot plant, or nothing, behind the glass."""
    h, w = y1 - y0, x1 - x0
    kind = rng.random()
    curtain = _col(rng, CLOTH_COLOURS + ((230, 230, 230),) * 3, 15)
    if kind < 0.3:  # side curtains
        cw = int(w * rng.uniform(0.15, 0.35))
        cv2.rectangle(img, (x0, y0), (x0 + cw, y1), curtain, -1)
        if rng.random() < 0.7:
            cv2.rectangle(img, (x1 - cw, y0), (x1, y1), curtain, -1)
    elif kind < 0.55:  # blind pulled down part way, with slats
        bh = int(h * rng.uniform(0.2, 0.9))
        cv2.rectangle(img, (x0, y0), (x1, y0 + bh), curtain, -1)
        for yy in range(y0 + 3, y0 + bh, 3):
            cv2.line(img, (x0, yy), (x1, yy), _shade(curtain, 0.8), 1)
    elif kind < 0.62:  # a pot plant on the sill inside
        r = max(2, w // 6)
        cx = x0 + int(rng.uniform(0.25, 0.75) * w)
        cv2.circle(img, (cx, y1 - r - 2), r, (40, 110, 50), -1)
        cv2.rectangle(img, (cx - r // 2, y1 - r), (cx + r // 2, y1), (40, 70, 150), -1)


def _window_frame(img: np.ndarray, x0: int, y0: int, x1: int, y1: int, style: _WindowStyle) -> None:
    """The frame, mullions and sill of the window [x0, x1) x [y0, y1)."""
    frame, t = style.frame, style.t
    cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), frame, t)
    if style.mullion in (1, 3):
        cx = (x0 + x1) // 2
        cv2.line(img, (cx, y0), (cx, y1), frame, max(1, t // 2 + 1))
    if style.mullion in (2, 3):
        cy = y0 + (y1 - y0) // 3
        cv2.line(img, (x0, cy), (x1, cy), frame, max(1, t // 2 + 1))
    if style.sill:
        cv2.rectangle(img, (x0 - t - 1, y1), (x1 + t, y1 + max(2, t + 1)), _shade(style.wall, 1.25), -1)
        cv2.line(
            img,
            (x0 - t - 1, y1 + max(2, t + 1) + 1),
            (x1 + t, y1 + max(2, t + 1) + 1),
            _shade(style.wall, 0.55),
            1,
        )


def facade(
    rng: Rng, width_m: float, height_m: float, ppm: float, *, shops: bool = True, side: bool = False
) -> np.ndarray:
    """A building facade, (H, W, 3) uint8 BGR with H = height_m * ppm rows, W = width_m * ppm columns.

    Args:
        rng: the building's own generator.
        width_m, height_m: facade size in metres (row 0 is the roof line).
        ppm: pixels per metre.
        shops: allow shop fronts on the ground floor.
        side: a side or back wall: plainer, fewer windows, no shops.
    """
    sheet = _Sheet(ppm, max(8, int(round(width_m * ppm))), max(8, int(round(height_m * ppm))))
    wall = _col(rng, WALL_COLOURS, 14)
    material = str(rng.choice(["plaster", "brick", "stone", "panel"], p=[0.4, 0.3, 0.15, 0.15]))
    img = _wall(rng, sheet.h, sheet.w, ppm, wall, material)
    style = _window_style(rng, sheet, wall)
    plan = _floor_plan(rng, width_m, height_m, side=side)
    _upper_floors(img, rng, sheet, plan, style, side=side)
    if shops and not side and rng.random() < 0.75:
        _shop_fronts(img, rng, sheet, width_m, plan.gf, style)
    else:
        _residential_ground_floor(img, rng, sheet, width_m, plan, style)
    _plinth(img, sheet, wall)
    if not side and rng.random() < 0.35:
        _posters(img, rng, sheet, width_m)
    if rng.random() < 0.6:
        _drainpipe(img, rng, sheet, width_m)
    _roof_cornice(img, rng, sheet, wall)
    return _weathered(img, rng, sheet)


def _window_style(rng: Rng, sheet: _Sheet, wall: Colour) -> _WindowStyle:
    """Draw a building's window style."""
    frame = _col(rng, FRAME_COLOURS, 8)
    t = max(1, sheet.px(rng.uniform(0.05, 0.1)))
    mullion = int(rng.integers(0, 4))
    sill = bool(rng.random() < 0.8)
    shutters = (
        _col(rng, ((40, 90, 40), (50, 50, 120), (120, 80, 40), (60, 60, 60)), 10)
        if rng.random() < 0.2
        else None
    )
    return _WindowStyle(frame, t, mullion, sill, shutters, wall)


def _floor_plan(rng: Rng, width_m: float, height_m: float, *, side: bool) -> _FloorPlan:
    """Draw a facade's floor heights, window size and columns (side walls: fewer columns)."""
    gf = rng.uniform(3.6, 4.6) if not side else rng.uniform(2.8, 3.2)
    fh = rng.uniform(2.9, 3.4)
    parapet = rng.uniform(0.6, 1.4)
    n_floors = max(0, int((height_m - gf - parapet) / fh))
    win_w = rng.uniform(0.9, 1.5)
    win_h = rng.uniform(1.3, min(1.9, fh - 0.9))
    spacing = win_w + rng.uniform(0.8, 2.0)
    if side:
        spacing *= rng.uniform(1.8, 3.0)
    n_cols = max(1, int((width_m - 1.0) / spacing))
    x_first = (width_m - (n_cols - 1) * spacing) / 2.0
    cornice = rng.random() < 0.5
    balcony_floors: set[int] = (
        set(rng.choice(max(n_floors, 1), size=min(n_floors, int(rng.integers(0, 3))), replace=False).tolist())
        if n_floors and rng.random() < 0.35
        else set()
    )
    return _FloorPlan(gf, fh, n_floors, win_w, win_h, spacing, n_cols, x_first, cornice, balcony_floors)


def _upper_floors(
    img: np.ndarray, rng: Rng, sheet: _Sheet, plan: _FloorPlan, style: _WindowStyle, *, side: bool
) -> None:
    """Ledges, windows (now and then a blind one) and balconies of the floors above the ground floor."""
    px, row = sheet.px, sheet.row
    for f in range(plan.n_floors):
        base = plan.gf + f * plan.fh
        if plan.cornice:
            yb = row(base)
            cv2.rectangle(img, (0, yb - px(0.22)), (sheet.w, yb), _shade(style.wall, 1.18), -1)
            cv2.line(img, (0, yb + 1), (sheet.w, yb + 1), _shade(style.wall, 0.6), 1)
        for c in range(plan.n_cols):
            if side and rng.random() < 0.4:
                continue
            cx = plan.x_first + c * plan.spacing
            x0, x1 = px(cx - plan.win_w / 2), px(cx + plan.win_w / 2)
            y1, y0 = row(base + 0.9), row(base + 0.9 + plan.win_h)
            if rng.random() < 0.03:  # a blind window: a plaque instead
                cv2.rectangle(img, (x0, y0), (x1, y1), _shade(style.wall, 0.85), -1)
                continue
            _window(img, x0, y0, x1, y1, rng, style)
            if f in plan.balcony_floors:
                _balcony(img, sheet, x0, x1, base, style)


def _balcony(img: np.ndarray, sheet: _Sheet, x0: int, x1: int, base: float, style: _WindowStyle) -> None:
    """A railed balcony in front of the window columns [x0, x1) of the floor starting at ``base`` m."""
    px, row = sheet.px, sheet.row
    yb0, yb1 = row(base + 1.0), row(base)
    rail = _shade(style.frame, 0.8)
    cv2.rectangle(img, (x0 - px(0.3), yb0), (x1 + px(0.3), yb1), _shade(style.wall, 0.8), -1)
    for xx in range(x0 - px(0.3), x1 + px(0.3), max(2, px(0.12))):
        cv2.line(img, (xx, yb0), (xx, yb1), rail, 1)
    cv2.line(img, (x0 - px(0.3), yb0), (x1 + px(0.3), yb0), rail, max(1, style.t))


def _shop_fronts(
    img: np.ndarray, rng: Rng, sheet: _Sheet, width_m: float, gf: float, style: _WindowStyle
) -> None:
    """A ground floor of one to three shops side by side."""
    n_units = max(1, min(3, int(width_m / rng.uniform(4.5, 7.0))))
    uw = width_m / n_units
    for u in range(n_units):
        _shop_front(img, rng, sheet, u * uw + 0.3, (u + 1) * uw - 0.3, gf, style)


def _shop_front(
    img: np.ndarray, rng: Rng, sheet: _Sheet, ux0: float, ux1: float, gf: float, style: _WindowStyle
) -> None:
    """One shop between ``ux0`` and ``ux1`` m: display window, door, lettered sign, maybe an awning."""
    row = sheet.row
    sign_bg = _col(rng, CAR_COLOURS + FRAME_COLOURS, 10)
    sy0, sy1 = row(gf - 0.25), row(gf - 0.25 - rng.uniform(0.5, 0.8))
    door_w = rng.uniform(1.0, 1.4)
    door_left = rng.random() < 0.5
    dx0 = ux0 if door_left else ux1 - door_w
    dx1 = dx0 + door_w
    wx0, wx1 = (dx1 + 0.15, ux1) if door_left else (ux0, dx0 - 0.15)
    _shop_window(img, rng, sheet, wx0, wx1, gf, style)
    _shop_door(img, rng, sheet, dx0, dx1)
    _shop_sign(img, rng, sheet, ux0, ux1, sy0, sy1, sign_bg)
    if rng.random() < 0.4:  # striped awning under the sign
        _awning(img, rng, sheet, ux0, ux1, sy1)


def _shop_window(
    img: np.ndarray, rng: Rng, sheet: _Sheet, wx0: float, wx1: float, gf: float, style: _WindowStyle
) -> None:
    """A display window with goods between ``wx0`` and ``wx1`` m."""
    px, row = sheet.px, sheet.row
    ys0, ys1 = row(gf - 0.95), row(0.35)
    cv2.rectangle(img, (px(wx0), ys0), (px(wx1), ys1), (55, 50, 45), -1)
    for _ in range(int(rng.integers(3, 10))):
        gx = rng.uniform(wx0 + 0.1, wx1 - 0.4)
        gy = rng.uniform(0.45, gf - 1.6)
        gw, gh = rng.uniform(0.15, 0.6), rng.uniform(0.2, 0.7)
        cv2.rectangle(img, (px(gx), row(gy + gh)), (px(gx + gw), row(gy)), _col(rng, CLOTH_COLOURS, 30), -1)
    cv2.rectangle(img, (px(wx0), ys0), (px(wx1), ys1), style.frame, style.t + 1)


def _shop_door(img: np.ndarray, rng: Rng, sheet: _Sheet, dx0: float, dx1: float) -> None:
    """A glazed shop door between ``dx0`` and ``dx1`` m, with its handle."""
    px, row = sheet.px, sheet.row
    door = _col(rng, FRAME_COLOURS + ((40, 60, 100),), 10)
    cv2.rectangle(img, (px(dx0), row(2.3)), (px(dx1), row(0.0)), door, -1)
    cv2.rectangle(img, (px(dx0 + 0.12), row(2.1)), (px(dx1 - 0.12), row(1.0)), (70, 60, 55), -1)
    cv2.circle(img, (px(dx1 - 0.2), row(1.05)), max(1, px(0.04)), (160, 180, 190), -1)


def _shop_sign(
    img: np.ndarray, rng: Rng, sheet: _Sheet, ux0: float, ux1: float, sy0: int, sy1: int, bg: Colour
) -> None:
    """The sign band between rows ``sy1`` (top) and ``sy0``, lettered with a random word."""
    px = sheet.px
    fg = (255, 255, 255) if sum(bg) < 380 else (20, 20, 20)
    cv2.rectangle(img, (px(ux0), sy0), (px(ux1), sy1), bg, -1)
    cv2.rectangle(img, (px(ux0), sy0), (px(ux1), sy1), _shade(bg, 0.5), 1)
    font = _FONTS[int(rng.integers(len(_FONTS) - 1))]
    put_text_box(img, random_word(rng, 3, 8), px(ux0) + 2, sy0 + 1, px(ux1) - 2, sy1 - 1, fg, font)


def _awning(img: np.ndarray, rng: Rng, sheet: _Sheet, ux0: float, ux1: float, sy1: int) -> None:
    """A striped awning hanging below the sign whose top is row ``sy1``."""
    px = sheet.px
    a0, a1 = sy1 + 1, sy1 + px(0.5)
    c1, c2 = _col(rng, CLOTH_COLOURS, 10), (235, 235, 235)
    stripe = max(3, px(0.3))
    for k, xx in enumerate(range(px(ux0), px(ux1), stripe)):
        cv2.rectangle(img, (xx, a0), (min(px(ux1), xx + stripe), a1), c1 if k % 2 else c2, -1)
    cv2.line(img, (px(ux0), a1 + 1), (px(ux1), a1 + 1), (40, 40, 40), 1)


def _residential_ground_floor(
    img: np.ndarray, rng: Rng, sheet: _Sheet, width_m: float, plan: _FloorPlan, style: _WindowStyle
) -> None:
    """A front door with its house number, and windows like the floors above (none beside the door)."""
    px, row = sheet.px, sheet.row
    dcx = _front_door(img, rng, sheet, width_m, style.t)
    for c in range(plan.n_cols):
        cx = plan.x_first + c * plan.spacing
        if abs(cx - dcx) < plan.win_w / 2 + 0.9:
            continue
        x0, x1 = px(cx - plan.win_w / 2), px(cx + plan.win_w / 2)
        y1, y0 = row(1.0), row(1.0 + min(plan.win_h, plan.gf - 1.6))
        _window(img, x0, y0, x1, y1, rng, style)


def _front_door(img: np.ndarray, rng: Rng, sheet: _Sheet, width_m: float, t: int) -> float:
    """A panelled front door with a number plate above it; returns its centre in metres."""
    px, row = sheet.px, sheet.row
    door = _col(rng, FRAME_COLOURS + ((40, 60, 120), (30, 90, 30)), 10)
    dcx = rng.uniform(1.5, max(1.6, width_m - 1.5))
    cv2.rectangle(img, (px(dcx - 0.55), row(2.4)), (px(dcx + 0.55), row(0.0)), door, -1)
    for pz in (0.4, 1.3):
        cv2.rectangle(
            img, (px(dcx - 0.4), row(pz + 0.8)), (px(dcx + 0.4), row(pz)), _shade(door, 0.75), max(1, t)
        )
    cv2.rectangle(img, (px(dcx - 0.15), row(2.75)), (px(dcx + 0.15), row(2.55)), (230, 230, 230), -1)
    put_text_box(
        img,
        str(int(rng.integers(1, 200))),
        px(dcx - 0.15),
        row(2.75),
        px(dcx + 0.15),
        row(2.55),
        (20, 20, 20),
        cv2.FONT_HERSHEY_SIMPLEX,
    )
    return dcx


def _plinth(img: np.ndarray, sheet: _Sheet, wall: Colour) -> None:
    """A darker band along the foot of the wall."""
    row = sheet.row
    cv2.rectangle(img, (0, row(0.45)), (sheet.w, sheet.h), _shade(wall, 0.7), -1)
    cv2.line(img, (0, row(0.45)), (sheet.w, row(0.45)), _shade(wall, 0.5), 1)


def _posters(img: np.ndarray, rng: Rng, sheet: _Sheet, width_m: float) -> None:
    """One or two lettered posters on the ground floor."""
    px, row = sheet.px, sheet.row
    for _ in range(int(rng.integers(1, 3))):
        pw_, ph_ = rng.uniform(0.5, 0.9), rng.uniform(0.7, 1.2)
        pxx = rng.uniform(0.2, max(0.3, width_m - pw_ - 0.2))
        pz = rng.uniform(0.6, 1.2)
        bg = _col(rng, CLOTH_COLOURS + ((240, 240, 240),), 20)
        cv2.rectangle(img, (px(pxx), row(pz + ph_)), (px(pxx + pw_), row(pz)), bg, -1)
        fg = (255, 255, 255) if sum(bg) < 380 else (10, 10, 10)
        put_text_box(
            img, random_word(rng, 2, 5), px(pxx), row(pz + ph_), px(pxx + pw_), row(pz + ph_ / 2), fg
        )
        cv2.circle(
            img, (px(pxx + pw_ / 2), row(pz + ph_ / 4)), max(2, px(0.12)), _col(rng, CAR_COLOURS, 20), -1
        )


def _drainpipe(img: np.ndarray, rng: Rng, sheet: _Sheet, width_m: float) -> None:
    """A drainpipe with brackets down one edge of the facade."""
    px = sheet.px
    dx = px(rng.choice([0.25, width_m - 0.25]))
    pipe = _col(rng, ((80, 80, 80), (60, 70, 90), (150, 150, 150)), 8)
    cv2.line(img, (dx, 0), (dx, sheet.h), pipe, max(2, px(0.1)))
    for yy in range(px(1.0), sheet.h, px(2.5)):
        cv2.line(img, (dx - px(0.1), yy), (dx + px(0.1), yy), _shade(pipe, 0.6), 1)


def _roof_cornice(img: np.ndarray, rng: Rng, sheet: _Sheet, wall: Colour) -> None:
    """The roof cornice along the top edge, with dentils under it more often than not."""
    px, w = sheet.px, sheet.w
    top = max(2, px(rng.uniform(0.25, 0.45)))
    cv2.rectangle(img, (0, 0), (w, top), _shade(wall, rng.uniform(0.7, 1.2)), -1)
    if rng.random() < 0.6:
        step = max(3, px(rng.uniform(0.2, 0.35)))
        for xx in range(step // 2, w, step):
            cv2.rectangle(img, (xx, top), (xx + step // 2, top + max(2, step // 2)), _shade(wall, 0.8), -1)
    cv2.line(img, (0, top), (w, top), _shade(wall, 0.5), 1)


def _weathered(img: np.ndarray, rng: Rng, sheet: _Sheet) -> np.ndarray:
    """Weathering: darker towards the ground, and vertical streaks."""
    h, w = sheet.h, sheet.w
    grime = np.linspace(0.0, 1.0, h, dtype=np.float32)[:, None] ** 3 * -18.0
    streaks = value_noise(rng, h, w, cell=max(2.0, 0.4 * sheet.ppm), octaves=1)
    streaks = cv2.resize(cv2.resize(streaks, (w, max(2, h // 12))), (w, h)) * 5.0
    return _add_tone(img, grime + streaks)


# --------------------------------------------------------------------------------------- ground


_WHITE_PAINT = (225, 228, 230)
_YELLOW_PAINT = (60, 190, 225)


def road(
    rng: Rng,
    length_m: float,
    width_m: float,
    ppm: float,
    *,
    parking_m: float = 2.0,
    zebra: tuple[bool, bool] = (True, True),
) -> np.ndarray:
    """A street segment's asphalt, (H, W, 3) uint8: columns along the street, rows across it.

    Row 0 is the left kerb for a driver travelling towards increasing columns; the right half
    carries that direction (right-hand traffic). ``zebra`` puts crossings at the (start, end).
    """
    sheet = _Sheet(ppm, max(8, int(round(length_m * ppm))), max(8, int(round(width_m * ppm))))
    grey = rng.uniform(70, 100)
    img = _asphalt(rng, sheet, grey)
    _patches_and_cracks(img, rng, sheet, length_m, width_m, grey)
    _manholes(img, rng, sheet, length_m, width_m)
    lw = _centre_line(img, rng, sheet)
    _parking_strips(img, sheet, parking_m, lw)
    _zebra_crossings(img, sheet, parking_m, zebra)
    for half in (0, 1):
        if rng.random() < 0.6 and length_m > 16:
            _lane_word(img, rng, sheet, half, length_m, parking_m)
    return img


def _asphalt(rng: Rng, sheet: _Sheet, grey: float) -> np.ndarray:
    """Plain asphalt of brightness ``grey`` with blotchy and fine grain."""
    h, w = sheet.h, sheet.w
    img = np.empty((h, w, 3), np.uint8)
    img[:] = (grey, grey, grey * 1.02)
    blotches = value_noise(rng, h, w, cell=4.0 * sheet.ppm) * 8.0
    tone = blotches + rng.normal(0.0, 7.0, (h, w)).astype(np.float32)
    return _add_tone(img, tone)


def _patches_and_cracks(
    img: np.ndarray, rng: Rng, sheet: _Sheet, length_m: float, width_m: float, grey: float
) -> None:
    """Repair patches (lighter or darker rectangles) and meandering cracks."""
    px = sheet.px
    for _ in range(int(rng.integers(1, 5))):
        x0 = rng.uniform(0, length_m - 2)
        y0 = rng.uniform(0, width_m - 1)
        pw, ph = rng.uniform(0.8, 3.0), rng.uniform(0.6, 2.0)
        d = rng.uniform(-25, 15)
        cv2.rectangle(img, (px(x0), px(y0)), (px(x0 + pw), px(y0 + ph)), (grey + d,) * 3, -1)
    for _ in range(int(rng.integers(2, 7))):
        pts = [np.array([rng.uniform(0, length_m), rng.uniform(0, width_m)])]
        for _ in range(int(rng.integers(3, 8))):
            pts.append(pts[-1] + rng.normal(0, 0.4, 2))
        arr = (np.array(pts) * sheet.ppm).astype(np.int32)
        cv2.polylines(img, [arr], False, (grey * 0.45,) * 3, 1)


def _manholes(img: np.ndarray, rng: Rng, sheet: _Sheet, length_m: float, width_m: float) -> None:
    """Up to two ribbed manhole covers."""
    px = sheet.px
    for _ in range(int(rng.integers(0, 3))):
        c = (px(rng.uniform(1, length_m - 1)), px(rng.uniform(2.5, width_m - 2.5)))
        r = px(0.35)
        cv2.circle(img, c, r, (55, 55, 60), -1)
        cv2.circle(img, c, r, (35, 35, 35), 1)
        for k in range(-r + 3, r - 2, 4):
            cv2.line(img, (c[0] + k, c[1] - r + 4), (c[0] + k, c[1] + r - 4), (80, 80, 85), 1)


def _centre_line(img: np.ndarray, rng: Rng, sheet: _Sheet) -> int:
    """A dashed or solid double centre line, white or yellow; returns the line width in pixels."""
    px, w = sheet.px, sheet.w
    mid = sheet.h // 2
    centre = _YELLOW_PAINT if rng.random() < 0.3 else _WHITE_PAINT
    lw = max(2, px(0.12))
    if rng.random() < 0.5:  # dashed centre line
        dash, gap = px(3.0), px(rng.uniform(3.0, 6.0))
        for x in range(px(1.0), w, dash + gap):
            cv2.rectangle(img, (x, mid - lw // 2), (min(w, x + dash), mid + lw // 2), centre, -1)
    else:  # solid double
        cv2.rectangle(img, (0, mid - lw - 1), (w, mid - 1), centre, -1)
        cv2.rectangle(img, (0, mid + 1), (w, mid + lw + 1), centre, -1)
    return lw


def _parking_strips(img: np.ndarray, sheet: _Sheet, parking_m: float, lw: int) -> None:
    """Parking strips along both kerbs: a thin line and bay ticks."""
    px, w, h = sheet.px, sheet.w, sheet.h
    mid = h // 2
    for yl in (px(parking_m), h - px(parking_m)):
        cv2.line(img, (0, yl), (w, yl), _WHITE_PAINT, max(1, lw // 2))
        for x in range(px(1.0), w, px(6.0)):
            y_out = 0 if yl < mid else h
            cv2.line(img, (x, yl), (x, y_out), _WHITE_PAINT, 1)


def _zebra_crossings(img: np.ndarray, sheet: _Sheet, parking_m: float, zebra: tuple[bool, bool]) -> None:
    """Zebra crossings at the (start, end) where ``zebra`` says, each with the stop line before it."""
    px, w, h = sheet.px, sheet.w, sheet.h
    mid = h // 2
    stripe = max(2, px(0.5))
    for end, on in zip((0, 1), zebra, strict=True):
        if not on:
            continue
        xa = px(0.6) if end == 0 else w - px(3.6)
        xb = xa + px(3.0)
        for y in range(px(parking_m * 0.5), h - px(parking_m * 0.5), 2 * stripe):
            cv2.rectangle(img, (xa, y), (xb, y + stripe - 1), _WHITE_PAINT, -1)
        # stop line for the traffic arriving at this end
        if end == 1:
            cv2.rectangle(img, (xa - px(1.2), mid), (xa - px(0.9), h - px(parking_m)), _WHITE_PAINT, -1)
        else:
            cv2.rectangle(img, (xb + px(0.9), px(parking_m)), (xb + px(1.2), mid), _WHITE_PAINT, -1)


def _lane_word(
    img: np.ndarray, rng: Rng, sheet: _Sheet, half: int, length_m: float, parking_m: float
) -> None:
    """A word painted in one half's lane (0: row 0's side), readable for that lane's driver."""
    px, h = sheet.px, sheet.h
    mid = h // 2
    word = str(rng.choice(["BUS", "SLOW", "STOP", "KEEP", "TAXI", "30", "20", random_word(rng, 3, 4)]))
    tl = rng.uniform(4.0, max(4.5, length_m - 8.0))
    lane0 = px(parking_m) + 2 if half == 0 else mid + 3
    lane1 = mid - 3 if half == 0 else h - px(parking_m) - 2
    # draw upright, then rotate so the top points along the lane's travel direction
    up = np.zeros((px(2.4), lane1 - lane0, 3), np.uint8)
    put_text_box(up, word, 0, 0, up.shape[1], up.shape[0], _WHITE_PAINT, cv2.FONT_HERSHEY_SIMPLEX, 0.15)
    rot = np.rot90(up, k=-1 if half == 1 else 1)
    x0 = px(tl)
    region = img[lane0:lane1, x0 : x0 + rot.shape[1]]
    rr = rot[: region.shape[0], : region.shape[1]]
    m = rr.max(axis=2) > 100
    region[m] = rr[m]


def intersection(rng: Rng, size_m: float, ppm: float) -> np.ndarray:
    """The asphalt square where two streets cross, (H, W, 3) uint8."""
    n = max(8, int(round(size_m * ppm)))
    grey = rng.uniform(70, 100)
    img = np.empty((n, n, 3), np.uint8)
    img[:] = (grey, grey, grey)
    img = _add_tone(
        img, value_noise(rng, n, n, cell=3.0 * ppm) * 8.0 + rng.normal(0, 7.0, (n, n)).astype(np.float32)
    )
    if rng.random() < 0.3:  # yellow box junction
        step = int(1.5 * ppm)
        for k in range(-n, n, step):
            cv2.line(img, (k, 0), (k + n, n), (60, 190, 225), 2)
            cv2.line(img, (k, n), (k + n, 0), (60, 190, 225), 2)
    c = (int(rng.uniform(0.3, 0.7) * n), int(rng.uniform(0.3, 0.7) * n))
    cv2.circle(img, c, int(0.35 * ppm), (50, 50, 55), -1)
    return img


def sidewalk(
    rng: Rng,
    length_m: float,
    width_m: float,
    ppm: float,
    *,
    features: tuple[float, ...] = (),
    kerb_row_top: bool = False,
) -> np.ndarray:
    """Paving slabs along a block side, (H, W, 3) uint8; columns along the side, rows across.

    Args:
        features: positions (metres along the side) of tree pits to draw.
        kerb_row_top: draw the kerb stones along row 0 (else along the last row).
    """
    w = max(8, int(round(length_m * ppm)))
    h = max(8, int(round(width_m * ppm)))

    def px(m: float) -> int:
        return int(round(m * ppm))

    base = _col(
        rng, ((150, 150, 150), (135, 145, 160), (110, 120, 150), (165, 165, 160), (120, 125, 125)), 10
    )
    slab_w = rng.choice([0.3, 0.5, 0.6])
    slab_h = rng.choice([0.3, 0.5, 0.6])
    sw, sh = max(3, px(slab_w)), max(3, px(slab_h))
    ys = np.arange(h, dtype=np.int32)[:, None]
    xs = np.arange(w, dtype=np.int32)[None, :]
    stagger = rng.random() < 0.5
    rowi = ys // sh
    xx = xs + (rowi % 2) * (sw // 2) * int(stagger)
    coli = xx // sw
    per = rng.normal(0, 9.0, (h // sh + 1, w // sw + 2)).astype(np.float32)
    # a few odd, replaced slabs
    odd = rng.random(per.shape) < 0.03
    per[odd] += rng.choice([-35.0, 30.0], size=int(odd.sum())).astype(np.float32)
    tone = (
        per[rowi, coli]
        + value_noise(rng, h, w, cell=2.0 * ppm) * 7.0
        + rng.standard_normal((h, w), dtype=np.float32) * np.float32(4.0)
    )
    joint = ((ys % sh) == 0) | ((xx % sw) == 0)
    tone[joint] -= np.float32(35.0)
    img = np.empty((h, w, 3), np.uint8)
    img[:] = base
    img = _add_tone(img, tone)
    # stains and gum
    for _ in range(int(rng.integers(3, 12))):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        cv2.circle(img, c, int(rng.integers(1, max(2, px(0.15)))), (base[0] * 0.6,) * 3, -1)
    # kerb stones
    kh = max(2, px(0.3))
    k0, k1 = (0, kh) if kerb_row_top else (h - kh, h)
    kerb = _shade(base, 1.2)
    cv2.rectangle(img, (0, k0), (w, k1), kerb, -1)
    for x in range(0, w, px(1.0)):
        cv2.line(img, (x, k0), (x, k1), _shade(base, 0.6), 1)
    cv2.line(
        img, (0, k0 if not kerb_row_top else k1), (w, k0 if not kerb_row_top else k1), _shade(base, 0.5), 1
    )
    # tree pits (soil with a grate) where trees stand
    for f in features:
        cx = px(f)
        cy = px(0.9) if kerb_row_top else h - px(0.9)
        r = px(0.6)
        cv2.rectangle(img, (cx - r, cy - r), (cx + r, cy + r), (40, 55, 70), -1)
        for k in range(-r, r + 1, max(2, px(0.15))):
            cv2.line(img, (cx + k, cy - r), (cx + k, cy + r), (50, 50, 50), 1)
        cv2.rectangle(img, (cx - r, cy - r), (cx + r, cy + r), (70, 70, 70), 1)
    # drains
    for _ in range(int(rng.integers(0, 3))):
        cx = px(rng.uniform(0.5, length_m - 0.5))
        cy = (k1 + px(0.2)) if kerb_row_top else (k0 - px(0.4))
        cv2.rectangle(img, (cx - px(0.25), cy), (cx + px(0.25), cy + px(0.2)), (40, 40, 40), -1)
    return img


def gravel(rng: Rng, width_m: float, height_m: float, ppm: float) -> np.ndarray:
    """Courtyard ground (gravel with stones), (H, W, 3) uint8."""
    w = max(8, int(round(width_m * ppm)))
    h = max(8, int(round(height_m * ppm)))
    img = np.empty((h, w, 3), np.uint8)
    img[:] = _col(rng, ((120, 140, 150), (100, 115, 125)), 8)
    img = _add_tone(
        img, rng.normal(0, 14.0, (h, w)).astype(np.float32) + value_noise(rng, h, w, 2.0 * ppm) * 10
    )
    for _ in range(int(w * h / 150)):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        cv2.circle(img, c, int(rng.integers(1, 3)), (int(rng.integers(60, 200)),) * 3, -1)
    return img


# --------------------------------------------------------------------------------------- vegetation


def foliage(rng: Rng, width_m: float, height_m: float, ppm: float) -> np.ndarray:
    """A tree canopy cut-out, (H, W, 4) uint8 BGRA (alpha 0 or 255)."""
    w = max(8, int(round(width_m * ppm)))
    h = max(8, int(round(height_m * ppm)))
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    d = ((xs - w / 2) / (w / 2)) ** 2 + ((ys - h * 0.52) / (h * 0.5)) ** 2
    edge = (
        value_noise(rng, h, w, cell=0.8 * ppm) * 0.25
        + value_noise(rng, h, w, cell=0.25 * ppm, octaves=1) * 0.12
    )
    alpha = (d + edge) < 0.85
    base = np.array(
        _col(rng, ((40, 110, 60), (30, 90, 50), (50, 120, 80), (30, 100, 90), (35, 80, 40)), 12), np.float32
    )
    light = value_noise(rng, h, w, cell=1.0 * ppm) * 18.0 + (1.0 - ys / h) * 25.0 - 10.0
    img = np.clip(base[None, None, :] + light[..., None], 0, 255).astype(np.uint8)
    # leaf clusters: many small light/dark blobs give FAST corners
    n = int(w * h / 40)
    cx = rng.integers(0, w, n)
    cy = rng.integers(0, h, n)
    rr = rng.integers(1, max(2, int(0.12 * ppm)), n)
    shades = rng.uniform(0.55, 1.45, n)
    colours = np.clip(base[None, :] * shades[:, None], 0, 255).astype(int).tolist()
    for x, y, r, c in zip(cx.tolist(), cy.tolist(), rr.tolist(), colours, strict=True):
        cv2.circle(img, (x, y), r, c, -1)
    # a few branches showing through
    for _ in range(int(rng.integers(2, 6))):
        x0 = w // 2 + int(rng.normal(0, w * 0.05))
        x1, y1 = int(rng.uniform(0.15, 0.85) * w), int(rng.uniform(0.2, 0.7) * h)
        cv2.line(img, (x0, h - 1), (x1, y1), (40, 55, 70), max(1, int(0.05 * ppm)))
    out = np.dstack([img, np.where(alpha, 255, 0).astype(np.uint8)])
    return out


def bark(rng: Rng, width_m: float, height_m: float, ppm: float) -> np.ndarray:
    """A tree trunk, (H, W, 3) uint8 with vertical furrows and knots."""
    w = max(4, int(round(width_m * ppm)))
    h = max(8, int(round(height_m * ppm)))
    base = np.array(_col(rng, ((50, 70, 90), (60, 75, 85), (70, 85, 95)), 8), np.float32)
    streak = cv2.resize(
        rng.standard_normal((max(2, h // 12), w)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC
    )
    tone = streak * 18.0 + rng.normal(0, 6.0, (h, w)).astype(np.float32)
    img = np.clip(base[None, None, :] + tone[..., None], 0, 255).astype(np.uint8)
    for _ in range(int(rng.integers(1, 4))):
        c = (int(rng.integers(1, max(2, w - 1))), int(rng.integers(0, h)))
        cv2.ellipse(img, c, (max(1, w // 5), max(2, w // 3)), 0, 0, 360, (30, 40, 50), -1)
    # shade the sides so the trunk looks round
    xs = np.linspace(-1, 1, w, dtype=np.float32)
    img = np.clip(img.astype(np.float32) * (1.0 - 0.35 * xs**2)[None, :, None], 0, 255).astype(np.uint8)
    return img


# --------------------------------------------------------------------------------------- street furniture


def metal(rng: Rng, width_m: float, height_m: float, ppm: float) -> np.ndarray:
    """A painted pole, (H, W, 3) uint8, with a base band and the odd sticker."""
    w = max(3, int(round(width_m * ppm)))
    h = max(8, int(round(height_m * ppm)))
    c = _col(rng, ((70, 75, 80), (60, 90, 60), (40, 40, 40), (140, 140, 140)), 8)
    img = np.empty((h, w, 3), np.uint8)
    img[:] = c
    xs = np.linspace(-1, 1, w, dtype=np.float32)
    img = np.clip(
        img.astype(np.float32) * (1.0 - 0.4 * xs**2 + 0.15 * (xs < -0.3))[None, :, None], 0, 255
    ).astype(np.uint8)
    band = int(round(0.5 * ppm))
    img[h - band :] = _shade(c, 0.6)
    for _ in range(int(rng.integers(0, 3))):
        y = int(rng.integers(int(0.8 * ppm), max(int(0.9 * ppm), int(2.0 * ppm))))
        img[max(0, h - y - 6) : h - y] = _col(rng, CLOTH_COLOURS, 30)
    return img


def lamp_head(rng: Rng, length_m: float, height_m: float, ppm: float) -> np.ndarray:
    """A street-lamp arm and head seen from the side, (H, W, 4) BGRA; column 0 at the pole."""
    w = max(8, int(round(length_m * ppm)))
    h = max(4, int(round(height_m * ppm)))
    img = np.zeros((h, w, 4), np.uint8)
    c = (60, 65, 70, 255)
    cv2.line(img, (0, h // 3), (w - 1, h // 4), c, max(2, int(0.06 * ppm)))
    hx = int(w * 0.65)
    cv2.rectangle(img, (hx, h // 5), (w - 1, int(h * 0.7)), c, -1)
    cv2.rectangle(img, (hx + 2, int(h * 0.55)), (w - 3, int(h * 0.7)), (200, 235, 245, 255), -1)
    return img


def sign_plate(rng: Rng, size_m: float, ppm: float) -> np.ndarray:
    """The face of a traffic sign, (H, W, 4) uint8 BGRA; alpha cuts its shape."""
    n = max(16, int(round(size_m * ppm)))
    img = np.zeros((n, n, 4), np.uint8)
    kind = int(rng.integers(6))
    red, white, blue, black = (30, 30, 200, 255), (240, 240, 240, 255), (160, 80, 20, 255), (20, 20, 20, 255)
    c = (n // 2, n // 2)
    r = n // 2 - 1
    if kind == 0:  # speed limit
        cv2.circle(img, c, r, red, -1)
        cv2.circle(img, c, int(r * 0.78), white, -1)
        put_text_box(
            img,
            str(int(rng.choice([20, 30, 40, 50, 60]))),
            c[0] - r // 2,
            c[1] - r // 2,
            c[0] + r // 2,
            c[1] + r // 2,
            black,
            cv2.FONT_HERSHEY_DUPLEX,
            0.14,
        )
    elif kind == 1:  # no entry
        cv2.circle(img, c, r, red, -1)
        cv2.rectangle(
            img, (c[0] - int(r * 0.7), c[1] - r // 6), (c[0] + int(r * 0.7), c[1] + r // 6), white, -1
        )
    elif kind == 2:  # warning triangle with a glyph
        pts = np.array([[c[0], 1], [n - 2, n - 4], [1, n - 4]], np.int32)
        cv2.fillConvexPoly(img, pts, red)
        inner = ((pts - c) * 0.7 + c + [0, n // 20]).astype(np.int32)
        cv2.fillConvexPoly(img, inner, white)
        put_text_box(
            img,
            str(rng.choice(list("!?XYZ"))),
            c[0] - r // 3,
            c[1] - r // 6,
            c[0] + r // 3,
            c[1] + r // 2,
            black,
            cv2.FONT_HERSHEY_SIMPLEX,
            0.2,
        )
    elif kind == 3:  # parking
        cv2.rectangle(img, (1, 1), (n - 2, n - 2), blue, -1)
        cv2.rectangle(img, (3, 3), (n - 4, n - 4), white, 1)
        put_text_box(img, "P", 4, 4, n - 4, n - 4, white, cv2.FONT_HERSHEY_DUPLEX, 0.2)
    elif kind == 4:  # one way arrow
        cv2.rectangle(img, (1, n // 4), (n - 2, 3 * n // 4), blue, -1)
        cv2.arrowedLine(img, (n // 8, n // 2), (7 * n // 8, n // 2), white, max(2, n // 10), tipLength=0.4)
    else:  # give way: inverted triangle
        pts = np.array([[1, 3], [n - 2, 3], [c[0], n - 2]], np.int32)
        cv2.fillConvexPoly(img, pts, red)
        inner = ((pts - c) * 0.65 + c - [0, n // 20]).astype(np.int32)
        cv2.fillConvexPoly(img, inner, white)
    return img


def street_name(rng: Rng, width_m: float, height_m: float, ppm: float) -> np.ndarray:
    """A street-name plate with lettering, (H, W, 3) uint8."""
    w, h = max(16, int(round(width_m * ppm))), max(8, int(round(height_m * ppm)))
    bg = _col(rng, ((120, 60, 20), (40, 100, 30), (230, 230, 230), (30, 30, 30)), 5)
    fg = (20, 20, 20) if sum(bg) > 500 else (240, 240, 240)
    img = np.empty((h, w, 3), np.uint8)
    img[:] = bg
    cv2.rectangle(img, (1, 1), (w - 2, h - 2), fg, 1)
    name = random_word(rng, 4, 8) + " " + str(rng.choice(["ST", "RD", "AV", "PL", "LN"]))
    put_text_box(img, name, 3, 2, w - 3, h - 2, fg, cv2.FONT_HERSHEY_SIMPLEX, 0.12)
    return img


def sign_back(rng: Rng, size_m: float, ppm: float, shape: np.ndarray | None = None) -> np.ndarray:
    """The plain grey back of a sign, (H, W, 4) BGRA; ``shape`` (an alpha mask) is mirrored."""
    n = max(16, int(round(size_m * ppm)))
    img = np.zeros((n, n, 4), np.uint8)
    img[..., :3] = (150, 150, 145)
    img[..., 3] = 255
    if shape is not None:
        img[..., 3] = cv2.resize(shape[:, ::-1], (n, n), interpolation=cv2.INTER_NEAREST)
    cv2.rectangle(img, (n // 2 - n // 12, n // 5), (n // 2 + n // 12, 4 * n // 5), (110, 110, 110, 255), -1)
    img[..., 3] = np.where(img[..., 3] > 127, 255, 0).astype(np.uint8) if shape is not None else 255
    return img


def traffic_light(rng: Rng, width_m: float, height_m: float, ppm: float, lit: int) -> np.ndarray:
    """A traffic-light housing, (H, W, 3) uint8, with lamp ``lit`` (0 red, 1 amber, 2 green) on."""
    w, h = max(6, int(round(width_m * ppm))), max(12, int(round(height_m * ppm)))
    img = np.empty((h, w, 3), np.uint8)
    img[:] = (35, 35, 35)
    cols = ((40, 40, 230), (40, 180, 240), (120, 220, 60))
    for k in range(3):
        c = (w // 2, int((k + 0.5) * h / 3))
        r = int(min(w, h / 3) * 0.35)
        cv2.circle(img, c, r + 1, (15, 15, 15), -1)
        colour = cols[k] if k == lit else _shade(cols[k], 0.25)
        cv2.circle(img, c, r, colour, -1)
    cv2.rectangle(img, (0, 0), (w - 1, h - 1), (60, 60, 60), 1)
    return img


def fence(rng: Rng, length_m: float, height_m: float, ppm: float) -> np.ndarray:
    """A fence or railing cut-out, (H, W, 4) uint8 BGRA."""
    w, h = max(8, int(round(length_m * ppm))), max(8, int(round(height_m * ppm)))
    img = np.zeros((h, w, 4), np.uint8)
    kind = int(rng.integers(3))
    if kind == 0:  # wooden pickets
        wood = _col(rng, ((90, 130, 170), (220, 225, 230), (60, 90, 120), (80, 120, 90)), 10)
        pw = max(3, int(round(0.09 * ppm)))
        gap = max(2, int(round(rng.uniform(0.04, 0.08) * ppm)))
        for x in range(0, w, pw + gap):
            top = int(round(rng.uniform(0.0, 0.05) * ppm))
            pts = np.array(
                [[x, top + pw], [x + pw // 2, top], [x + pw - 1, top + pw], [x + pw - 1, h - 1], [x, h - 1]],
                np.int32,
            )
            cv2.fillPoly(img, [pts], (*_shade(wood, rng.uniform(0.85, 1.1)), 255))
            cv2.line(img, (x + pw - 1, top + pw), (x + pw - 1, h - 1), (*_shade(wood, 0.6), 255), 1)
        for yr in (0.3, 0.75):
            y = int(yr * h)
            cv2.rectangle(img, (0, y), (w, y + max(2, pw // 2)), (*_shade(wood, 0.75), 255), -1)
    elif kind == 1:  # metal railing
        c = (*_col(rng, ((30, 30, 30), (40, 70, 40), (90, 90, 90)), 6), 255)
        step = max(4, int(round(0.12 * ppm)))
        for x in range(0, w, step):
            cv2.line(img, (x, int(0.05 * h)), (x, h - 1), c, max(1, int(0.025 * ppm)))
            cv2.circle(img, (x, int(0.05 * h)), max(1, int(0.03 * ppm)), c, -1)
        for yr in (0.1, 0.9):
            cv2.line(img, (0, int(yr * h)), (w, int(yr * h)), c, max(2, int(0.04 * ppm)))
        for x in range(0, w, int(2.0 * ppm)):
            cv2.rectangle(img, (x, 0), (x + max(2, int(0.08 * ppm)), h - 1), c, -1)
    else:  # low brick wall with a coping
        colour = _col(rng, WALL_COLOURS, 10)
        wall = _wall(rng, h, w, ppm, colour, "brick")
        img[..., :3] = wall
        img[..., 3] = 255
        cv2.rectangle(img, (0, 0), (w, max(2, int(0.1 * ppm))), (*_shade(colour, 1.3), 255), -1)
    return img


# --------------------------------------------------------------------------------------- vehicles and people


def car_side(
    rng: Rng, length_m: float, height_m: float, ppm: float, colour: tuple[int, int, int], flip: bool
) -> np.ndarray:
    """A car's side profile, (H, W, 4) BGRA, front at column 0 (mirrored when ``flip``)."""
    w, h = max(16, int(round(length_m * ppm))), max(8, int(round(height_m * ppm)))

    def px(m: float) -> int:
        return int(round(m * ppm))

    img = np.zeros((h, w, 4), np.uint8)
    body = (*colour, 255)
    belt = h - px(0.85)
    cab_front, cab_back = px(rng.uniform(1.1, 1.5)), w - px(rng.uniform(0.4, 0.9))
    cabin = np.array(
        [[cab_front, belt], [cab_front + px(0.55), 0], [cab_back - px(0.35), 0], [cab_back, belt]], np.int32
    )
    cv2.fillConvexPoly(img, cabin, body)
    cv2.rectangle(img, (0, belt), (w - 1, h - px(0.18)), body, -1)
    glass = np.array(
        [
            [cab_front + px(0.12), belt - 1],
            [cab_front + px(0.6), px(0.08)],
            [cab_back - px(0.4), px(0.08)],
            [cab_back - px(0.1), belt - 1],
        ],
        np.int32,
    )
    cv2.fillConvexPoly(img, glass, (70, 55, 45, 255))
    pillar = (cab_front + cab_back) // 2
    cv2.line(img, (pillar, px(0.05)), (pillar, belt), body, max(2, px(0.08)))
    cv2.line(img, (pillar, belt + 2), (pillar, h - px(0.3)), (*_shade(colour, 0.5), 255), 1)
    cv2.line(img, (0, belt + px(0.1)), (w, belt + px(0.1)), (*_shade(colour, 0.7), 255), 1)
    for hx in (pillar - px(0.35), pillar + px(0.5)):
        cv2.rectangle(
            img, (hx, belt + px(0.15)), (hx + px(0.2), belt + px(0.2)), (*_shade(colour, 0.5), 255), -1
        )
    r = px(0.33)
    for wx in (px(0.85), w - px(0.85)):
        cv2.circle(img, (wx, h - r - 1), r + 2, (*_shade(colour, 0.4), 255), -1)
        cv2.circle(img, (wx, h - r - 1), r, (25, 25, 25, 255), -1)
        cv2.circle(img, (wx, h - r - 1), r // 2, (170, 170, 170, 255), -1)
        for a in range(0, 360, 72):
            t = np.deg2rad(a)
            cv2.line(
                img,
                (wx, h - r - 1),
                (int(wx + np.cos(t) * r / 2), int(h - r - 1 + np.sin(t) * r / 2)),
                (90, 90, 90, 255),
                1,
            )
    cv2.rectangle(img, (0, belt + px(0.05)), (px(0.12), belt + px(0.25)), (200, 230, 240, 255), -1)
    cv2.rectangle(img, (w - px(0.1), belt + px(0.05)), (w - 1, belt + px(0.25)), (30, 30, 200, 255), -1)
    return np.ascontiguousarray(img[:, ::-1]) if flip else img


def car_end(
    rng: Rng,
    width_m: float,
    height_m: float,
    ppm: float,
    colour: tuple[int, int, int],
    front: bool,
    plate: str,
) -> np.ndarray:
    """A car's front or back, (H, W, 4) BGRA."""
    w, h = max(12, int(round(width_m * ppm))), max(8, int(round(height_m * ppm)))

    def px(m: float) -> int:
        return int(round(m * ppm))

    img = np.zeros((h, w, 4), np.uint8)
    body = (*colour, 255)
    belt = h - px(0.85)
    inset = px(0.2)
    cv2.fillConvexPoly(
        img,
        np.array(
            [[inset, belt], [inset + px(0.15), 0], [w - 1 - inset - px(0.15), 0], [w - 1 - inset, belt]],
            np.int32,
        ),
        body,
    )
    cv2.rectangle(img, (0, belt), (w - 1, h - px(0.15)), body, -1)
    cv2.fillConvexPoly(
        img,
        np.array(
            [
                [inset + px(0.08), belt - 1],
                [inset + px(0.2), px(0.08)],
                [w - inset - px(0.2), px(0.08)],
                [w - inset - px(0.08), belt - 1],
            ],
            np.int32,
        ),
        (70, 55, 45, 255),
    )
    lamp = (200, 235, 245, 255) if front else (30, 30, 190, 255)
    ly = belt + px(0.12)
    cv2.rectangle(img, (px(0.1), ly), (px(0.45), ly + px(0.15)), lamp, -1)
    cv2.rectangle(img, (w - px(0.45), ly), (w - px(0.1), ly + px(0.15)), lamp, -1)
    if front:
        cv2.rectangle(img, (px(0.6), ly), (w - px(0.6), ly + px(0.22)), (30, 30, 30, 255), -1)
        for x in range(px(0.62), w - px(0.6), 3):
            cv2.line(img, (x, ly), (x, ly + px(0.22)), (80, 80, 80, 255), 1)
    pw, ph = px(0.52), px(0.12)
    px0, py0 = (w - pw) // 2, h - px(0.45)
    cv2.rectangle(img, (px0, py0), (px0 + pw, py0 + ph), (235, 235, 235, 255), -1)
    put_text_box(
        img, plate, px0 + 1, py0, px0 + pw - 1, py0 + ph, (20, 20, 20, 255), cv2.FONT_HERSHEY_SIMPLEX, 0.15
    )
    cv2.rectangle(img, (0, h - px(0.15)), (w - 1, h - 1), (25, 25, 25, 255), -1)
    for wx in (px(0.1), w - px(0.35)):
        cv2.rectangle(img, (wx, h - px(0.3)), (wx + px(0.25), h - 1), (25, 25, 25, 255), -1)
    return img


def car_roof(
    rng: Rng, length_m: float, width_m: float, ppm: float, colour: tuple[int, int, int]
) -> np.ndarray:
    """A car's roof seen from above, (H, W, 3) uint8: columns along the car, front at column 0."""
    w, h = max(8, int(round(length_m * ppm))), max(8, int(round(width_m * ppm)))
    img = np.empty((h, w, 3), np.uint8)
    img[:] = _shade(colour, 1.1)
    cv2.rectangle(img, (0, 2), (max(2, w // 6), h - 3), (70, 55, 45), -1)
    cv2.rectangle(img, (w - max(2, w // 8), 2), (w - 1, h - 3), (70, 55, 45), -1)
    return img


def pedestrian(rng: Rng, height_m: float, ppm: float) -> np.ndarray:
    """A person cut-out seen from the front, (H, W, 4) uint8 BGRA, about 0.6 m wide."""
    h = max(16, int(round(height_m * ppm)))
    w = max(8, int(round(0.6 * ppm)))
    img = np.zeros((h, w, 4), np.uint8)
    skin = (*_col(rng, SKIN_COLOURS, 8), 255)
    hair = (*_col(rng, ((20, 20, 20), (30, 50, 90), (40, 90, 150), (180, 180, 180)), 6), 255)
    shirt = (*_col(rng, CLOTH_COLOURS, 20), 255)
    trousers = (*_col(rng, CLOTH_COLOURS, 20), 255)
    cx = w // 2
    head_r = max(2, int(0.11 * ppm))
    head_c = (cx, head_r + 1)
    cv2.circle(img, head_c, head_r, skin, -1)
    cv2.ellipse(img, (cx, head_r), (head_r, max(1, head_r // 2 + 1)), 0, 180, 360, hair, -1)
    neck = 2 * head_r + 1
    torso_b = int(h * 0.55)
    sw = int(0.2 * ppm)
    cv2.fillConvexPoly(
        img,
        np.array(
            [
                [cx - sw, neck + 2],
                [cx + sw, neck + 2],
                [cx + int(sw * 0.8), torso_b],
                [cx - int(sw * 0.8), torso_b],
            ],
            np.int32,
        ),
        shirt,
    )
    arm = max(2, int(0.06 * ppm))
    swing = int(rng.uniform(-0.08, 0.08) * ppm)
    cv2.line(img, (cx - sw, neck + 4), (cx - sw - 1 + swing, int(h * 0.52)), shirt, arm)
    cv2.line(img, (cx + sw, neck + 4), (cx + sw + 1 - swing, int(h * 0.52)), shirt, arm)
    cv2.circle(img, (cx - sw + swing, int(h * 0.53)), max(1, arm // 2 + 1), skin, -1)
    cv2.circle(img, (cx + sw - swing, int(h * 0.53)), max(1, arm // 2 + 1), skin, -1)
    leg = max(2, int(0.09 * ppm))
    stride = int(rng.uniform(0.0, 0.12) * ppm)
    cv2.line(img, (cx - leg // 2 - 1, torso_b), (cx - leg // 2 - 1 - stride, h - 3), trousers, leg)
    cv2.line(img, (cx + leg // 2 + 1, torso_b), (cx + leg // 2 + 1 + stride, h - 3), trousers, leg)
    cv2.rectangle(img, (cx - leg - stride - 2, h - 4), (cx - stride, h - 1), (20, 20, 20, 255), -1)
    cv2.rectangle(img, (cx + stride, h - 4), (cx + leg + stride + 2, h - 1), (20, 20, 20, 255), -1)
    if rng.random() < 0.4:  # a bag
        cv2.rectangle(
            img,
            (cx + sw - 2, int(h * 0.45)),
            (min(w - 1, cx + sw + int(0.1 * ppm)), int(h * 0.6)),
            (*_col(rng, CLOTH_COLOURS, 20), 255),
            -1,
        )
    img[..., 3] = np.where(img[..., 3] > 0, 255, 0).astype(np.uint8)
    return img


def bicyclist(rng: Rng, ppm: float) -> np.ndarray:
    """A cyclist seen from the side, (H, W, 4) BGRA, 1.8 m long, 1.75 m tall; front at column 0."""
    w, h = max(16, int(round(1.8 * ppm))), max(16, int(round(1.75 * ppm)))
    img = np.zeros((h, w, 4), np.uint8)
    frame_c = (*_col(rng, CAR_COLOURS, 20), 255)
    r = int(0.34 * ppm)
    wy = h - r - 1
    wf, wb = (r + 2, wy), (w - r - 3, wy)
    for c in (wf, wb):
        cv2.circle(img, c, r, (25, 25, 25, 255), max(2, int(0.04 * ppm)))
        for deg in range(0, 180, 30):
            t = np.deg2rad(deg)
            d = (int(np.cos(t) * r), int(np.sin(t) * r))
            cv2.line(img, (c[0] - d[0], c[1] - d[1]), (c[0] + d[0], c[1] + d[1]), (120, 120, 120, 255), 1)
    seat = (int(w * 0.62), int(h - 2.4 * r))
    bar = (int(w * 0.3), int(h - 2.6 * r))
    crank = (w // 2, wy)
    for p0, p1 in ((wf, bar), (bar, crank), (crank, wb), (wb, seat), (seat, crank), (bar, seat)):
        cv2.line(img, p0, p1, frame_c, max(2, int(0.04 * ppm)))
    shirt = (*_col(rng, CLOTH_COLOURS, 20), 255)
    skin = (*_col(rng, SKIN_COLOURS, 8), 255)
    hip = (seat[0], seat[1] - 4)
    shoulder = (int(w * 0.42), int(h * 0.22))
    cv2.line(img, hip, shoulder, shirt, max(3, int(0.18 * ppm)))
    cv2.line(img, shoulder, bar, shirt, max(2, int(0.06 * ppm)))
    cv2.circle(img, (shoulder[0] - 2, shoulder[1] - int(0.15 * ppm)), max(2, int(0.11 * ppm)), skin, -1)
    cv2.line(img, hip, crank, (*_col(rng, CLOTH_COLOURS, 20), 255), max(2, int(0.09 * ppm)))
    img[..., 3] = np.where(img[..., 3] > 0, 255, 0).astype(np.uint8)
    return img


# --------------------------------------------------------------------------------------- sky


def _tileable_noise(rng: Rng, h: int, w: int, cells_x: int, octaves: int = 4) -> np.ndarray:
    """Multi-octave noise, (h, w) float32, that wraps around in x (for a 360 degree panorama)."""
    out = np.zeros((h, w), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        gx = cells_x * 2**o
        gy = max(2, int(round(gx * h / w)) + 2)
        small = rng.standard_normal((gy, gx)).astype(np.float32)
        ext = np.concatenate([small[:, -2:], small, small[:, :3]], axis=1)
        cell = w / gx
        big = cv2.resize(ext, (int(round(cell * (gx + 5))), h), interpolation=cv2.INTER_CUBIC)
        start = int(round(2 * cell))
        out += amp * big[:, start : start + w]
        total += amp * amp
        amp *= 0.5
    return out / np.float32(np.sqrt(total))


def sky_panorama(
    rng: Rng,
    width: int,
    height: int,
    horizon: tuple[float, float, float],
    zenith: tuple[float, float, float],
    cloud: float,
    cloud_colour: tuple[float, float, float],
) -> np.ndarray:
    """A sky panorama, (height, width, 3) uint8; row 0 is the horizon, the last row highest.

    Columns cover azimuth 0..2 pi and wrap around. ``cloud`` in [0, 1] is the cloud cover.
    """
    t = np.linspace(0.0, 1.0, height, dtype=np.float32)[:, None, None] ** 0.7
    hz = np.array(horizon, np.float32)[None, None, :]
    zn = np.array(zenith, np.float32)[None, None, :]
    img = hz * (1 - t) + zn * t + np.zeros((1, width, 1), np.float32)
    if cloud > 0:
        n = _tileable_noise(rng, height, width, cells_x=12)
        thresh = 1.0 - 1.6 * cloud
        cover = np.clip((n - thresh) * 1.2, 0, 1)[..., None] * np.clip(t * 2.0 + 0.2, 0, 1)
        shade = 1.0 - 0.25 * np.clip(n - thresh - 0.5, 0, 1)[..., None]
        img = img * (1 - cover) + np.array(cloud_colour, np.float32)[None, None, :] * shade * cover
    return np.clip(img, 0, 255).astype(np.uint8)
