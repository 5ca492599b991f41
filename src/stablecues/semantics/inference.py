"""Inference of the shipped segmentation network through onnxruntime, with MC dropout.

``SegmentationModel.load()`` opens the weights shipped in ``stablecues/data`` (or a given file),
``predict(image, T)`` segments a frame of any size:

- ``T = 1``: one deterministic pass, dropout off (the network's standard "weight averaging"
  prediction); the uncertainty is zero everywhere.
- ``T >= 2``: Bayesian SegNet's Monte-Carlo dropout. The deterministic encoder runs once and only
  the decoder runs on a batch of T dropout masks (see :mod:`stablecues.semantics.model`). The masks
  come from a generator seeded by ``(seed, T, size)`` and are reused for every frame, so a result
  is a pure function of the image, T and the seed.

Uncertainty (documented choice): the variance over the T samples of the softmax probability of
the winning class (the class with the highest mean softmax), as in Bayesian SegNet's per-class
variance read at the chosen class. Its range is [0, 0.25]. ``uncertainty="mutual_information"``
gives the BALD mutual information (entropy of the mean minus mean entropy, in nats) instead.
"""

from __future__ import annotations

import importlib.resources
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import ConfigError, InputError, ModelError
from ..onnxsession import default_threads, open_session, set_default_threads  # noqa: F401 (their old home)
from ..vocabulary.engine import compiled_kernels, resolve
from .classes import CLASS_NAMES, NUM_CLASSES

log = logging.getLogger(__name__)

DEFAULT_WEIGHTS = "segnet_camvid.onnx"
#: the shipped weights of each precision (the int8 file is made by ``scripts/quantize_segnet.py``)
WEIGHTS = {"float32": DEFAULT_WEIGHTS, "int8": "segnet_camvid_int8.onnx"}
DEFAULT_INPUT_SIZE = (288, 384)
DEFAULT_T = 6
UNCERTAINTY_KINDS = ("variance", "mutual_information")


