"""What an input file may make stablecues allocate: every limit in one place.

A file is untrusted: its header or its manifest can claim sizes that its bytes do not hold. Every
reader sizes its allocations from what the file can hold (its byte size) and refuses, with one
line naming the file and the limit, whatever would go past the limits below. Each limit is
generous for real data; the table says which real input comes nearest.

=============================== ================ =====================================================
limit                           value            what it bounds (nearest real input)
=============================== ================ =====================================================
``MAX_IMAGE_PIXELS``            2^26 (67 Mpx)    a decoded image, from its header before decoding:
                                                 8192 x 8192 (KITTI 1241 x 376, CamVid 960 x 720)
``MAX_IMAGE_BYTES``             256 MiB          a decoded PNG's bytes from its header (channels x
                                                 bit depth): a 16-bit RGBA 8192 x 8191 PNG in a bag,
                                                 1 MB of file, decoded to 1.7 GB
``MAX_GT_IMAGE_PIXELS``         2^28 (268 Mpx)   a loop ground truth stored as an N x N image
                                                 (N <= 16384)
``MAX_LOOP_FRAMES``             40,000           frames of a dense N x N loop matrix (1.6 GB of bool):
                                                 ground-truth files, VPR-Bench tables, loop truth
                                                 from poses (Bicocca: 26,335)
``MAX_SIMILARITY_FRAMES``       32,768           frames of a run's N x N float32 similarity matrix
                                                 (4 GiB); longer runs need ``--set similarity=false``
``MAX_TEXT_BYTES``              256 MiB          a text file read whole: poses, ``times.txt``,
                                                 ``rgb.txt``, EuRoC ``data.csv``, CSV tables, run files
``MAX_CALIBRATION_BYTES``       1 MiB            a calibration file (real ones: under 10 kB)
``MAX_YAML_DEPTH``              64               nesting of a YAML document (calibration: 3)
``MAX_YAML_VALUES``             100,000          values of a YAML document counted with its aliases
                                                 expanded (an alias bomb is refused, not expanded)
``MAX_PICKLE_BYTES``            64 MiB           the pickled VPR-Bench ``ground_truth_new.npy``
                                                 table (Tokyo247: 112 kB)
``MAX_CSV_FIELD_BYTES``         131,072          one CSV field (Python's own limit, named here)
``MAX_PLOTTED_LOOP_PAIRS``      20,000           loop pairs drawn on a trajectory picture (all of
                                                 them are saved; the picture says how many it drew)
``MAX_BAG_METADATA_BYTES``      4 MiB            a ROS 2 bag's ``metadata.yaml`` (real ones: a few kB;
                                                 YAML parses at about 1 s a megabyte)
``MAX_SWEEP_CELLS``             10,000           configurations a ``sweep`` plans from its ``--vary``
                                                 lists (checked before their product is built)
=============================== ================ =====================================================

Checked the same way, without a number to tune:

* a ``.npy`` file is read only when its header's shape times its item size fits in the bytes
  that follow the header; a pickled array only through the restricted unpickler of
  :mod:`stablecues.fileio`, which builds numpy arrays, lists and integers and nothing else;
* a MATLAB v5 file is walked by :mod:`stablecues.matfile`, every element's size checked
  against the bytes left and a compressed one inflated no further than its matrix needs;
* images are decoded only as PNG, JPEG, BMP, PNM, TIFF or WebP, after their header gave a size
  within the limit (and, for PNG, after every chunk was found to lie within the file);
* a VPR-Bench table's rows must be flat lists of whole numbers (a nested list that numpy would
  expand is refused before numpy sees it).
"""

from __future__ import annotations

from pathlib import Path

from .errors import DatasetError, StableCuesError

__all__ = [
    "MAX_BAG_METADATA_BYTES",
    "MAX_CALIBRATION_BYTES",
    "MAX_CSV_FIELD_BYTES",
    "MAX_GT_IMAGE_PIXELS",
    "MAX_IMAGE_BYTES",
    "MAX_IMAGE_PIXELS",
    "MAX_LOOP_FRAMES",
    "MAX_PICKLE_BYTES",
    "MAX_PLOTTED_LOOP_PAIRS",
    "MAX_SIMILARITY_FRAMES",
    "MAX_SWEEP_CELLS",
    "MAX_TEXT_BYTES",
    "MAX_YAML_DEPTH",
    "MAX_YAML_VALUES",
    "check_file_size",
    "check_loop_frames",
]

MAX_IMAGE_PIXELS = 1 << 26
MAX_IMAGE_BYTES = 1 << 28
MAX_GT_IMAGE_PIXELS = 1 << 28
MAX_LOOP_FRAMES = 40_000
MAX_SIMILARITY_FRAMES = 32_768
MAX_TEXT_BYTES = 256 << 20
MAX_CALIBRATION_BYTES = 1 << 20
MAX_YAML_DEPTH = 64
MAX_YAML_VALUES = 100_000
MAX_PICKLE_BYTES = 64 << 20
MAX_CSV_FIELD_BYTES = 131_072
MAX_PLOTTED_LOOP_PAIRS = 20_000
MAX_SWEEP_CELLS = 10_000
MAX_BAG_METADATA_BYTES = 4 << 20


def _size(n: int) -> str:
    for unit, shift in (("GiB", 30), ("MiB", 20), ("kiB", 10)):
        if n >= 1 << shift:
            return f"{n / (1 << shift):.1f} {unit}"
    return f"{n} bytes"


def check_file_size(
    path: str | Path, limit: int, what: str, error: type[StableCuesError] = DatasetError
) -> int:
    """Raise unless ``path`` is a regular file of at most ``limit`` bytes; return its size.

    Args:
        path: the file.
        limit: the largest size accepted, bytes (one of this module's constants).
        what: what the file is, for the message ("TUM trajectory").
        error: the error class to raise.

    Raises:
        error: the file is missing, not a regular file, or larger than ``limit``.
    """
    p = Path(path)
    if not p.is_file():
        raise error(f"{p}: {what} not found")
    size = p.stat().st_size
    if size > limit:
        raise error(
            f"{p}: {what} of {_size(size)} is larger than the {_size(limit)} accepted "
            "(stablecues.limits)"
        )
    return size


def check_loop_frames(n: int, source: object, error: type[StableCuesError] = DatasetError) -> None:
    """Raise unless a dense N x N loop matrix of ``n`` frames is within :data:`MAX_LOOP_FRAMES`.

    Raises:
        error: ``n`` is negative or larger than the limit.
    """
    if not 0 <= n <= MAX_LOOP_FRAMES:
        raise error(
            f"{source}: a loop matrix of {n} frames is outside the 0..{MAX_LOOP_FRAMES} accepted "
            f"({MAX_LOOP_FRAMES} x {MAX_LOOP_FRAMES} bool = {_size(MAX_LOOP_FRAMES**2)}; stablecues.limits)"
        )
