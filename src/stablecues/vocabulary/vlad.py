"""VLAD: one global descriptor per image from its local float descriptors (a second retrieval vote).

VLAD (Jegou et al., 2010) sums, for each of K codebook centres, the residuals of the image's
descriptors assigned to that centre, giving a K x D vector. Here, as "All about VLAD"
(Arandjelovic and Zisserman, 2013) recommends, each centre's block is normalised on its own
(intra-normalisation, so a few bursty repeated structures do not dominate) and the whole vector
then made a unit vector; two images' similarity is the dot product of their vectors (cosine).

The codebook is plain k-means (``scripts/make_vlad_codebook.py``) on development descriptors
only; the shipped one (``default:xfeat``) has 32 centres of XFeat's 64 dimensions, so a VLAD
vector has 2048 dimensions (4 KiB stored as float16 with each entry of a map, 8 KiB in memory as
float32 while the map is open).

The loop detector fuses the VLAD similarity with the BoW score (``QueryConfig.vlad``).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from ..errors import ModelError
from ..fileio import read_npy

__all__ = ["DEFAULT_CODEBOOKS", "VladCodebook", "default_codebook", "load_codebook", "vlad_similarity"]

#: the shipped codebook of each learned extractor (``src/stablecues/data``)
DEFAULT_CODEBOOKS = {"xfeat": "vlad_xfeat_k32.npy"}

#: the largest codebook read: centres x dimensions (a codebook file is a few KiB to a few MiB)
MAX_CODEBOOK_VALUES = 1 << 22


@dataclass(frozen=True)
class VladCodebook:
    """K float32 centres of D dimensions, and where they came from.

    Attributes:
        centres: (K, D) float32 centres (k-means on unit descriptors).
        source: the file they were read from (or a label), for messages and run records.
    """

    centres: np.ndarray
    source: str = "memory"

    def __post_init__(self) -> None:
        c = self.centres
        if not isinstance(c, np.ndarray) or c.ndim != 2 or c.shape[0] < 1 or c.shape[1] < 1:
            raise ModelError(f"VLAD codebook {self.source}: expected a (K, D) array of centres, got "
                             f"{getattr(c, 'shape', type(c).__name__)}")
        if c.dtype.kind != "f" or not np.isfinite(c).all():
            raise ModelError(f"VLAD codebook {self.source}: expected finite float centres")
        centres = np.ascontiguousarray(c, np.float32)
        centres.flags.writeable = False
        object.__setattr__(self, "centres", centres)
        half = 0.5 * np.einsum("ij,ij->i", centres, centres)
        object.__setattr__(self, "_half_norms", half.astype(np.float32))

    @property
    def k(self) -> int:
        return int(self.centres.shape[0])

    @property
    def dim(self) -> int:
        """Dimensions of one local descriptor."""
        return int(self.centres.shape[1])

    @property
    def size(self) -> int:
        """Dimensions of one VLAD vector (K x D)."""
        return self.k * self.dim

    @property
    def fingerprint(self) -> str:
        """SHA-256 of the centres' float32 bytes (shape included)."""
        h = hashlib.sha256(f"{self.k}x{self.dim}".encode())
        h.update(self.centres.tobytes())
        return h.hexdigest()

    def encode(self, descriptors: np.ndarray) -> np.ndarray:
        """The VLAD vector of one image's descriptors.

        Args:
            descriptors: (N, D) float descriptors (made unit vectors here, as the centres were
                trained on unit descriptors).

        Returns:
            (K * D,) float32 unit vector; all zeros for an image without descriptors.

        Raises:
            ModelError: descriptors of another dimension than the codebook's.
        """
        x = np.asarray(descriptors)
        if x.ndim != 2 or x.shape[1] != self.dim or x.dtype.kind not in "fiu":
            raise ModelError(f"VLAD codebook {self.source}: expected (N, {self.dim}) float descriptors, "
                             f"got {x.shape} {x.dtype}")
        out = np.zeros((self.k, self.dim), np.float32)
        if x.shape[0] == 0:
            return out.reshape(-1)
        x = x.astype(np.float32)
        x /= np.maximum(np.sqrt(np.einsum("ij,ij->i", x, x)), 1e-12)[:, None]
        # nearest centre: argmin |x - c|^2 = argmax x.c - |c|^2 / 2
        nearest = np.argmax(x @ self.centres.T - self._half_norms, axis=1)  # type: ignore[attr-defined]
        onehot = np.zeros((self.k, x.shape[0]), np.float32)
        onehot[nearest, np.arange(x.shape[0])] = 1.0
        out = onehot @ x - onehot.sum(axis=1)[:, None] * self.centres  # residual sums
        norms = np.sqrt(np.einsum("ij,ij->i", out, out))
        out /= np.where(norms > 0, norms, 1.0)[:, None]  # intra-normalisation
        flat = out.reshape(-1)
        total = float(np.sqrt(flat @ flat))
        return flat / total if total > 0 else flat


def vlad_similarity(query: np.ndarray, stored: np.ndarray) -> np.ndarray:
    """Cosine similarity of a query's VLAD vector with each row of ``stored`` (unit vectors):
    (N,) float32 in [-1, 1]; an all-zero vector (no descriptors) is 0 to everything."""
    return np.asarray(stored @ np.asarray(query, np.float32), np.float32)


def load_codebook(path: str | Path) -> VladCodebook:
    """Read a codebook: a ``.npy`` file of (K, D) float centres (no pickled objects; the header
    checked against the file's size before anything is read).

    Raises:
        ModelError: a missing, truncated or malformed file, named, in one line.
    """
    p = Path(path)
    if p.is_dir():
        raise ModelError(f"VLAD codebook {p}: is a folder, expected a .npy file")
    centres = read_npy(p, "VLAD codebook", error=ModelError, max_side=MAX_CODEBOOK_VALUES)
    if centres.ndim != 2 or centres.dtype.kind != "f" or centres.size > MAX_CODEBOOK_VALUES:
        raise ModelError(f"VLAD codebook {p}: expected a (K, D) float array of at most "
                         f"{MAX_CODEBOOK_VALUES} values, got {centres.shape} {centres.dtype}")
    return VladCodebook(np.asarray(centres), str(p))


def _data_path(name: str) -> Path:
    return Path(str(resources.files("stablecues") / "data" / name))


def default_codebook(extractor: str) -> VladCodebook:
    """The shipped codebook of a learned extractor (``xfeat``)."""
    name = DEFAULT_CODEBOOKS.get(extractor)
    if name is None:
        raise ModelError(f"no shipped VLAD codebook for {extractor!r} features; known: "
                         f"{', '.join(sorted(DEFAULT_CODEBOOKS))} (or give a codebook file)")
    return load_codebook(_data_path(name))


def codebook_provenance(extractor: str) -> dict[str, object]:
    """The shipped codebook's provenance JSON (beside it), {} when absent."""
    name = DEFAULT_CODEBOOKS.get(extractor)
    if name is None:
        return {}
    p = _data_path(name).with_suffix(".json")
    try:
        out = json.loads(p.read_text())
    except (OSError, ValueError):
        return {}
    return out if isinstance(out, dict) else {}
