"""3D points of keypoints from a depth image, or from map points handed in by a SLAM system."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError, check_array
from ..types import Features
from .camera import PinholeCamera
from .points import NoiseModel, Points3D

__all__ = ["DepthConfig", "depth_to_metres", "lift_depth", "lift_map_points"]


@dataclass(frozen=True)
class DepthConfig:
    """Settings of lifting keypoints with a depth image.

    Attributes:
        min_depth: nearer readings are rejected, metres (a Kinect v1 measures from ~0.5 m).
        max_depth: farther readings are rejected, metres; None keeps every reading (far ones
            are noisy, but their sigma says so: 9 cm at 8 m for a Kinect).
        max_relative_step: largest spread (max - min) of the valid depths in the
            ``(2 * edge_radius + 1)``-pixel square around the keypoint, relative to its depth.
            A corner on an occluding contour reads the foreground or the background depending
            on a pixel, so its depth is not trustworthy. 0.05 over the 4-pixel span of a 5x5
            square is a surface slanted by more than ~80 degrees at f = 520 px
            (tan = 0.05 * f / 4 = 6.5), far beyond a Kinect's noise (0.57 % of depth at 4 m),
            so only real discontinuities are rejected.
        edge_radius: half-size of that square. A Kinect's depth is registered to the colour
            image only to within a few pixels at object boundaries, so a corner 1-2 px from a
            depth edge may read the other side's depth: radius 2 (5x5) rejects those.
    """

    min_depth: float = 0.3
    max_depth: float | None = None
    max_relative_step: float = 0.05
    edge_radius: int = 2


def depth_to_metres(depth: np.ndarray, depth_scale: float | None) -> np.ndarray:
    """A depth image in metres, float32, NaN where there is no reading.

    Args:
        depth: (H, W) depth image: integer raw units (e.g. uint16 with ``depth_scale`` units
            per metre), or float metres (``depth_scale`` None or 1).
        depth_scale: raw units per metre (TUM: 5000, Kinect recordings: 1000).

    Returns:
        (H, W) float32 metres; zeros, negatives and non-finite values become NaN.
    """
    if not isinstance(depth, np.ndarray) or depth.ndim != 2:
        raise InputError(f"depth image: expected a 2-D array, got {getattr(depth, 'shape', type(depth))}")
    out = depth.astype(np.float32)
    if depth_scale is not None:
        if not depth_scale > 0:
            raise InputError(f"depth scale: expected a positive number, got {depth_scale}")
        out /= np.float32(depth_scale)
    elif np.issubdtype(depth.dtype, np.integer):
        raise InputError("depth image: integer depths need a depth scale (units per metre)")
    out[~(np.isfinite(out) & (out > 0))] = np.nan
    return out


def lift_depth(
    features: Features | np.ndarray,
    depth: np.ndarray,
    camera: PinholeCamera,
    *,
    depth_scale: float | None = None,
    noise: NoiseModel | None = None,
    config: DepthConfig = DepthConfig(),
    octaves: np.ndarray | None = None,
) -> Points3D:
    """3D points of keypoints from a depth image registered to the image they come from.

    The depth is read at the nearest pixel. Holes, the zero border, readings outside
    ``[min_depth, max_depth]`` and depth discontinuities (see :class:`DepthConfig`) give NaN.

    Args:
        features: the image's features, or (N, 2) keypoint pixels (x, y).
        depth: (H, W) depth image of the same size as the colour image (raw or metres).
        camera: the colour camera (distortion is undone before back-projection).
        depth_scale: raw units per metre (None for float metres).
        noise: depth noise model; default ``NoiseModel.kinect(camera.fx)``.
        config: lifting settings.
        octaves: (N,) pyramid levels when ``features`` is an array.

    Returns:
        (N,) points in the camera frame, metres.
    """
    if isinstance(features, Features):
        keypoints = features.keypoints
        octaves = features.octaves
    else:
        keypoints = np.asarray(features)
        check_array("keypoints", keypoints, shape=(None, 2))
    metres = depth_to_metres(depth, depth_scale)
    h, w = metres.shape
    if camera.image_size is not None and camera.image_size != (w, h):
        raise InputError(
            f"depth image: expected {camera.image_size[0]}x{camera.image_size[1]} "
            f"like the camera, got {w}x{h}"
        )
    n = keypoints.shape[0]
    if n == 0:
        return Points3D.empty(0)
    xs = np.rint(keypoints[:, 0]).astype(np.int64)
    ys = np.rint(keypoints[:, 1]).astype(np.int64)
    rad = int(config.edge_radius)
    inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
    z = np.full(n, np.nan)
    if inside.any():
        xi, yi = xs[inside], ys[inside]
        padded = np.pad(metres, rad, constant_values=np.nan)
        span = np.arange(-rad, rad + 1)
        # (M, (2r+1)^2) neighbourhoods; NaN (no reading) ignored in the spread
        neigh = padded[
            (yi + rad)[:, None, None] + span[None, :, None], (xi + rad)[:, None, None] + span[None, None, :]
        ]
        neigh = neigh.reshape(yi.size, -1)
        centre = metres[yi, xi].astype(np.float64)
        finite = np.isfinite(neigh)
        with np.errstate(invalid="ignore"):
            spread = np.max(np.where(finite, neigh, -np.inf), axis=1) - np.min(
                np.where(finite, neigh, np.inf), axis=1
            )
            ok = (
                np.isfinite(centre)
                & (centre >= config.min_depth)
                & (centre <= (np.inf if config.max_depth is None else config.max_depth))
                & (spread <= config.max_relative_step * centre)
            )
        zi = np.where(ok, centre, np.nan)
        z[inside] = zi
    xyz = camera.unproject(np.asarray(keypoints, np.float64), z)
    model = noise if noise is not None else NoiseModel.kinect(camera.fx)
    return model.points(xyz, octaves)


def lift_map_points(
    points: np.ndarray,
    noise: NoiseModel,
    *,
    octaves: np.ndarray | None = None,
    sigma_depth: np.ndarray | None = None,
) -> Points3D:
    """Map points handed in by a SLAM system, validated, with their noise.

    Args:
        points: (N, 3) float points per keypoint, in the keypoints' camera frame (a SLAM
            system transforms its world map points with the keyframe's pose first); NaN rows
            mean "no map point".
        noise: noise model giving sigmas where ``sigma_depth`` does not.
        octaves: (N,) pyramid level of each keypoint.
        sigma_depth: (N,) depth sigmas from the SLAM system (NaN: use the model).

    Returns:
        (N,) points; rows that are non-finite or behind the camera become NaN.
    """
    points = np.asarray(points)
    check_array("map points", points, shape=(None, 3))
    if not np.issubdtype(points.dtype, np.floating):
        raise InputError(f"map points: expected a float array, got dtype {points.dtype}")
    xyz = points.astype(np.float64, copy=True)
    with np.errstate(invalid="ignore"):
        bad = ~(np.isfinite(xyz).all(axis=1) & (xyz[:, 2] > 0))
    xyz[bad] = np.nan
    return noise.points(xyz, octaves, sigma_depth)
