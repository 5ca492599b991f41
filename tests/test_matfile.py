"""stablecues.matfile: MATLAB v5 files read as SciPy reads them, and refused where SciPy crashes."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import scipy.sparse

from conftest import shared_path
from stablecues.errors import DatasetError
from stablecues.groundtruth import load_ground_truth
from stablecues.matfile import read_mat5

LIMIT = 40_000**2


def _same_as_scipy(path: Path) -> None:
    ref = {k: v for k, v in scipy.io.loadmat(path).items() if not k.startswith("__")}
    mine = read_mat5(path, max_elements=LIMIT)
    assert set(mine) == set(ref)
    for name, value in ref.items():
        got = mine[name]
        if scipy.sparse.issparse(value):
            assert scipy.sparse.issparse(got) and got.shape == value.shape and (got != value).nnz == 0
        elif value.dtype.kind in "biufc":
            assert got.shape == value.shape and got.dtype == value.dtype, name
            np.testing.assert_array_equal(got, value)
        else:
            assert got is None, f"{name}: not numeric, listed as None"


@pytest.mark.parametrize("compress", [False, True])
def test_matrices_of_every_kind_read_as_scipy_reads_them(tmp_path: Path, compress: bool) -> None:
    rng = np.random.default_rng(0)
    loops = rng.random((30, 20)) > 0.8
    variables = {
        "double": loops.astype(float),
        "logical": loops,
        "uint8": loops.astype(np.uint8),
        "int16": loops.astype(np.int16) * -3,
        "single": loops.astype(np.float32),
        "complex": loops.astype(complex) * (1 + 2j),
        "sparse": scipy.sparse.csc_matrix(loops.astype(float)),
        "empty": np.zeros((0, 0)),
        "cube": np.arange(24.0).reshape(2, 3, 4),
        "text": "not a matrix",
        "record": {"a": 1},
    }
    scipy.io.savemat(tmp_path / "a.mat", variables, do_compression=compress)
    _same_as_scipy(tmp_path / "a.mat")


@pytest.mark.parametrize(
    "name", ["NewCollegeGroundTruth.mat", "kitti06GroundTruth.mat", "Lip6IndoorGroundTruth.mat"]
)
def test_real_ground_truth_files(name: str) -> None:
    _same_as_scipy(shared_path("loop_gt_matrices", name))


def _valid(compress: bool = False) -> bytes:
    buf = io.BytesIO()
    scipy.io.savemat(buf, {"gt": np.eye(12, k=-5).astype(np.uint8)}, do_compression=compress)
    return buf.getvalue()


def test_the_file_that_crashed_scipy_is_refused(tmp_path: Path) -> None:
    """A byte count of 1.7 GB on the matrix and the complex flag set: SciPy's compiled reader
    read past the end of the file and the process died (SIGSEGV); here it is one error."""
    data = bytearray(_valid())
    data[135] = 0x69  # the matrix element's byte count, high byte
    data[145] = 0xBB  # array flags: complex, global, logical
    (tmp_path / "gt.mat").write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"gt\.mat: not a readable MATLAB file \(an element declares"):
        load_ground_truth(tmp_path / "gt.mat")


def test_sizes_are_checked_before_anything_is_allocated(tmp_path: Path) -> None:
    data = bytearray(_valid(compress=False))
    at = data.find(struct.pack("<ii", 12, 12))
    data[at : at + 8] = struct.pack("<ii", 100_000, 100_000)
    (tmp_path / "dims.mat").write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"dims\.mat: .*100000x100000 is larger than the"):
        read_mat5(tmp_path / "dims.mat", max_elements=LIMIT)
    with pytest.raises(DatasetError, match=r"dims\.mat: .* is larger than"):
        load_ground_truth(tmp_path / "dims.mat")


def test_a_compressed_matrix_cannot_inflate_past_what_it_declares(tmp_path: Path) -> None:
    # a 2 x 2 matrix whose compressed element declares 10^9 bytes of zeros (a zip bomb)
    import zlib

    inner = bytearray()
    inner += struct.pack("<II", 6, 8) + struct.pack("<II", 6, 0)  # array flags: double
    inner += struct.pack("<II", 5, 8) + struct.pack("<ii", 2, 2)  # dimensions
    inner += struct.pack("<HH", 1, 2) + b"gt\0\0"  # small element: the name
    body = struct.pack("<II", 14, 10**9) + bytes(inner) + b"\0" * 100_000
    comp = zlib.compress(body)
    head = b"MATLAB 5.0 MAT-file".ljust(124, b" ") + b"\x00\x01IM"
    (tmp_path / "bomb.mat").write_bytes(head + struct.pack("<II", 15, len(comp)) + comp)
    with pytest.raises(DatasetError, match=r"bomb\.mat: .*declares 1000000000 bytes"):
        read_mat5(tmp_path / "bomb.mat", max_elements=LIMIT)


def test_sparse_indices_out_of_range_are_refused(tmp_path: Path) -> None:
    scipy.io.savemat(tmp_path / "s.mat", {"gt": scipy.sparse.csc_matrix(np.eye(4, k=-1))})
    data = bytearray((tmp_path / "s.mat").read_bytes())
    at = data.find(struct.pack("<iii", 1, 2, 3))  # the row indices
    data[at : at + 4] = struct.pack("<i", 99)
    (tmp_path / "s.mat").write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="sparse row indices outside"):
        read_mat5(tmp_path / "s.mat", max_elements=LIMIT)


def test_truncated_and_foreign_files(tmp_path: Path) -> None:
    data = _valid(compress=True)
    (tmp_path / "cut.mat").write_bytes(data[: len(data) - 20])
    with pytest.raises(DatasetError, match=r"cut\.mat"):
        load_ground_truth(tmp_path / "cut.mat")
    (tmp_path / "text.mat").write_bytes(b"hello, this is not a MATLAB file at all" * 5)
    with pytest.raises(DatasetError, match=r"text\.mat: not a MATLAB file"):
        load_ground_truth(tmp_path / "text.mat")
