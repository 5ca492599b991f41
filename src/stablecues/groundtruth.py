"""Loop ground truth: the project convention, loading every published form, and from poses.

Convention for every loop ground truth in stablecues: an (N, N) ``bool`` array ``gt`` with
``gt[i, j]`` True when query frame ``i`` closes a loop with the EARLIER frame ``j`` (``j < i``),
so the matrix is strictly lower-triangular. It is saved as ``.npy``.

Files read by :func:`load_ground_truth`:

* ``.mat`` (MATLAB v5 through :mod:`stablecues.matfile`, v4 through ``scipy.io.loadmat``):
  the variable is found automatically (the only
  2-D numeric array, else the largest) or named with ``variable=``. Nonzero cells are loops.
  Files stored upper-triangular (``j > i``) are transposed; symmetric ones keep their lower
  half; the diagonal (a frame with itself) is dropped. MATLAB v7.3 (HDF5) files are read with
  ``h5py`` when it is installed (none of the classic benchmark files is v7.3).
* ``.npy`` / ``.npz``: a 2-D numeric or bool matrix, oriented the same way; or the VPR-Bench
  object array ``ground_truth_new.npy`` (rows ``[query i, [ref ids]]``), mapped to the combined
  sequence "all reference images, then all queries" (query ``i`` is frame ``n_ref + i``). That
  file is a pickle: it is read by a restricted unpickler that builds numpy arrays, lists and
  integers only (:func:`stablecues.fileio.read_npy`), never by ``allow_pickle=True``.

Every reader sizes what it allocates from the file's bytes and the limits of
:mod:`stablecues.limits` (at most ``MAX_LOOP_FRAMES`` frames); an all-NaN matrix is refused.
* images (``.png``, ``.bmp``, ``.pgm``, ``.tif``): N x N, nonzero pixel = loop.

Interleaved two-camera releases (FAB-MAP New College and City Centre: image 1 left, image 2
right, image 3 left, ...; 0-based: even index = left camera) are reduced with ``view=``:
``"left"`` keeps ``gt[0::2, 0::2]``, ``"right"`` ``gt[1::2, 1::2]``, ``"pair"`` makes one frame per
left/right pair with a loop when any image of pair ``i`` matches any image of an earlier pair,
and ``"all"`` (default) keeps the matrix as stored.
"""

from __future__ import annotations

import hashlib
import logging
import math
import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from .errors import DatasetError, InputError, check_array, reason
from .fileio import read_npy, read_npz
from .imageio import list_images, read_image
from .limits import MAX_GT_IMAGE_PIXELS, MAX_LOOP_FRAMES, check_loop_frames
from .matfile import is_mat5, read_mat5

logger = logging.getLogger(__name__)

View = Literal["all", "left", "right", "pair"]
Orientation = Literal["auto", "lower", "upper"]
# lossless image formats only: a JPEG's artefacts would invent loops
LOSSLESS_SUFFIXES = (".png", ".bmp", ".pgm", ".tif", ".tiff")


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """A loop matrix and where it came from.

    Attributes:
        matrix: (N, N) bool strictly lower-triangular loop matrix (the project convention).
        path: the file it was read from, or None (made from poses, or in memory).
        sha256: hex SHA-256 of that file, or None.
        variable: the variable / array name inside the file, or None.
        transposed: True when the file was upper-triangular and was transposed.
        view: which images of an interleaved two-camera release were kept ("all" if none).
        query_mask: (N,) bool frames that count as queries (two-pass sets: the query pass
            only), or None when every frame is a query.
        notes: other things done while loading (diagonal dropped, symmetric, ...).
    """

    matrix: np.ndarray
    path: Path | None = None
    sha256: str | None = None
    variable: str | None = None
    transposed: bool = False
    view: str = "all"
    query_mask: np.ndarray | None = None
    notes: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_loop_matrix(self.matrix)
        if self.query_mask is not None:
            check_array("query_mask", self.query_mask, dtype=bool, shape=(self.n,))

    @property
    def n(self) -> int:
        """Number of frames."""
        return int(self.matrix.shape[0])

    def provenance(self) -> dict[str, Any]:
        """JSON-ready description: file, hash, variable, orientation, view, size and loop counts."""
        return {
            "gt_file": None if self.path is None else str(self.path),
            "gt_sha256": self.sha256,
            "gt_variable": self.variable,
            "gt_transposed": self.transposed,
            "gt_view": self.view,
            "gt_frames": self.n,
            "gt_loops": int(np.count_nonzero(self.matrix)),
            "gt_rows_with_loops": int(np.count_nonzero(self.matrix.any(axis=1))),
            "gt_queries": self.n if self.query_mask is None else int(self.query_mask.sum()),
            "gt_notes": dict(self.notes),
        }


