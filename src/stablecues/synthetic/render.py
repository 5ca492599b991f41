"""A z-buffered renderer of textured quads: one homography warp per visible quad.

For a quad with texel-to-world map ``X = origin + tx * u + ty * v`` and a camera with
camera-to-world rotation ``R`` and centre ``C``, the texel-to-pixel map is the homography
``H = K [R^T u | R^T v | R^T (origin - C)]``. Each visible quad is clipped against the near plane,
its screen polygon filled, its texture warped into its screen bounding box with
``cv2.warpPerspective`` (from the mip level matching its nearest depth), and composited where it
is nearer than the z-buffer. Depth is exact per pixel: on a plane ``n . X = d`` (camera frame), the
inverse depth ``1 / z = n . K^-1 (x, y, 1) / d`` is affine in the pixel coordinates.

Pixel coordinates follow OpenCV: integer coordinates are pixel centres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple, cast

import cv2
import numpy as np

from .scene import SKY, Lighting, QuadSet, TextureBank
from .town import Decals


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera without distortion (OpenCV convention)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @staticmethod
    def from_fov(width: int, height: int, hfov_deg: float) -> Intrinsics:
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return Intrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


class _Screen(NamedTuple):
    """Where candidate quads land on screen (see :meth:`Renderer._screen_all`)."""

    ok: np.ndarray
    box: np.ndarray
    zmin: np.ndarray
    poly: np.ndarray
    clipped: dict[int, np.ndarray]


@dataclass
class View:
    """One rendered view.

    Attributes:
        image: (H, W, 3) uint8 BGR.
        depth: (H, W) float32 metres along the optical axis, 0 where nothing is (sky).
        labels: (H, W) uint8 CamVid ids, or None when not asked for.
        levels: (M,) int8 mip level used per candidate quad (-1: not drawn), to reuse in a stereo pair.
    """

    image: np.ndarray
    depth: np.ndarray
    labels: np.ndarray | None
    levels: np.ndarray


@dataclass
class _Batch:
    """The candidate quads of one view, ready to draw nearest first (see :meth:`Renderer._batch`).

    Per-quad values are plain Python lists for the drawing loop (numpy scalar indexing is slow).

    Attributes:
        order: indices of the quads with something on screen, nearest first.
        boxes: (x0, y0, x1, y1) screen bounding box of each quad, clamped to the image.
        izmax: inverse of each quad's nearest depth (at least the near plane's).
        abcs: (a, b, c) of each quad's plane: inverse depth = a x + b y + c at pixel (x, y).
        gains: (b, g, r, 1) shading factors of each quad.
        tex: texture id of each quad.
        label: CamVid class id of each quad.
        chosen: mip level chosen for each quad.
        H0: (M, 3, 3) texel -> pixel homographies at level 0.
        H: (M, 3, 3) texel -> bounding-box pixel homographies at the chosen levels.
        pts16: (M, 4, 2) int32 screen corners relative to the box, in 1/16 pixels.
        clipped: {index: (k, 2) screen polygon} of the quads clipped by the near plane.
        levels: (M,) int8 mip level used per quad: ``chosen``, lowered for textures with fewer
            levels as the quads are drawn.
    """

    order: list[int]
    boxes: list[list[int]]
    izmax: list[float]
    abcs: list[list[float]]
    gains: list[tuple[float, float, float, float]]
    tex: list[int]
    label: list[int]
    chosen: list[int]
    H0: np.ndarray
    H: np.ndarray
    pts16: np.ndarray
    clipped: dict[int, np.ndarray]
    levels: np.ndarray


def cull(
    R: np.ndarray,
    C: np.ndarray,
    centre: np.ndarray,
    radius: np.ndarray,
    cam: Intrinsics,
    far: float,
    margin: float = 0.0,
) -> np.ndarray:
    """Indices of the bounding spheres (centre (M, 3), radius (M,)) that may be in view."""
    d = centre - C
    cz = d @ R[:, 2]
    cx = d @ R[:, 0]
    cy = d @ R[:, 1]
    r = radius + margin
    tx = (cam.width / 2.0 + 1.0) / cam.fx
    ty = (cam.height / 2.0 + 1.0) / cam.fy
    sx = math.sqrt(1.0 + tx * tx)
    sy = math.sqrt(1.0 + ty * ty)
    dist = np.sqrt((d * d).sum(axis=1))
    keep = (cz > -r) & (dist - r < far) & (np.abs(cx) <= cz * tx + r * sx) & (np.abs(cy) <= cz * ty + r * sy)
    return np.nonzero(keep)[0]


def _multiply(img: np.ndarray, scalar: tuple[float, ...]) -> np.ndarray:
    """``img`` times a per-channel scalar (4 values), saturating."""
    # Any: OpenCV 5.0's stubs take no tuple scalar here, 5.1's do
    return cv2.multiply(img, cast(Any, scalar))


def _clip_near(poly: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a camera-frame polygon (k, 3) to z >= near."""
    out = []
    k = len(poly)
    for i in range(k):
        a, b = poly[i], poly[(i + 1) % k]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out) if out else np.zeros((0, 3))