@dataclass(frozen=True)
class SegmentationResult:
    """Segmentation of one frame, at the frame's own size.

    Attributes:
        labels: (H, W) uint8 class id of the highest mean softmax (0..10, never void).
        confidence: (H, W) float32 highest mean softmax, in [0, 1] (interpolated from the
            network's output resolution).
        uncertainty: (H, W) float32 model uncertainty (see the module docstring); zero for T = 1.
        samples: the number T of Monte-Carlo samples used.
        prob: (11, h, w) float32 mean softmax at the network's output resolution (1/4 of the
            network input), for soft uses such as per-class weights.
    """

    labels: np.ndarray
    confidence: np.ndarray
    uncertainty: np.ndarray
    samples: int
    prob: np.ndarray

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) of the frame."""
        return int(self.labels.shape[1]), int(self.labels.shape[0])

    def frame_certainty(self) -> float:
        """How sure the network is of this frame as a whole, in [0, 1]: the mean over the
        output pixels of ``(max_c p_c - 1/C) / (1 - 1/C)`` (0 for flat posteriors, 1 for sure
        ones). It tells frames of the network's domain from others: on CamVid drives the median
        frame gives 0.86-0.87, on indoor sets (the corridor, TUM desk, Kinect) 0.72-0.77, on
        KITTI and EuRoC 0.79-0.81 (``docs`` and ``semantics.weighting``). Labels handed in
        (no posterior) count as certain: 1.
        """
        prob = self.prob
        if prob.ndim != 3 or prob.shape[0] < 2 or prob.shape[1] < 2 or prob.shape[2] < 2:
            return 1.0
        c = prob.shape[0]
        top = np.asarray(prob.max(axis=0), np.float64)
        return float(np.clip((top.mean() - 1.0 / c) / (1.0 - 1.0 / c), 0.0, 1.0))


def default_weights_path(precision: str = "float32") -> Path:
    """Path of the ONNX weights shipped with the package: ``"float32"`` (as trained) or
    ``"int8"`` (their static int8 quantisation)."""
    if precision not in WEIGHTS:
        raise ConfigError(f"segmentation precision {precision!r}: expected one of {', '.join(WEIGHTS)}")
    return Path(str(importlib.resources.files("stablecues") / "data" / WEIGHTS[precision]))


def _as_rgb(image: np.ndarray, bgr: bool) -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise InputError(f"image: expected a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise InputError(f"image: expected dtype uint8, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        rgb = np.repeat(image[:, :, None], 3, axis=2)
    elif image.ndim == 3 and image.shape[2] in (3, 4):
        code3, code4 = (cv2.COLOR_BGR2RGB, cv2.COLOR_BGRA2RGB) if bgr else (None, cv2.COLOR_RGBA2RGB)
        code = code3 if image.shape[2] == 3 else code4
        rgb = cv2.cvtColor(image, code) if code is not None else image
    else:
        raise InputError(f"image: expected shape HxW or HxWxC with C in 1, 3, 4; got {image.shape}")
    if rgb.shape[0] == 0 or rgb.shape[1] == 0:
        raise InputError(f"image: expected a non-empty image, got shape {image.shape}")
    return rgb


class SegmentationModel:
    """The segmentation network behind an onnxruntime session.

    Use :meth:`load`; the constructor takes an open session.

    Args:
        session: onnxruntime InferenceSession of the exported graph.
        meta: the weights' metadata (``input_size``, ``default_t``, ``dropout_p`` ...).
        path: the ONNX file, for messages.
        seed: seed of the dropout masks.
    """

    def __init__(self, session: Any, meta: dict[str, Any], path: Path, seed: int = 0) -> None:
        self.session = session
        self.meta = meta
        self.path = path
        self.seed = int(seed)
        size = meta.get("input_size", DEFAULT_INPUT_SIZE)
        self.input_size: tuple[int, int] = (int(size[0]), int(size[1]))
        self.default_t = int(meta.get("default_t", DEFAULT_T))
        self.p = float(meta.get("dropout_p", 0.5))
        inputs = {i.name: i.shape for i in session.get_inputs()}
        if set(inputs) != {"image", "mask16", "mask8"}:
            raise ModelError(f"{path}: expected graph inputs image, mask16, mask8; found {sorted(inputs)}")
        self._channels = (int(inputs["mask16"][1]), int(inputs["mask8"][1]))
        out_shape = session.get_outputs()[0].shape
        if len(out_shape) != 4 or out_shape[1] != NUM_CLASSES:
            raise ModelError(f"{path}: expected a (T, {NUM_CLASSES}, h, w) output, found {out_shape}")
        self._masks: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}
        self.class_names: tuple[str, ...] = tuple(meta.get("classes", CLASS_NAMES))

    @classmethod
    def load(
        cls, path: str | Path | None = None, *, threads: int | None = None, seed: int = 0,
        precision: str = "float32",
    ) -> SegmentationModel:
        """Open ONNX weights (the shipped ones of ``precision`` when ``path`` is None), inferring
        on ``threads`` threads (None: :func:`set_default_threads`' value, 2 unless changed).

        The metadata JSON beside the file (same stem) is read when present; without it the
        shipped defaults (input 288x384, T = 6) apply.

        Raises:
            ModelError: the file is missing or not a loadable ONNX graph of this network.
        """
        p = default_weights_path(precision) if path is None else Path(path)
        if not p.is_file():
            raise ModelError(f"{p}: segmentation weights not found (expected an .onnx file)")
        meta: dict[str, Any] = {}
        meta_path = p.with_suffix(".json")
        if meta_path.is_file():
            try:
                meta = json.loads(meta_path.read_text())
            except (OSError, ValueError) as exc:
                raise ModelError(f"{meta_path}: expected JSON metadata, could not parse it ({exc})") from exc
        session = open_session(p, "segmentation graph", threads)
        return cls(session, meta, p, seed=seed)

    # -- Monte-Carlo dropout -----------------------------------------------------------------
    def masks(self, t: int, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """The T dropout masks for a network input of ``height`` x ``width`` (cached).

        T = 1 gives all-ones masks (deterministic pass, dropout off). For T >= 2 each entry is 0
        with probability p and 1/(1-p) otherwise, drawn from ``default_rng([seed, T, h, w])``.

        Returns:
            ((T, c16, h16, w16), (T, c8, h8, w8)) float32.
        """
        key = (t, height, width)
        if key not in self._masks:
            h8, w8 = height, width
            for _ in range(3):
                h8, w8 = (h8 + 1) // 2, (w8 + 1) // 2
            h16, w16 = (h8 + 1) // 2, (w8 + 1) // 2
            s16 = (t, self._channels[0], h16, w16)
            s8 = (t, self._channels[1], h8, w8)
            if t == 1:
                m16, m8 = np.ones(s16, np.float32), np.ones(s8, np.float32)
            else:
                rng = np.random.default_rng([self.seed, t, height, width])
                keep = np.float32(1.0 / (1.0 - self.p))
                m16 = (rng.random(s16, dtype=np.float32) >= self.p).astype(np.float32) * keep
                m8 = (rng.random(s8, dtype=np.float32) >= self.p).astype(np.float32) * keep
            if len(self._masks) > 16:
                self._masks.clear()
            self._masks[key] = (m16, m8)
        return self._masks[key]

    def sample(self, x: np.ndarray, t: int) -> np.ndarray:
        """Run the graph on a prepared input.

        Args:
            x: (1, 3, h, w) float32 RGB in [0, 1].
            t: number of samples (1 = deterministic).

        Returns:
            (T, 11, ceil(h/4), ceil(w/4)) float32 softmax per sample.
        """
        check_t(t)
        m16, m8 = self.masks(t, int(x.shape[2]), int(x.shape[3]))
        (prob,) = self.session.run(None, {"image": x, "mask16": m16, "mask8": m8})
        return np.asarray(prob, dtype=np.float32)

    def predict(
        self,
        image: np.ndarray,
        t: int | None = None,
        *,
        bgr: bool = True,
        uncertainty: str = "variance",
    ) -> SegmentationResult:
        """Segment one frame.

        Args:
            image: (H, W) grey, (H, W, 3) colour or (H, W, 4) uint8 image of any size; colour in
                OpenCV's BGR order unless ``bgr=False``.
            t: Monte-Carlo samples T (None: the weights' default; 1: deterministic).
            bgr: colour channel order of ``image``.
            uncertainty: "variance" (of the winning class's softmax) or "mutual_information".

        Returns:
            The per-pixel result at the image's size.
        """
        if uncertainty not in UNCERTAINTY_KINDS:
            raise ConfigError(f"uncertainty: expected one of {UNCERTAINTY_KINDS}, got {uncertainty!r}")
        t = self.default_t if t is None else int(t)
        rgb = _as_rgb(image, bgr)
        h, w = self.input_size
        interp = cv2.INTER_AREA if rgb.shape[0] > h else cv2.INTER_LINEAR
        x = cv2.resize(rgb, (w, h), interpolation=interp).astype(np.float32) * np.float32(1.0 / 255.0)
        x = np.ascontiguousarray(x.transpose(2, 0, 1)[None])
        probs = self.sample(x, t)
        return summarize_samples(probs, (int(rgb.shape[0]), int(rgb.shape[1])), uncertainty)


def check_t(t: int) -> None:
    """Raise :class:`ConfigError` unless ``t`` is a positive sample count."""
    if int(t) < 1:
        raise ConfigError(f"T: expected at least 1 Monte-Carlo sample, got {t}")


def class_map(hwc: np.ndarray, engine: str = "auto") -> np.ndarray:
    """(H, W) uint8 index of the largest of (H, W, C) float32 finite scores per pixel (the first
    of equal ones): ``hwc.argmax(axis=2)``, in a compiled loop when numba is there (about
    1 ms instead of 2.5-6 ms for 480x360 and 11 classes; ``engine`` as for the vocabulary)."""
    if hwc.dtype == np.float32 and hwc.flags.c_contiguous and resolve(engine) == "compiled":
        kernels = compiled_kernels()
        if kernels is not None:
            out = np.empty(hwc.shape[:2], np.uint8)
            kernels.argmax_channels(hwc, out)
            return out
    return hwc.argmax(axis=2).astype(np.uint8)


def summarize_samples(
    probs: np.ndarray, size: tuple[int, int], uncertainty: str = "variance"
) -> SegmentationResult:
    """Mean, class, confidence and uncertainty of T softmax samples, upsampled to ``size``.

    Args:
        probs: (T, C, h, w) float32 softmax samples.
        size: (height, width) of the output maps.
        uncertainty: "variance" or "mutual_information".
    """
    t = probs.shape[0]
    mean = probs.mean(axis=0) if t > 1 else probs[0]
    if t == 1:
        unc = np.zeros(mean.shape[1:], np.float32)
    elif uncertainty == "variance":
        win = mean.argmax(axis=0)[None, None]
        winner = np.take_along_axis(probs, np.broadcast_to(win, (t, 1) + win.shape[2:]), axis=1)[:, 0]
        unc = winner.var(axis=0).astype(np.float32)
    else:
        eps = np.float32(1e-12)
        h_mean = -(mean * np.log(mean + eps)).sum(axis=0)
        h_each = -(probs * np.log(probs + eps)).sum(axis=1).mean(axis=0)
        unc = np.maximum(h_mean - h_each, 0.0).astype(np.float32)
    height, width = size
    hwc = np.ascontiguousarray(mean.transpose(1, 2, 0))
    up = cv2.resize(hwc, (width, height), interpolation=cv2.INTER_LINEAR)
    labels = class_map(up) if up.ndim == 3 else np.zeros(size, np.uint8)
    # the confidence map is interpolated from the output resolution (cheaper than a gather)
    conf_low = np.ascontiguousarray(mean.max(axis=0))
    confidence = cv2.resize(conf_low, (width, height), interpolation=cv2.INTER_LINEAR).astype(np.float32)
    if t == 1:
        unc_up = np.zeros(size, np.float32)
    else:
        unc_up = np.maximum(cv2.resize(unc, (width, height), interpolation=cv2.INTER_LINEAR), 0.0)
    return SegmentationResult(labels, confidence, unc_up.astype(np.float32), t, np.ascontiguousarray(mean))