def check_loop_matrix(matrix: object, name: str = "ground truth") -> None:
    """Raise :class:`InputError` unless ``matrix`` is an (N, N) bool strictly lower-triangular array."""
    check_array(name, matrix, dtype=bool, ndim=2)
    assert isinstance(matrix, np.ndarray)
    if matrix.shape[0] != matrix.shape[1]:
        raise InputError(f"{name}: expected a square N x N matrix, got shape {matrix.shape}")
    rows, cols = np.nonzero(matrix)
    bad = int(np.count_nonzero(cols >= rows))
    if bad:
        raise InputError(
            f"{name}: expected loops only below the diagonal (gt[i, j], j < i), found {bad} on or above it"
        )


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with Path(path).open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def save_ground_truth(path: str | Path, matrix: np.ndarray) -> Path:
    """Save a loop matrix as ``.npy`` after checking it follows the convention.

    Returns:
        The path written.
    """
    check_loop_matrix(matrix)
    p = Path(path)
    np.save(p, matrix)
    return p if p.suffix == ".npy" else p.with_name(p.name + ".npy")


def orient(
    matrix: Any, *, orientation: Orientation = "auto", source: str = "ground truth"
) -> tuple[np.ndarray, bool, dict[str, Any]]:
    """Turn any square matrix of loops (nonzero = loop) into the lower-triangular convention.

    Args:
        matrix: (N, N) numeric or bool array, or a SciPy sparse matrix.
        orientation: "auto" (transpose when all loops lie above the diagonal; keep the lower
            half of a symmetric matrix; refuse a matrix with loops on both sides otherwise),
            "lower" (keep the part below the diagonal), "upper" (transpose, then the same).
        source: name for messages (the file).

    Returns:
        ((N, N) bool matrix, whether it was transposed, notes).

    Raises:
        DatasetError: not square, or loops on both sides of a non-symmetric matrix in "auto".
    """
    shape = tuple(matrix.shape)
    if len(shape) != 2 or shape[0] != shape[1]:
        raise DatasetError(f"{source}: expected a square N x N loop matrix, found shape {shape}")
    n = int(shape[0])
    check_loop_frames(n, source)
    if hasattr(matrix, "tocoo"):  # scipy.sparse
        coo = matrix.tocoo()
        keep = coo.data != 0
        rows, cols = coo.row[keep].astype(np.int64), coo.col[keep].astype(np.int64)
    else:
        arr = np.asarray(matrix)
        if arr.dtype.kind not in "biuf":
            raise DatasetError(f"{source}: expected a numeric loop matrix, found dtype {arr.dtype}")
        rows, cols = _nonzero_indices(arr)
        if rows.size == 0 and arr.dtype.kind == "f" and arr.size and _all_nan(arr):
            raise DatasetError(f"{source}: expected a loop matrix of 0/1 values, found only NaN")
    notes: dict[str, Any] = {}
    diag = rows == cols
    if diag.any():
        notes["dropped_diagonal"] = int(diag.sum())
        rows, cols = rows[~diag], cols[~diag]
    lower = rows > cols
    n_lower, n_upper = int(lower.sum()), int((~lower).sum())
    transposed = False
    if orientation == "upper" or (orientation == "auto" and n_lower == 0 and n_upper > 0):
        rows, cols = cols, rows
        lower = ~lower
        transposed = True
    elif orientation == "auto" and n_lower and n_upper:
        low = set(zip(rows[lower].tolist(), cols[lower].tolist(), strict=True))
        up = set(zip(cols[~lower].tolist(), rows[~lower].tolist(), strict=True))
        if low != up:
            raise DatasetError(
                f"{source}: loops on both sides of the diagonal ({n_lower} below, {n_upper} above) and "
                "not symmetric; say which half to use (orientation 'lower' or 'upper')"
            )
        notes["symmetric"] = True
    elif orientation not in ("auto", "lower", "upper"):
        raise DatasetError(f"orientation: expected 'auto', 'lower' or 'upper', got {orientation!r}")
    dropped = int((~lower).sum())
    if dropped and not notes.get("symmetric"):
        notes["dropped_other_half"] = dropped
        logger.warning("%s: dropped %d loops on the other side of the diagonal", source, dropped)
    out = np.zeros((n, n), dtype=bool)
    out[rows[lower], cols[lower]] = True
    return out, transposed, notes


