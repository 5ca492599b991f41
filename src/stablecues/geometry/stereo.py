"""Sparse stereo: 3D points of left-image keypoints from a rectified stereo pair.

For each left keypoint the right image is searched along the same row (a band of
``2 * patch_radius + 1`` rows) over a disparity range, comparing zero-mean normalised
cross-correlation (ZNCC) of patches. ZNCC is insensitive to the gain and offset differences
between the two cameras of a rig (EuRoC's are visibly different). No dense disparity map is
computed: the work is proportional to the number of keypoints.

Steps, all vectorised over keypoints:

1. coarse search on a half-resolution pyramid level over the whole disparity range;
2. left-right consistency: the right patch found is searched back along the left row, and must
   come back to the keypoint (within ``lr_tolerance`` coarse pixels), which rejects occlusions
   and repeated texture;
3. fine search at full resolution within +-2 px of the coarse result, then a parabola through
   the ZNCC peak and its neighbours for a sub-pixel disparity;
4. rejection of flat patches (``min_texture``) and weak peaks (``min_zncc``).

Depth ``z = f B / d``; its noise is ``z**2 sigma_d / (f B)`` (:class:`~.points.NoiseModel`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ..errors import CalibrationError, InputError, check_array
from ..types import Features
from .camera import Calibration
from .points import STEREO_DISPARITY_SIGMA, NoiseModel, Points3D
from .rectify import StereoRectifier

__all__ = ["StereoConfig", "StereoLifter", "stereo_disparities"]


@dataclass(frozen=True)
class StereoConfig:
    """Settings of sparse stereo matching.

    Attributes:
        patch_radius: half-size of the full-resolution ZNCC patch (3: 7x7 pixels).
        coarse_patch_radius: half-size of the half-resolution patch (2: 5x5, i.e. 10x10 at full
            resolution, enough context to make the coarse search unambiguous).
        min_depth: nearest depth searched, metres; sets the largest disparity ``f B / min_depth``.
        max_disparity: largest disparity in pixels; None: ``f B / min_depth`` capped at a third
            of the image width.
        min_disparity: smallest disparity in pixels. One pixel means depths beyond ``f B``
            metres (48 m for EuRoC) are not lifted: at 0.3 px disparity noise their depth
            error exceeds 30 %, useless for a 3D check.
        min_zncc: smallest accepted correlation of the fine match. 0.7 keeps matches on real
            texture between two differently exposed cameras; the left-right check does the
            real outlier rejection.
        min_texture: smallest grey-level standard deviation of the left patch; flatter patches
            give no reliable disparity.
        lr_tolerance: largest disagreement of the left-right check, in coarse pixels.
        sigma_disparity: disparity noise in pixels used for the depth sigma.
        coarse_to_fine: search at half resolution first (fast); False searches the whole range
            at full resolution (about 4x slower, for small images or fine texture).
    """

    patch_radius: int = 3
    coarse_patch_radius: int = 2
    min_depth: float = 0.5
    max_disparity: float | None = None
    min_disparity: float = 1.0
    min_zncc: float = 0.7
    min_texture: float = 3.0
    lr_tolerance: float = 1.0
    sigma_disparity: float = STEREO_DISPARITY_SIGMA
    coarse_to_fine: bool = True


def _grey(name: str, image: np.ndarray) -> np.ndarray:
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or image.size == 0:
        raise InputError(
            f"{name}: expected a non-empty image array, got {getattr(image, 'shape', type(image))}"
        )
    if image.ndim == 3:
        if image.shape[2] == 1:
            image = image[:, :, 0]
        elif image.shape[2] in (3, 4):
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
        else:
            raise InputError(f"{name}: expected 1, 3 or 4 channels, got {image.shape[2]}")
    if image.dtype not in (np.uint8, np.uint16, np.float32):
        image = image.astype(np.float32)
    return np.ascontiguousarray(image)


def _window_std(image: np.ndarray, r: int) -> np.ndarray:
    """(H, W) float32 grey-level std of the (2r+1)^2 window around each pixel; 0 where the window
    leaves the image on the left or right (such candidates are then never chosen)."""
    w = 2 * r + 1
    mean = cv2.boxFilter(image, cv2.CV_32F, (w, w), borderType=cv2.BORDER_REFLECT)
    sq = cv2.sqrBoxFilter(image, cv2.CV_32F, (w, w), borderType=cv2.BORDER_REFLECT)
    var = sq - mean * mean
    np.maximum(var, 0.0, out=var)
    std = np.sqrt(var, out=var)
    std[:, :r] = 0.0
    std[:, image.shape[1] - r :] = 0.0
    return std


def _strip_std(strips: np.ndarray, count: int, r: int) -> np.ndarray:
    """(N, count) grey-level std of each candidate window of (N, 2r+1, count+2r) strips."""
    w = 2 * r + 1
    col = strips.sum(axis=1)
    colsq = np.einsum("nas,nas->ns", strips, strips)
    wsum = col[:, :count].copy()
    wsq = colsq[:, :count].copy()
    for b in range(1, w):
        wsum += col[:, b : b + count]
        wsq += colsq[:, b : b + count]
    area = float(w * w)
    return np.sqrt(np.maximum(wsq / area - (wsum / area) ** 2, 0.0))


def _scan(
    src: np.ndarray,
    dst: np.ndarray,
    dst_std: np.ndarray | None,
    xs: np.ndarray,
    ys: np.ndarray,
    x0: np.ndarray,
    count: int,
    r: int,
) -> tuple[np.ndarray, np.ndarray]:
    """ZNCC of the ``src`` patch at (xs, ys) against ``dst`` patches at (x0 + j, ys), j < count.

    ``src`` patches must lie inside the image; ``dst`` candidates whose window leaves the image
    score -inf. Images may be of any numeric dtype; only gathered pixels become float32.

    Args:
        src, dst: (H, W) images.
        dst_std: ``_window_std(dst, r)``, or None to compute the candidates' std from the
            gathered strips (cheaper when ``count`` is small).
        xs, ys: (N,) int64 patch centres in ``src``.
        x0: (N,) int64 first candidate column in ``dst``.
        count: number of candidates per patch.
        r: patch radius.

    Returns:
        (N, count) float32 scores and (N,) float32 grey-level std of each src patch.
    """
    n = xs.shape[0]
    w = 2 * r + 1
    if n == 0:
        return np.zeros((0, count), np.float32), np.zeros(0, np.float32)
    width = dst.shape[1]
    span = count + 2 * r  # strip length
    pad_left = int(max(0, r - int(x0.min())))
    pad_right = int(max(0, int(x0.max()) + count - 1 + r - (width - 1)))
    if pad_left or pad_right:
        dst = np.pad(dst, ((0, 0), (pad_left, pad_right)))
        if dst_std is not None:
            dst_std = np.pad(dst_std, ((0, 0), (pad_left, pad_right)))
    strips = sliding_window_view(dst, (w, span))[ys - r, x0 - r + pad_left].astype(np.float32)
    if dst_std is not None:
        stds = sliding_window_view(dst_std, count, axis=1)[ys, x0 + pad_left]  # (N, count)
    else:
        stds = _strip_std(strips, count, r)
        cand = x0[:, None] + np.arange(count)[None, :]
        stds[(cand < r) | (cand > width - 1 - r)] = 0.0
    patches = sliding_window_view(src, (w, w))[ys - r, xs - r].astype(np.float32)

    area = float(w * w)
    flat = patches.reshape(n, w * w)
    pz = (flat - (flat.sum(axis=1) / area)[:, None]).reshape(n, w, w)
    pnorm = np.sqrt(np.einsum("nk,nk->n", pz.reshape(n, w * w), pz.reshape(n, w * w)))
    num = np.zeros((n, count), np.float32)
    if count <= 3 * w:  # few candidates: one small matmul per patch row
        windows = sliding_window_view(strips, w, axis=2)  # (N, w, count, w), a view
        for a in range(w):
            num += np.matmul(windows[:, a], pz[:, a, :, None])[..., 0]
    else:  # many candidates: in-place multiply-adds over the patch pixels
        tmp = np.empty((n, count), np.float32)
        for a in range(w):
            row = strips[:, a, :]
            for b in range(w):
                np.multiply(pz[:, a, b, None], row[:, b : b + count], out=tmp)
                num += tmp
    # sum(pz * q) = sum(pz * (q - mean q)), so ZNCC = num / (|pz| * sqrt(area) * std_q)
    with np.errstate(divide="ignore", invalid="ignore"):
        score = num / ((pnorm * math.sqrt(area))[:, None] * stds)
    score[~np.isfinite(score)] = -np.inf
    return score, (pnorm / math.sqrt(area)).astype(np.float32)


def _coarse_search(
    left_f: np.ndarray,
    right_f: np.ndarray,
    keypoints: np.ndarray,
    inside: np.ndarray,
    d_lo: int,
    d_hi: int,
    config: StereoConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Integer disparities at half resolution, left-right checked, for the coarse-to-fine search.

    Args:
        left_f, right_f: (H, W) float32 rectified images.
        keypoints: (N, 2) pixel coordinates (x, y) in the left image.
        inside: (N,) bool keypoints whose full-resolution patch fits.
        d_lo, d_hi: integer disparity range at full resolution.
        config: matching settings.

    Returns:
        ``(idx, d_centre)``: (K,) int64 indices of the keypoints that passed and (K,) int64
        their full-resolution disparity (twice the coarse one).
    """
    rc = config.coarse_patch_radius
    left_c = cv2.pyrDown(left_f)
    right_c = cv2.pyrDown(right_f)
    hc, wc = left_c.shape
    xc = np.rint(keypoints[:, 0] / 2.0).astype(np.int64)
    yc = np.rint(keypoints[:, 1] / 2.0).astype(np.int64)
    idx = np.flatnonzero(inside & (xc >= rc) & (xc < wc - rc) & (yc >= rc) & (yc < hc - rc))
    dc_lo, dc_hi = d_lo // 2, -(-d_hi // 2)
    count_c = dc_hi - dc_lo + 1
    xi, yi = xc[idx], yc[idx]
    # candidates at x - dc_hi + j: disparity dc_hi - j
    sc, _ = _scan(left_c, right_c, _window_std(right_c, rc), xi, yi, xi - dc_hi, count_c, rc)
    jbest = np.argmax(sc, axis=1)
    ok = np.isfinite(sc[np.arange(idx.size), jbest])
    dc = dc_hi - jbest
    # left-right check: right patch at x - dc searched along the left row, x_r + dc_lo + j
    xr = xi - dc
    ok &= (xr >= rc) & (xr < wc - rc)
    idx, xi, yi, dc, xr = idx[ok], xi[ok], yi[ok], dc[ok], xr[ok]
    sb, _ = _scan(right_c, left_c, _window_std(left_c, rc), xr, yi, xr + dc_lo, count_c, rc)
    back = dc_lo + np.argmax(sb, axis=1)
    ok = np.abs(back - dc) <= config.lr_tolerance
    return idx[ok], 2 * dc[ok]