NEAR_TEST = 1.0 / 6.0  # quads nearer than 6 m skip the "already hidden" test (inverse metres)


class Renderer:
    """Renders quads seen by a camera into colour, depth and label images.

    Args:
        cam: intrinsics (also fixes the image size).
        bank: the textures the quads refer to.
        near, far: clipping distances in metres.
    """

    def __init__(self, cam: Intrinsics, bank: TextureBank, near: float = 0.1, far: float = 250.0) -> None:
        self.cam = cam
        self.bank = bank
        self.near = near
        self.far = far
        W, H = cam.width, cam.height
        self.K = cam.K
        self.K_inv = np.linalg.inv(self.K)
        self.gx = np.ascontiguousarray(np.broadcast_to(np.arange(W, dtype=np.float32)[None, :], (H, W)))
        self.gy = np.ascontiguousarray(np.broadcast_to(np.arange(H, dtype=np.float32)[:, None], (H, W)))
        # sky: azimuth offset per column and elevation per pixel of a level camera
        xn = (np.arange(W) - cam.cx) / cam.fx
        yn = (np.arange(H) - cam.cy) / cam.fy
        self._sky_az = -np.arctan(xn)  # radians, added to the heading
        self._sky_el = np.arctan2(-yn[:, None], np.sqrt(1.0 + xn[None, :] ** 2))
        self.sky_el_max = math.radians(40.0)
        self._label_planes = [np.full((H, W), k, np.uint8) for k in range(12)]
        self._sky_rows: dict[int, np.ndarray] = {}
        self._noise: dict[float, np.ndarray] = {}
        self._alpha_cache: dict[int, np.ndarray] = {}

    # ------------------------------------------------------------------ geometry per quad

    def _prepare(
        self, q: QuadSet, R: np.ndarray, C: np.ndarray, normals: np.ndarray
    ) -> dict[str, np.ndarray]:
        oc = (q.origin - C) @ R
        uc = q.u @ R
        vc = q.v @ R
        nc = normals @ R
        r = q.rect
        tx = np.stack([r[:, 0], r[:, 2], r[:, 2], r[:, 0]], axis=1)
        ty = np.stack([r[:, 1], r[:, 1], r[:, 3], r[:, 3]], axis=1)
        pc = oc[:, None, :] + tx[..., None] * uc[:, None, :] + ty[..., None] * vc[:, None, :]
        d = (nc * oc).sum(axis=1)  # plane n.X = d in the camera frame
        with np.errstate(divide="ignore", invalid="ignore"):
            abc = (nc @ self.K_inv) / d[:, None]  # 1/z = abc . (x, y, 1)
        Hm = np.einsum("ij,mjk->mik", self.K, np.stack([uc, vc, oc], axis=2))
        return {"pc": pc, "d": d, "abc": abc, "H": Hm}

    def _screen_all(self, pc: np.ndarray, cand: np.ndarray) -> _Screen:
        """Screen polygons, clamped bounding boxes and nearest depths of camera-frame quads (M, 4, 3).

        Quads crossing the near plane are clipped (Sutherland-Hodgman), one by one; the others
        are projected together. Returns ``ok`` (M,) bool (something on screen), ``box`` (M, 4)
        int (x0, y0, x1, y1), ``zmin`` (M,), ``poly`` (M, 4, 2) projected corners, and
        ``clipped`` {index: (k, 2) polygon} for the clipped ones.
        """
        cam = self.cam
        z = pc[:, :, 2]
        zmin = z.min(axis=1)
        zmax = z.max(axis=1)
        ok = cand & (zmax >= self.near)
        straddle = np.nonzero(ok & (zmin < self.near))[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            poly = np.stack([cam.fx * pc[:, :, 0] / z + cam.cx, cam.fy * pc[:, :, 1] / z + cam.cy], axis=2)
        lo = poly.min(axis=1)
        hi = poly.max(axis=1)
        clipped: dict[int, np.ndarray] = {}
        for k in straddle.tolist():
            cp = _clip_near(pc[k], self.near)
            if len(cp) < 3:
                ok[k] = False
                continue
            pp = np.stack(
                [cam.fx * cp[:, 0] / cp[:, 2] + cam.cx, cam.fy * cp[:, 1] / cp[:, 2] + cam.cy], axis=1
            )
            clipped[k] = pp
            lo[k] = pp.min(axis=0)
            hi[k] = pp.max(axis=0)
            zmin[k] = cp[:, 2].min()
        with np.errstate(invalid="ignore"):
            box = np.empty((len(pc), 4), np.int64)
            box[:, 0] = np.clip(
                np.floor(np.nan_to_num(lo[:, 0], nan=-1.0, posinf=1e9, neginf=-1e9)), 0, cam.width
            )
            box[:, 1] = np.clip(
                np.floor(np.nan_to_num(lo[:, 1], nan=-1.0, posinf=1e9, neginf=-1e9)), 0, cam.height
            )
            box[:, 2] = np.clip(
                np.ceil(np.nan_to_num(hi[:, 0], nan=-1.0, posinf=1e9, neginf=-1e9)) + 1, 0, cam.width
            )
            box[:, 3] = np.clip(
                np.ceil(np.nan_to_num(hi[:, 1], nan=-1.0, posinf=1e9, neginf=-1e9)) + 1, 0, cam.height
            )
        ok &= (box[:, 2] > box[:, 0]) & (box[:, 3] > box[:, 1])
        return _Screen(ok, box, zmin, poly, clipped)

    # ------------------------------------------------------------------ main entry

    def render(
        self,
        R: np.ndarray,
        C: np.ndarray,
        quads: QuadSet,
        normals: np.ndarray,
        light: Lighting,
        decals: Decals | None = None,
        *,
        labels: bool = True,
        levels: np.ndarray | None = None,
        noise: float = 0.0,
        noise_rng: np.random.Generator | None = None,
    ) -> View:
        """Render one view.

        Args:
            R: (3, 3) camera-to-world rotation (x right, y down, z forward).
            C: (3,) camera centre in the world.
            quads: candidate quads (already culled roughly).
            normals: (M, 3) their unit front normals.
            light: the lap's lighting (shading gains and the sky).
            decals: cast shadows that may be in view (culled by the caller), or None.
            labels: also produce the label image.
            levels: (M,) mip levels to use (from the other view of a stereo pair), -1 = choose.
            noise: standard deviation of added sensor noise, grey levels (0: none).
            noise_rng: generator for the noise.
        """
        cam = self.cam
        H, W = cam.height, cam.width
        img = np.zeros((H, W, 3), np.uint8)
        ibuf = np.zeros((H, W), np.float32)  # inverse depth: 0 where nothing is (the sky)
        lab = np.full((H, W), SKY, np.uint8) if labels else None
        lv = np.full(len(quads), -1, np.int8) if levels is None else levels.copy()
        if len(quads):
            batch = self._batch(quads, R, C, normals, light, lv)
            for qi in batch.order:
                self._draw_quad(qi, batch, img, ibuf, lab)
            lv = batch.levels
        if decals is not None and len(decals.quads):
            self._shadows(img, ibuf, R, C, decals)
        self._sky(img, ibuf, R, light)
        if noise > 0:
            self._add_noise(img, noise, noise_rng if noise_rng is not None else np.random.default_rng(0))
        depth = np.divide(np.float32(1.0), ibuf, out=np.zeros_like(ibuf), where=ibuf > 0)
        return View(img, depth, lab, lv)

    def _batch(
        self,
        quads: QuadSet,
        R: np.ndarray,
        C: np.ndarray,
        normals: np.ndarray,
        light: Lighting,
        levels: np.ndarray,
    ) -> _Batch:
        """Project, shade and order the candidate quads, and choose their mip levels (-1 in ``levels``)."""
        g = self._prepare(quads, R, C, normals)
        facing = g["d"] < 0.0  # camera on the front side of the plane
        ok, box, zmin, poly, clipped = self._screen_all(g["pc"], quads.two_sided | facing)
        eff_n = np.where(facing[:, None], normals, -normals)
        gains = light.gains(eff_n, quads.lit)
        lv = self._mip_levels(quads, g["d"], zmin, levels)
        order = np.nonzero(ok)[0]
        order = order[np.argsort(zmin[order], kind="stable")]
        # texel -> bounding-box pixel homographies at the chosen level, all at once
        Hs = g["H"].copy()
        scale = np.ldexp(1.0, lv.astype(np.int64))
        Hs[:, :, 0] *= scale[:, None]
        Hs[:, :, 1] *= scale[:, None]
        Hs[:, 0, :] -= box[:, :1] * Hs[:, 2, :]
        Hs[:, 1, :] -= box[:, 1:2] * Hs[:, 2, :]
        with np.errstate(invalid="ignore"):
            pts16 = np.round((poly - box[:, None, :2]) * 16.0).astype(np.int32)
        return _Batch(
            order=order.tolist(),
            boxes=box.tolist(),
            izmax=(1.0 / np.maximum(zmin, self.near)).tolist(),
            abcs=g["abc"].tolist(),
            gains=[(g0, g1, g2, 1.0) for g0, g1, g2 in gains.tolist()],
            tex=quads.tex.tolist(),
            label=quads.label.tolist(),
            chosen=lv.tolist(),
            H0=g["H"],
            H=Hs,
            pts16=pts16,
            clipped=clipped,
            levels=lv,
        )

    def _mip_levels(self, quads: QuadSet, d: np.ndarray, zmin: np.ndarray, levels: np.ndarray) -> np.ndarray:
        """(M,) int8 mip levels: ``levels`` where set (>= 0), else chosen from the quads' footprints.

        The level follows texels per pixel at the quad's nearest point, between the footprint
        across the view and the (longer) one along a surface seen at a grazing angle (geometric
        mean; warpPerspective has no anisotropic filtering). ``d`` (M,) is each quad's plane
        offset in the camera frame and ``zmin`` (M,) its nearest depth.
        """
        texel = np.linalg.norm(quads.u, axis=1)
        zn = np.maximum(zmin, self.near)
        grazing = np.clip(np.abs(d) / zn, 0.05, 1.0)
        with np.errstate(divide="ignore"):
            auto = np.floor(np.log2(np.maximum(zn / self.cam.fx / texel / np.sqrt(grazing), 1e-9)) + 0.3)
        return np.where(levels < 0, np.clip(auto, 0, 6), levels).astype(np.int8)

    def _draw_quad(
        self, qi: int, batch: _Batch, img: np.ndarray, ibuf: np.ndarray, lab: np.ndarray | None
    ) -> None:
        """Warp quad ``qi``'s texture into its box and composite it where it is nearest (in place)."""
        x0, y0, x1, y1 = batch.boxes[qi]
        ib = ibuf[y0:y1, x0:x1]
        # hidden behind what is already drawn? (near quads rarely are: skip the test)
        if batch.izmax[qi] < NEAR_TEST and ib.min() > batch.izmax[qi]:
            return
        pyramid = self.bank.levels(batch.tex[qi])
        level = batch.chosen[qi]
        Hm = batch.H[qi]
        if level >= len(pyramid):  # a small texture has fewer levels
            level = len(pyramid) - 1
            batch.levels[qi] = level
            Hm = batch.H0[qi].copy()
            Hm[:, :2] *= float(1 << level)
            Hm[0] -= x0 * Hm[2]
            Hm[1] -= y0 * Hm[2]
        bw, bh = x1 - x0, y1 - y0
        warped = cv2.warpPerspective(
            pyramid[level], Hm, (bw, bh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        mask = np.zeros((bh, bw), np.uint8)
        pp = batch.clipped.get(qi)
        pts = batch.pts16[qi] if pp is None else np.round((pp - (x0, y0)) * 16.0).astype(np.int32)
        cv2.fillConvexPoly(mask, pts, 255, lineType=cv2.LINE_8, shift=4)
        a_, b_, c_ = batch.abcs[qi]
        iz = cv2.addWeighted(self.gx[y0:y1, x0:x1], a_, self.gy[y0:y1, x0:x1], b_, c_)
        cv2.bitwise_and(mask, cv2.compare(iz, ib, cv2.CMP_GT), dst=mask)
        if warped.shape[2] == 4:
            opaque = cv2.threshold(cv2.extractChannel(warped, 3), 127, 255, cv2.THRESH_BINARY)[1]
            cv2.bitwise_and(mask, opaque, dst=mask)
            col = cv2.cvtColor(_multiply(warped, batch.gains[qi]), cv2.COLOR_BGRA2BGR)
        else:
            col = _multiply(warped, batch.gains[qi])
        cv2.copyTo(iz, mask, ib)
        cv2.copyTo(col, mask, img[y0:y1, x0:x1])
        if lab is not None:
            cv2.copyTo(self._label_planes[batch.label[qi]][:bh, :bw], mask, lab[y0:y1, x0:x1])

    def _add_noise(self, img: np.ndarray, sigma: float, rng: np.random.Generator) -> None:
        """Add Gaussian sensor noise in place: a window of a fixed noise field, placed by ``rng``."""
        H, W = img.shape[:2]
        field = self._noise.get(sigma)
        if field is None:
            unit = np.random.default_rng(12345).standard_normal((2 * H, 2 * W, 3), dtype=np.float32)
            field = np.round(unit * np.float32(sigma)).astype(np.int16)
            self._noise[sigma] = field
        oy, ox = int(rng.integers(0, H)), int(rng.integers(0, W))
        cv2.add(img, field[oy : oy + H, ox : ox + W], dst=img, dtype=cv2.CV_8U)

    # ------------------------------------------------------------------ shadows and sky

    def _shadows(
        self, img: np.ndarray, ibuf: np.ndarray, R: np.ndarray, C: np.ndarray, decals: Decals
    ) -> None:
        cam = self.cam
        H, W = cam.height, cam.width
        sub = decals.quads
        g = self._prepare(sub, R, C, decals.normal)
        ok, box, _, poly, clipped = self._screen_all(g["pc"], g["d"] < 0.0)  # camera on the lit side
        done = np.zeros((H, W), np.uint8)
        tol_rel, tol_abs = np.float32(2e-4), np.float32(2e-3)
        boxes = box.tolist()
        abcs = g["abc"].tolist()
        alpha_l = decals.alpha.tolist()
        tex_l = sub.tex.tolist()
        gain_l = [(g0, g1, g2, 1.0) for g0, g1, g2 in decals.gain.tolist()]
        for k in np.nonzero(ok)[0].tolist():
            x0, y0, x1, y1 = boxes[k]
            bw, bh = x1 - x0, y1 - y0
            mask = np.zeros((bh, bw), np.uint8)
            pp = clipped.get(k)
            pts = np.round(((poly[k] if pp is None else pp) - (x0, y0)) * 16.0).astype(np.int32)
            cv2.fillConvexPoly(mask, pts, 255, lineType=cv2.LINE_8, shift=4)
            a_, b_, c_ = abcs[k]
            iz = cv2.addWeighted(self.gx[y0:y1, x0:x1], a_, self.gy[y0:y1, x0:x1], b_, c_)
            ib = ibuf[y0:y1, x0:x1]
            # on the receiving surface: |depth difference| <= tol_rel * z + tol_abs, in inverse depth
            tol = iz * (tol_rel + tol_abs * iz)
            cv2.bitwise_and(mask, cv2.compare(cv2.absdiff(ib, iz), tol, cv2.CMP_LE), dst=mask)
            cv2.bitwise_and(mask, cv2.bitwise_not(done[y0:y1, x0:x1]), dst=mask)
            if not cv2.countNonZero(mask):
                continue
            if alpha_l[k]:
                Hm = g["H"][k].copy()
                Hm[0] -= x0 * Hm[2]
                Hm[1] -= y0 * Hm[2]
                alpha = cv2.warpPerspective(
                    self._alpha(tex_l[k]),
                    Hm,
                    (bw, bh),
                    flags=cv2.INTER_NEAREST,
                    borderMode=cv2.BORDER_CONSTANT,
                )
                cv2.bitwise_and(mask, alpha, dst=mask)
            sl = img[y0:y1, x0:x1]
            cv2.copyTo(_multiply(sl, gain_l[k]), mask, sl)
            cv2.bitwise_or(done[y0:y1, x0:x1], mask, dst=done[y0:y1, x0:x1])

    def _alpha(self, tex_id: int) -> np.ndarray:
        """The cut-out mask (0 or 255) of a BGRA texture at level 0, cached."""
        hit = self._alpha_cache.get(tex_id)
        if hit is None:
            tex = self.bank.levels(tex_id)[0]
            hit = cv2.threshold(cv2.extractChannel(tex, 3), 127, 255, cv2.THRESH_BINARY)[1]
            if len(self._alpha_cache) > 4096:
                self._alpha_cache.clear()
            self._alpha_cache[tex_id] = hit
        return hit

    def _sky(self, img: np.ndarray, ibuf: np.ndarray, R: np.ndarray, light: Lighting) -> None:
        empty = ibuf <= 0
        rows = np.nonzero(empty.any(axis=1))[0]
        if not len(rows):
            return
        hs = int(rows.max()) + 1
        pano = self.bank.levels(light.sky_tex)[0]
        ph, pw = pano.shape[:2]
        my = self._sky_rows.get(ph)
        if my is None:
            my = np.clip(self._sky_el / self.sky_el_max * (ph - 1), 0, ph - 1).astype(np.float32)
            self._sky_rows[ph] = my
        heading = math.atan2(R[1, 2], R[0, 2])
        mx = np.mod((heading + self._sky_az) * (pw / (2 * math.pi)), pw).astype(np.float32)
        sky = cv2.remap(
            pano,
            np.ascontiguousarray(np.broadcast_to(mx[None, :], (hs, len(mx)))),
            my[:hs],
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_WRAP,
        )
        cv2.copyTo(sky, empty[:hs].view(np.uint8), img[:hs])