def _all_nan(arr: np.ndarray) -> bool:
    """True when every cell of a float matrix is NaN (checked a block of rows at a time)."""
    return all(np.isnan(arr[k : k + _ROW_BLOCK]).all() for k in range(0, arr.shape[0], _ROW_BLOCK))


def _nonzero_indices(arr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.nonzero`` for a 2-D array, fast on large, sparse, C- or Fortran-ordered matrices.

    MATLAB files load in Fortran order, where ``np.nonzero`` is slow (12 s for the 26335^2
    Bicocca matrix); scanning the memory in order, 8 bytes at a time for byte-sized dtypes,
    takes well under a second. NaN cells count as zero.
    """
    order: Literal["C", "F"]
    if arr.flags.c_contiguous:
        order = "C"
    elif arr.flags.f_contiguous:
        order = "F"
    else:
        r, c = np.nonzero(np.nan_to_num(arr) if arr.dtype.kind == "f" else arr)
        return r.astype(np.int64), c.astype(np.int64)
    flat_view = arr.ravel(order=order)  # no copy: memory order
    if flat_view.dtype.itemsize == 1:
        v = flat_view.view(np.uint8)
        whole = v.size // 8 * 8
        blocks = np.flatnonzero(v[:whole].view(np.uint64))
        cand = np.concatenate([(blocks[:, None] * 8 + np.arange(8)).ravel(), np.arange(whole, v.size)])
        flat = cand[v[cand] != 0]
    elif flat_view.dtype.kind == "f":
        flat = np.flatnonzero(np.nan_to_num(flat_view))
    else:
        flat = np.flatnonzero(flat_view)
    n_rows, n_cols = arr.shape
    if order == "C":
        rows, cols = np.divmod(flat, n_cols)
    else:
        cols, rows = np.divmod(flat, n_rows)
    return rows.astype(np.int64), cols.astype(np.int64)


def select_view(matrix: np.ndarray, view: View) -> np.ndarray:
    """Reduce the loop matrix of an interleaved left/right release (0-based even index = left).

    Args:
        matrix: (2M, 2M) bool lower-triangular matrix (``view="all"`` accepts any N).
        view: "all", "left", "right" or "pair" (see the module docstring).

    Returns:
        (M, M) bool lower-triangular matrix ((N, N) for "all").

    Raises:
        InputError: unknown view, or an odd size for an interleaved view.
    """
    check_array("ground truth", matrix, dtype=bool, ndim=2)
    if view == "all":
        return matrix
    if view not in ("left", "right", "pair"):
        raise InputError(f"view: expected 'all', 'left', 'right' or 'pair', got {view!r}")
    if matrix.shape[0] % 2:
        raise InputError(f"view {view!r} needs an even number of interleaved images, got {matrix.shape[0]}")
    if view == "left":
        return np.ascontiguousarray(matrix[0::2, 0::2])
    if view == "right":
        return np.ascontiguousarray(matrix[1::2, 1::2])
    pair = matrix[0::2, 0::2] | matrix[0::2, 1::2] | matrix[1::2, 0::2] | matrix[1::2, 1::2]
    return np.tril(pair, -1)


def fit_view(gt: GroundTruth, view: View, n_frames: int | None = None) -> GroundTruth:
    """Apply an interleaved-release view to a loaded ground truth, unless it is already per camera.

    Args:
        gt: the ground truth as stored (``view="all"``).
        view: "all", "left", "right" or "pair".
        n_frames: the dataset's frame count, when known: a matrix already of that size (a
            per-camera copy such as ``city_GT_final.mat``) is returned as is.

    Returns:
        The ground truth with the view applied (``gt`` itself when nothing changes).

    Raises:
        DatasetError: the matrix fits neither ``n_frames`` nor twice it.
    """
    if view == "all" or gt.view != "all":
        return gt
    if n_frames is not None and gt.n == n_frames:
        return gt
    if n_frames is not None and gt.n not in (2 * n_frames, 2 * n_frames + 1):
        raise DatasetError(
            f"{gt.path or 'ground truth'}: {gt.n} x {gt.n} fits neither the {n_frames} frames "
            f"nor the {2 * n_frames} interleaved images of view {view!r}"
        )
    even = gt.n - gt.n % 2
    matrix = select_view(np.ascontiguousarray(gt.matrix[:even, :even]), view)
    if gt.query_mask is None:
        mask = None
    elif view == "left":
        mask = np.asarray(gt.query_mask[0:even:2])
    elif view == "right":
        mask = np.asarray(gt.query_mask[1:even:2])
    else:  # "pair": a place counts when either camera's image does
        mask = np.asarray(gt.query_mask[0:even:2] | gt.query_mask[1:even:2])
    return GroundTruth(matrix, gt.path, gt.sha256, gt.variable, gt.transposed, view, mask, dict(gt.notes))


def vprbench_matrix(
    table: np.ndarray, n_ref: int | None = None, *, source: str = "ground_truth_new.npy"
) -> tuple[np.ndarray, np.ndarray]:
    """Loop matrix of a two-pass VPR-Bench set evaluated as one sequence.

    The sequence is all ``n_ref`` reference images, then the ``Q`` queries: query ``i`` is frame
    ``n_ref + i`` and closes a loop with reference frame ``r`` for each ``r`` in its row. Ids of
    -1 (no match) are ignored.

    Args:
        table: (Q, 2) object array, rows ``[query i, list of ref ids]``.
        n_ref: number of reference images; None takes the largest id + 1.
        source: name for messages.

    Returns:
        ((n_ref + Q, n_ref + Q) bool loop matrix, (n_ref + Q,) bool query mask).

    Raises:
        DatasetError: malformed rows, or a reference id outside ``[0, n_ref)``.
    """
    if table.ndim != 2 or table.shape[1] != 2:
        raise DatasetError(
            f"{source}: expected rows [query id, [ref ids]] (Q x 2), found shape {table.shape}"
        )
    refs: list[np.ndarray] = []
    queries: list[int] = []
    for k, (q, ids) in enumerate(table):
        row = _table_ids(ids)
        if row is None or not _is_int(q):
            raise DatasetError(
                f"{source}: row {k}: expected [query id, [ref ids]] (a whole number and a flat list of "
                f"whole numbers), found [{type(q).__name__}, {type(ids).__name__}]"
            )
        queries.append(int(q))
        refs.append(row)
    nq = len(queries)
    if sorted(queries) != list(range(nq)):
        raise DatasetError(f"{source}: expected query ids 0..{nq - 1}, found {queries[:5]}...")
    largest = max((int(r.max()) for r in refs if r.size), default=-1)
    if n_ref is None:
        n_ref = largest + 1
    if largest >= n_ref:
        raise DatasetError(f"{source}: reference id {largest} out of range for {n_ref} reference images")
    n = n_ref + nq
    check_loop_frames(n, source)
    gt = np.zeros((n, n), dtype=bool)
    for q, r in zip(queries, refs, strict=True):
        r = r[r >= 0]
        gt[n_ref + q, r] = True
    mask = np.zeros(n, dtype=bool)
    mask[n_ref:] = True
    return gt, mask


def _is_int(value: object) -> bool:
    """A whole number that fits an int64 (not a bool)."""
    return (
        isinstance(value, int | np.integer)
        and not isinstance(value, bool | np.bool_)
        and -(2**63) <= int(value) < 2**63
    )


def _table_ids(ids: object) -> np.ndarray | None:
    """(K,) int64 reference ids of a VPR-Bench row: an int, a flat list of ints or a 1-D int
    array; None for anything else (nested lists are refused before numpy could expand them)."""
    if _is_int(ids):
        return np.array([int(ids)], dtype=np.int64)  # type: ignore[call-overload]
    if isinstance(ids, np.ndarray):
        if ids.ndim > 1 or ids.dtype.kind not in "iu":
            return None
        return np.atleast_1d(ids.astype(np.int64))
    if isinstance(ids, list | tuple) and all(_is_int(v) for v in ids):
        return np.asarray([int(v) for v in ids], dtype=np.int64)
    return None


def load_ground_truth(
    path: str | Path,
    *,
    variable: str | None = None,
    orientation: Orientation = "auto",
    view: View = "all",
    n_ref: int | None = None,
) -> GroundTruth:
    """Read a loop ground-truth file into the project convention, with its provenance.

    Args:
        path: ``.mat``, ``.npy``, ``.npz`` or an image (see the module docstring).
        variable: name of the variable in a ``.mat`` / ``.npz``; None finds it.
        orientation: see :func:`orient`.
        view: for interleaved two-camera releases; see :func:`select_view`.
        n_ref: reference images of a VPR-Bench ``ground_truth_new.npy``; None counts the
            ``ref/`` folder beside the file, else takes the largest id + 1.

    Returns:
        The :class:`GroundTruth`.

    Raises:
        DatasetError: missing, unreadable or malformed file.
    """
    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"{p}: ground-truth file not found")
    suffix = p.suffix.lower()
    query_mask = None
    if suffix == ".mat":
        raw, name = _read_mat(p, variable)
    elif suffix == ".npz":
        raw, name = _read_npz(p, variable)
    elif suffix == ".npy":
        raw = _read_npy(p)
        name = None
        if raw.dtype == object:
            if n_ref is None and (p.parent / "ref").is_dir():
                n_ref = len(list_images(p.parent / "ref"))
            gt, query_mask = vprbench_matrix(raw, n_ref, source=str(p))
            gt = select_view(gt, view)
            return GroundTruth(
                gt,
                p,
                sha256_file(p),
                None,
                False,
                view,
                query_mask if view == "all" else None,
                {"format": "vprbench", "n_ref": int(query_mask.size - query_mask.sum())},
            )
    elif suffix in LOSSLESS_SUFFIXES:
        raw, name = _read_image(p), None
    else:
        raise DatasetError(f"{p}: expected a .mat, .npy, .npz or image (.png, .bmp) ground-truth file")
    matrix, transposed, notes = orient(raw, orientation=orientation, source=str(p))
    del raw
    matrix = select_view(matrix, view)
    return GroundTruth(matrix, p, sha256_file(p), name, transposed, view, query_mask, notes)


def _pick(arrays: Mapping[str, Any], source: Path, variable: str | None) -> tuple[Any, str]:
    if variable is not None:
        if variable not in arrays:
            raise DatasetError(f"{source}: no variable {variable!r}; found {sorted(arrays)}")
        if arrays[variable] is None:
            raise DatasetError(f"{source}: variable {variable!r} is not a numeric matrix")
        return arrays[variable], variable
    cands = {
        k: v
        for k, v in arrays.items()
        if not k.startswith("__")
        and v is not None
        and len(getattr(v, "shape", ())) == 2
        and (hasattr(v, "tocoo") or np.asarray(v).dtype.kind in "biuf")
    }
    if not cands:
        raise DatasetError(f"{source}: expected a 2-D numeric loop matrix, found variables {sorted(arrays)}")
    name = max(cands, key=lambda k: int(np.prod(cands[k].shape)))
    if len(cands) > 1:
        logger.info("%s: several 2-D arrays %s; using the largest, %r", source, sorted(cands), name)
    return cands[name], name


_MAT_ERRORS = (
    ValueError, TypeError, OSError, IndexError, KeyError, EOFError, AttributeError, OverflowError,
    UnicodeDecodeError, RecursionError, zlib.error, struct.error,
)  # fmt: skip


def _read_mat(path: Path, variable: str | None) -> tuple[Any, str]:
    """A MATLAB file's loop matrix: v5 (v6, v7) through :mod:`stablecues.matfile`, never
    SciPy's compiled reader (which a crafted file can crash); v4 through SciPy's pure-Python
    reader; v7.3 (HDF5) through h5py."""
    with path.open("rb") as fh:
        head = fh.read(128)
    if len(head) == 128 and head[126:128] in (b"IM", b"MI") and 2 in head[124:126]:
        return _read_mat73(path, variable)
    if is_mat5(head):
        arrays = read_mat5(path, max_elements=MAX_LOOP_FRAMES**2)
        return _pick(arrays, path, variable)
    if len(head) < 4 or 0 not in head[:4]:  # SciPy takes a file for v4 when its first 4 bytes hold a 0
        raise DatasetError(f"{path}: not a MATLAB file (no v4, v5 or v7.3 header)")
    return _read_mat4(path, variable)


def _read_mat4(path: Path, variable: str | None) -> tuple[Any, str]:
    import scipy.io

    try:
        infos = scipy.io.whosmat(str(path))
        for name, shape, _ in infos:
            if math.prod(shape) > MAX_LOOP_FRAMES**2:
                raise DatasetError(
                    f"{path}: variable {name!r} of shape {shape} is larger than the "
                    f"{MAX_LOOP_FRAMES} x {MAX_LOOP_FRAMES} accepted (stablecues.limits)"
                )
        data = scipy.io.loadmat(str(path))
    except (*_MAT_ERRORS, scipy.io.matlab.MatReadError, NotImplementedError) as exc:
        raise DatasetError(f"{path}: not a readable MATLAB file ({reason(exc)})") from None
    return _pick(data, path, variable)


def _read_mat73(path: Path, variable: str | None) -> tuple[Any, str]:
    try:
        import h5py
    except ImportError:
        raise DatasetError(
            f"{path}: a MATLAB v7.3 (HDF5) file; install h5py to read it (pip install h5py)"
        ) from None
    try:
        with h5py.File(path, "r") as fh:
            datasets = {
                k if isinstance(k, str) else bytes(k).decode("utf-8", errors="replace"): v
                for k, v in fh.items()
                if isinstance(v, h5py.Dataset)
            }
            # numeric datasets within the limits only (a larger one could not be a loop matrix);
            # MATLAB stores column-major: the HDF5 dataset is the transpose of the MATLAB matrix
            arrays = {
                k: np.asarray(v[()]).T
                for k, v in datasets.items()
                if v.dtype.kind in "biuf" and math.prod(v.shape or ()) <= MAX_LOOP_FRAMES**2
            }
    except (OSError, RuntimeError, *_MAT_ERRORS) as exc:  # h5py raises RuntimeError too
        raise DatasetError(f"{path}: not a readable MATLAB v7.3 (HDF5) file ({reason(exc)})") from None
    return _pick(arrays, path, variable)


def _read_npy(path: Path) -> np.ndarray:
    """A .npy array, never unpickling arbitrary objects: an object array (the VPR-Bench table)
    goes through the restricted unpickler of :func:`stablecues.fileio.read_npy`."""
    return read_npy(path, "ground truth", objects=True, max_side=MAX_LOOP_FRAMES)


def _read_npz(path: Path, variable: str | None) -> tuple[Any, str]:
    arrays = read_npz(path, "ground truth", max_bytes=8 * MAX_LOOP_FRAMES**2)
    return _pick(arrays, path, variable)


def _read_image(path: Path) -> np.ndarray:
    image = read_image(path, "unchanged", max_pixels=MAX_GT_IMAGE_PIXELS)
    # colour images: any colour channel set (an alpha channel is not a loop)
    return np.asarray(image[..., :3].any(axis=2)) if image.ndim == 3 else np.asarray(image)


def ground_truth_from_poses(positions: np.ndarray, *, max_distance: float, **kwargs: Any) -> GroundTruth:
    """:func:`loops_from_poses` wrapped as a :class:`GroundTruth` whose notes hold the settings."""
    matrix = loops_from_poses(positions, max_distance=max_distance, **kwargs)
    settings = {"max_distance": max_distance, **{k: v for k, v in kwargs.items() if np.isscalar(v)}}
    return GroundTruth(matrix, notes={"from_poses": settings})


def _check_loop_thresholds(
    max_distance: float,
    min_gap_s: float,
    min_gap_frames: int,
    yaws: np.ndarray | None,
    max_angle_deg: float | None,
    times: np.ndarray | None,
) -> None:
    """Check the options of :func:`loops_from_poses` that need no array.

    Raises:
        InputError: a negative or non-finite distance, negative gaps, ``yaws`` without
            ``max_angle_deg`` (or the reverse), or ``min_gap_s`` without ``times``.
    """
    if not np.isfinite(max_distance) or max_distance < 0:
        raise InputError(f"max_distance: expected a finite value >= 0, got {max_distance}")
    if min_gap_s < 0 or min_gap_frames < 0:
        raise InputError(f"min gaps must be >= 0, got min_gap_s={min_gap_s}, min_gap_frames={min_gap_frames}")
    if (yaws is None) != (max_angle_deg is None):
        raise InputError("orientations (yaws or rotations) and max_angle_deg must be given together")
    if times is None and min_gap_s > 0:
        raise InputError(f"min_gap_s={min_gap_s} needs times")


def _yaw_test(
    yaws: np.ndarray | None, max_angle_deg: float | None, n: int
) -> tuple[np.ndarray | None, float]:
    """(N,) float64 yaws and the cosine limit of the yaw test; (None, -2.0) when not used.

    ``|wrapped difference| <= a`` is tested as ``cos(difference) >= cos(a)`` for a in [0, 180].

    Raises:
        InputError: yaws of the wrong shape, or a negative or NaN ``max_angle_deg``.
    """
    if yaws is None or max_angle_deg is None:
        return None, -2.0
    yaw_arr = np.asarray(yaws, dtype=np.float64)
    check_array("yaws", yaw_arr, shape=(n,))
    if not max_angle_deg >= 0:  # also rejects NaN
        raise InputError(f"max_angle_deg: expected >= 0, got {max_angle_deg}")
    return yaw_arr, float(np.cos(np.radians(min(max_angle_deg, 180.0))))


_ROW_BLOCK = 512  # rows per block when building matrices from poses (bounds the memory)


def loops_from_poses(
    positions: np.ndarray,
    *,
    max_distance: float,
    yaws: np.ndarray | None = None,
    max_angle_deg: float | None = None,
    times: np.ndarray | None = None,
    min_gap_s: float = 0.0,
    min_gap_frames: int = 0,
    rotations: np.ndarray | None = None,
) -> np.ndarray:
    """Loop ground truth from camera positions: frames close in space but apart in time.

    ``gt[i, j]`` is True when ``j < i`` and all of these hold:

    * ``||positions[i] - positions[j]|| <= max_distance`` (Euclidean, in the positions' unit);
    * if ``yaws`` and ``max_angle_deg`` are given: the absolute yaw difference, wrapped to
      [0, 180] degrees, is ``<= max_angle_deg``;
    * if ``rotations`` and ``max_angle_deg`` are given instead: the angle of the relative
      rotation ``R_j^T R_i`` (how far one camera turns to look as the other; the same for the
      body frame and any camera rigidly on it) is ``<= max_angle_deg``;
    * if ``times`` is given: ``times[i] - times[j] >= min_gap_s``;
    * ``i - j >= min_gap_frames``.

    Frames with a NaN position (or NaN yaw / time when those are used) close no loop.

    Args:
        positions: (N, 3) float camera positions (any float dtype; ints are accepted too).
        max_distance: distance threshold, same unit as ``positions``; must be >= 0.
        yaws: (N,) float heading of each frame in RADIANS, or None to ignore orientation.
        max_angle_deg: largest yaw difference in degrees for a loop; needs ``yaws``.
        times: (N,) float timestamps in seconds, or None (then ``min_gap_s`` must be 0).
        min_gap_s: smallest time between the two frames of a loop, seconds.
        min_gap_frames: smallest index difference between the two frames of a loop.
        rotations: (N, 3, 3) float orientations (any frame, the same for all), or None; with
            ``max_angle_deg`` and in place of ``yaws``.

    Returns:
        (N, N) bool strictly lower-triangular loop matrix.

    Raises:
        InputError: on wrong shapes, negative thresholds or inconsistent options.
    """
    positions = np.asarray(positions)
    check_array("positions", positions, shape=(None, 3))
    if not np.issubdtype(positions.dtype, np.number):
        raise InputError(f"positions: expected a numeric array, got dtype {positions.dtype}")
    n = positions.shape[0]
    if rotations is not None and yaws is not None:
        raise InputError("give yaws or rotations, not both")
    _check_loop_thresholds(max_distance, min_gap_s, min_gap_frames,
                           yaws if rotations is None else rotations, max_angle_deg, times)
    pos = positions.astype(np.float64)
    valid = np.all(np.isfinite(pos), axis=1)
    rot: np.ndarray | None = None
    if rotations is not None:
        rot = np.asarray(rotations, dtype=np.float64)
        check_array("rotations", rot, shape=(n, 3, 3))
        valid &= np.isfinite(rot).all(axis=(1, 2))
        rot = np.where(valid[:, None, None], rot, 0.0)
        _, cos_limit = _yaw_test(np.zeros(n), max_angle_deg, n)
        yaw_arr = None
    else:
        yaw_arr, cos_limit = _yaw_test(yaws, max_angle_deg, n)
    if yaw_arr is not None:
        valid &= np.isfinite(yaw_arr)
    time_arr: np.ndarray | None = None
    if times is not None:
        time_arr = np.asarray(times, dtype=np.float64)
        check_array("times", time_arr, shape=(n,))
        valid &= np.isfinite(time_arr)

    check_loop_frames(n, "positions", InputError)
    gt = np.zeros((n, n), dtype=bool)
    if n == 0:
        return gt
    pos = np.where(valid[:, None], pos, 0.0)
    cols = np.arange(n)
    limit2 = float(max_distance) ** 2
    # rows per block: 512, fewer for long trajectories (a block's temporaries stay near 100 MB)
    step = max(1, min(_ROW_BLOCK, (1 << 22) // n))
    for start in range(0, n, step):
        stop = min(start + step, n)
        rows = np.arange(start, stop)
        diff = pos[start:stop, None, :] - pos[None, :stop, :]
        block = np.einsum("ijk,ijk->ij", diff, diff) <= limit2
        block &= rows[:, None] - cols[None, :stop] >= max(min_gap_frames, 1)
        block &= valid[start:stop, None] & valid[None, :stop]
        if yaw_arr is not None:
            block &= np.cos(yaw_arr[start:stop, None] - yaw_arr[None, :stop]) >= cos_limit - 1e-12
        if rot is not None:  # cos of the relative rotation's angle: (trace(R_j^T R_i) - 1) / 2
            trace = np.einsum("ikl,jkl->ij", rot[start:stop], rot[:stop])
            block &= (trace - 1.0) / 2.0 >= cos_limit - 1e-12
        if time_arr is not None:
            block &= time_arr[start:stop, None] - time_arr[None, :stop] >= min_gap_s
        gt[start:stop, :stop] = block
    return gt