def _left_right_check(
    left_f: np.ndarray,
    right_f: np.ndarray,
    xf: np.ndarray,
    yf: np.ndarray,
    d_int: np.ndarray,
    d_lo: int,
    d_hi: int,
    config: StereoConfig,
) -> np.ndarray:
    """(K,) bool: searching back from the right patch at ``xf - d_int`` finds ``d_int`` again.

    The back search covers the whole range [d_lo, d_hi] at full resolution and accepts a
    difference of up to ``2 * config.lr_tolerance`` pixels; a right patch that does not fit in
    the image fails.
    """
    r = config.patch_radius
    width = left_f.shape[1]
    xr = xf - d_int
    okr = (xr >= r) & (xr < width - r)
    back = np.full(xf.size, -(10**9), np.int64)
    if okr.any():
        sb, _ = _scan(
            right_f, left_f, _window_std(left_f, r), xr[okr], yf[okr], xr[okr] + d_lo, d_hi - d_lo + 1, r
        )
        back[okr] = d_lo + np.argmax(sb, axis=1)
    return np.abs(back - d_int) <= 2 * config.lr_tolerance


def _parabola_peak(scores: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best inner candidate of each row and its sub-pixel offset from a parabola through 3 scores.

    Args:
        scores: (K, C) float32 scores of C candidates per keypoint (C >= 3).

    Returns:
        ``(j, s0, offset)``: (K,) int64 column of the best inner candidate, (K,) its score and
        (K,) float64 offset in [-0.5, 0.5] towards the higher neighbour (0 without a peak).
    """
    j = 1 + np.argmax(scores[:, 1:-1], axis=1)
    rows = np.arange(scores.shape[0])
    s0 = scores[rows, j]
    sm = scores[rows, j - 1]
    sp = scores[rows, j + 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        denom = sm - 2.0 * s0 + sp
        offset = np.where(np.isfinite(denom) & (denom < 0), 0.5 * (sm - sp) / denom, 0.0)
    return j, s0, np.clip(offset, -0.5, 0.5)


def stereo_disparities(
    left: np.ndarray,
    right: np.ndarray,
    keypoints: np.ndarray,
    *,
    min_disparity: float,
    max_disparity: float,
    config: StereoConfig = StereoConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel disparities of left keypoints in a rectified pair.

    Args:
        left: rectified left image (H, W), grey or colour, any numeric dtype.
        right: rectified right image, same size.
        keypoints: (N, 2) pixel coordinates (x, y) in the rectified left image.
        min_disparity: smallest disparity searched, pixels (>= 0).
        max_disparity: largest disparity searched, pixels.
        config: matching settings (patch sizes, thresholds).

    Returns:
        ``(disparity, score)``: (N,) float32 disparities in pixels (NaN where no reliable match)
        and (N,) float32 ZNCC of the fine match (NaN where none).
    """
    left_f = _grey("left image", left)
    right_f = _grey("right image", right)
    if left_f.shape != right_f.shape:
        raise InputError(f"stereo images: expected equal sizes, got {left_f.shape} and {right_f.shape}")
    keypoints = np.asarray(keypoints)
    check_array("keypoints", keypoints, shape=(None, 2))
    n = keypoints.shape[0]
    disp = np.full(n, np.nan, np.float32)
    score_out = np.full(n, np.nan, np.float32)
    if n == 0:
        return disp, score_out
    if not 0 <= min_disparity < max_disparity:
        raise InputError(f"disparity range: expected 0 <= min < max, got [{min_disparity}, {max_disparity}]")
    height, width = left_f.shape
    r = config.patch_radius
    xs = np.rint(keypoints[:, 0]).astype(np.int64)
    ys = np.rint(keypoints[:, 1]).astype(np.int64)
    inside = (xs >= r) & (xs < width - r) & (ys >= r) & (ys < height - r)

    d_lo = int(math.floor(min_disparity))
    d_hi = int(math.ceil(max_disparity))
    if config.coarse_to_fine:
        idx, d_centre = _coarse_search(left_f, right_f, keypoints, inside, d_lo, d_hi, config)
        half = 3  # fine search d_centre-2..d_centre+2, plus one neighbour each side for the parabola
    else:
        idx = np.flatnonzero(inside)
        half = (d_hi - d_lo) // 2 + 1
        d_centre = np.full(idx.size, d_lo + half - 1, np.int64)

    # fine search: candidates at x - (d_centre + half) + j, disparity d_centre + half - j
    xf, yf = xs[idx], ys[idx]
    count_f = 2 * half + 1
    sf, texture = _scan(left_f, right_f, None, xf, yf, xf - (d_centre + half), count_f, r)
    if not config.coarse_to_fine and idx.size:
        # left-right check at full resolution for the exhaustive search
        d_int = d_centre + half - np.argmax(sf, axis=1)
        lr_ok = _left_right_check(left_f, right_f, xf, yf, d_int, d_lo, d_hi, config)
    else:
        lr_ok = np.ones(idx.size, bool)
    j, s0, offset = _parabola_peak(sf)
    d_sub = (d_centre + half - j).astype(np.float64) - offset
    good = (
        lr_ok
        & np.isfinite(s0)
        & (s0 >= config.min_zncc)
        & (texture >= config.min_texture)
        & (d_sub >= max(min_disparity, 1e-6))
        & (d_sub <= max_disparity)
    )
    disp[idx[good]] = d_sub[good]
    score_out[idx[good]] = s0[good]
    return disp, score_out


class StereoLifter:
    """Lifts left keypoints to 3D with a stereo pair.

    With a rectified calibration, images and keypoints must be rectified and points come out in
    the (rectified) left camera. With a raw calibration (EuRoC), the images are rectified here
    (remap tables cached), raw keypoints are mapped into the rectified image, and the points are
    rotated back into the raw left camera frame, so they pair with the raw keypoints and the raw
    camera model (e.g. for PnP with distortion).

    Args:
        calib: stereo calibration (rectified or raw).
        config: matching settings.
    """

    def __init__(self, calib: Calibration, config: StereoConfig = StereoConfig()) -> None:
        if not calib.is_stereo:
            raise CalibrationError(f"{calib.source}: stereo lifting needs a stereo calibration")
        self.config = config
        self.rectifier: StereoRectifier | None = None
        if calib.rectified:
            self.rectified = calib
        else:
            self.rectifier = StereoRectifier(calib)
            self.rectified = self.rectifier.rectified
        self.calib = calib
        cam = self.rectified.left
        baseline = self.rectified.baseline
        if baseline is None or not baseline > 0:
            raise CalibrationError(f"{calib.source}: stereo baseline unknown")
        self.bf = float(cam.fx * baseline)
        width = cam.width
        max_d = self.bf / config.min_depth
        if width is not None:
            max_d = min(max_d, width / 3.0)
        self.max_disparity = float(config.max_disparity) if config.max_disparity is not None else max_d
        self.noise = NoiseModel.stereo(cam.fx, baseline, config.sigma_disparity)

    def lift(
        self,
        features: Features | np.ndarray,
        left: np.ndarray,
        right: np.ndarray,
        octaves: np.ndarray | None = None,
    ) -> Points3D:
        """3D points of the keypoints.

        Args:
            features: the left image's features, or an (N, 2) array of keypoint pixels.
            left: left image as the calibration expects it (raw for a raw calibration).
            right: right image, same size.
            octaves: (N,) pyramid levels when ``features`` is an array (for the lateral sigma).

        Returns:
            (N,) points in the left camera frame; NaN where no reliable disparity.
        """
        if isinstance(features, Features):
            keypoints = features.keypoints
            octaves = features.octaves
        else:
            keypoints = np.asarray(features)
            check_array("keypoints", keypoints, shape=(None, 2))
        n = keypoints.shape[0]
        if n == 0:
            return Points3D.empty(0)
        if self.rectifier is not None:
            left, right = self.rectifier.rectify(left, right)
            kp_rect = self.rectifier.rectify_keypoints(keypoints)
        else:
            kp_rect = np.asarray(keypoints, np.float64)
        max_d = self.max_disparity
        if self.rectified.left.width is None and self.config.max_disparity is None:
            max_d = min(max_d, left.shape[1] / 3.0)  # width known only now: same cap as above
        disp, _ = stereo_disparities(
            left,
            right,
            kp_rect,
            min_disparity=self.config.min_disparity,
            max_disparity=max_d,
            config=self.config,
        )
        cam = self.rectified.left
        with np.errstate(invalid="ignore", divide="ignore"):
            z = self.bf / disp.astype(np.float64)
        xyz = cam.unproject(kp_rect, z)
        if self.rectifier is not None:
            xyz = xyz @ self.rectifier.rotation_raw_to_rectified  # R1^T applied to row vectors
        return self.noise.points(xyz, octaves)
