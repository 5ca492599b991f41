"""stablecues.groundtruth: loading loop ground truth from every supported form and every real
benchmark file; views of interleaved releases; loop ground truth from poses (hand-computed cases
and a brute-force comparison)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io

from conftest import shared_path
from stablecues.errors import DatasetError, InputError
from stablecues.groundtruth import (
    GroundTruth,
    check_loop_matrix,
    load_ground_truth,
    loops_from_poses,
    orient,
    save_ground_truth,
    select_view,
    sha256_file,
    vprbench_matrix,
)

LOWER = np.array([[0, 0, 0, 0], [0, 0, 0, 0], [1, 0, 0, 0], [1, 1, 0, 0]], np.uint8)


def test_mat_lower_upper_and_variable_choice(tmp_path: Path) -> None:
    scipy.io.savemat(tmp_path / "a.mat", {"truth": LOWER})
    gt = load_ground_truth(tmp_path / "a.mat")
    assert gt.matrix.dtype == bool and gt.matrix.sum() == 3 and not gt.transposed
    assert gt.variable == "truth" and gt.sha256 == sha256_file(tmp_path / "a.mat") and len(gt.sha256) == 64
    scipy.io.savemat(
        tmp_path / "b.mat", {"small": np.ones((2, 2)), "gt": LOWER.T.astype(float), "s": np.zeros((1, 3))}
    )
    gt = load_ground_truth(tmp_path / "b.mat")  # largest 2-D array, upper-triangular -> transposed
    assert gt.variable == "gt" and gt.transposed
    np.testing.assert_array_equal(gt.matrix, LOWER.astype(bool))
    prov = gt.provenance()
    assert prov["gt_loops"] == 3 and prov["gt_rows_with_loops"] == 2 and prov["gt_transposed"] is True
    with pytest.raises(DatasetError, match="no variable"):
        load_ground_truth(tmp_path / "b.mat", variable="nope")
    with pytest.raises(DatasetError, match="square"):
        load_ground_truth(tmp_path / "b.mat", variable="s")


def test_symmetric_diagonal_and_ambiguous() -> None:
    sym = LOWER | LOWER.T
    sym[1, 1] = 1
    m, t, notes = orient(sym)
    np.testing.assert_array_equal(m, LOWER.astype(bool))
    assert not t and notes == {"dropped_diagonal": 1, "symmetric": True}
    mixed = LOWER.copy()
    mixed[0, 3] = 1
    mixed[3, 0] = 0
    with pytest.raises(DatasetError, match="both sides"):
        orient(mixed)
    m, _, notes = orient(mixed, orientation="lower")
    assert m.sum() == 2 and notes["dropped_other_half"] == 1
    import scipy.sparse

    m, t, _ = orient(scipy.sparse.csr_matrix(LOWER.T))
    assert t and m.sum() == 3


def test_npy_npz_image_roundtrip(tmp_path: Path) -> None:
    matrix = LOWER.astype(bool)
    save_ground_truth(tmp_path / "loops.npy", matrix)
    np.testing.assert_array_equal(load_ground_truth(tmp_path / "loops.npy").matrix, matrix)
    np.savez(tmp_path / "g.npz", loops=LOWER.T)
    gt = load_ground_truth(tmp_path / "g.npz")
    assert gt.variable == "loops" and gt.transposed
    cv2.imwrite(str(tmp_path / "g.png"), LOWER * 255)
    cv2.imwrite(str(tmp_path / "g.bmp"), np.dstack([LOWER * 255] * 3))
    for name in ("g.png", "g.bmp"):
        np.testing.assert_array_equal(load_ground_truth(tmp_path / name).matrix, matrix)
    with pytest.raises(DatasetError, match="not found"):
        load_ground_truth(tmp_path / "absent.mat")
    (tmp_path / "x.txt").write_text("1")
    with pytest.raises(DatasetError, match="expected a .mat"):
        load_ground_truth(tmp_path / "x.txt")
    (tmp_path / "broken.mat").write_bytes(b"MATLAB garbage" * 10)
    with pytest.raises(DatasetError):
        load_ground_truth(tmp_path / "broken.mat")
    with pytest.raises(InputError):
        save_ground_truth(tmp_path / "bad.npy", matrix.T)


def test_views_of_interleaved_release() -> None:
    full = np.zeros((6, 6), bool)
    full[4, 0] = True  # left 2 - left 0
    full[5, 3] = True  # right 2 - right 1
    full[3, 2] = True  # right 1 - left 1: the same pair, not a loop between pairs
    full[3, 0] = True  # right 1 - left 0
    assert list(zip(*np.nonzero(select_view(full, "left")), strict=True)) == [(2, 0)]
    assert list(zip(*np.nonzero(select_view(full, "right")), strict=True)) == [(2, 1)]
    assert list(zip(*np.nonzero(select_view(full, "pair")), strict=True)) == [(1, 0), (2, 0), (2, 1)]
    assert select_view(full, "all") is full
    with pytest.raises(InputError):
        select_view(full[:5, :5], "left")


def test_vprbench_table() -> None:
    table = np.empty((2, 2), dtype=object)
    table[0] = [0, [1, 2]]
    table[1] = [1, [-1]]
    gt, mask = vprbench_matrix(table, 4)
    assert gt.shape == (6, 6) and list(zip(*np.nonzero(gt), strict=True)) == [(4, 1), (4, 2)]
    assert mask.tolist() == [False] * 4 + [True] * 2
    with pytest.raises(DatasetError, match="out of range"):
        vprbench_matrix(table, 2)
    with pytest.raises(InputError):
        GroundTruth(gt, query_mask=mask[:3])
    with pytest.raises(InputError):
        check_loop_matrix(np.ones((3, 3), bool))


# (file, size, loops, orientation as stored). Counted once from the files with scipy.io.loadmat.
REAL_FILES = [
    ("100909_1210_GT_labeled.mat", 3851, 57809, "lower"),
    ("100909_1410_GT_labeled.mat", 4179, 80337, "lower"),
    ("180809_1545_GT_labeled.mat", 4287, 67873, "lower"),
    ("190809_0845_GT_labeled.mat", 4363, 66154, "lower"),
    ("Lip6IndoorGroundTruth.mat", 388, 884, "lower"),
    ("Lip6OutdoorGroundTruth.mat", 1063, 3704, "lower"),
    ("NewCollegeGroundTruth.mat", 2146, 14832, "lower"),
    ("city_GT_final.mat", 1237, 8321, "lower"),
    ("groundTruth_KITTI00.mat", 4541, 31922, "lower"),
    ("groundTruth_KITTI_05.mat", 2761, 10558, "lower"),
    ("kitti02GroundTruth.mat", 4661, 4037, "lower"),
    ("kitti06GroundTruth.mat", 1101, 3287, "lower"),
    ("malaga_GT_final.mat", 3474, 34828, "lower"),
    ("newcollege_GT.mat", 2624, 46753, "upper"),
]


@pytest.mark.parametrize(("name", "size", "loops", "stored"), REAL_FILES)
def test_real_benchmark_files(name: str, size: int, loops: int, stored: str) -> None:
    gt = load_ground_truth(shared_path("loop_gt_matrices", name))
    assert gt.n == size and int(gt.matrix.sum()) == loops
    assert gt.transposed == (stored == "upper")
    check_loop_matrix(gt.matrix)


@pytest.mark.slow
def test_real_bicocca_upper_triangular() -> None:
    gt = load_ground_truth(shared_path("loop_gt_matrices", "new_GT_biccoca.mat"))
    assert gt.n == 26335 and gt.transposed and int(gt.matrix.sum()) == 254055


def test_real_new_college_views() -> None:
    gt = load_ground_truth(shared_path("loop_gt_matrices", "NewCollegeGroundTruth.mat"), view="left")
    assert gt.n == 1073 and gt.view == "left" and int(gt.matrix.sum()) == 3541
    pair = load_ground_truth(shared_path("loop_gt_matrices", "NewCollegeGroundTruth.mat"), view="pair")
    assert pair.n == 1073 and pair.matrix.sum() >= 3541


def test_real_vprbench_tables() -> None:
    root = shared_path("corridor", "vprbench_gt_only")
    for path in sorted(root.glob("*/ground_truth_new.npy")):
        table = np.load(path, allow_pickle=True)
        largest = max(max(ids) for ids in table[:, 1])
        if largest > 5000:  # Nordland, Pittsburgh, Tokyo247: dense matrices of 10^8+ cells, too slow here
            continue
        gt = load_ground_truth(path)
        assert gt.n == largest + 1 + len(table)
        assert gt.query_mask is not None and gt.provenance()["gt_notes"]["format"] == "vprbench"
        check_loop_matrix(gt.matrix)


def test_mat_v73_hdf5(tmp_path: Path) -> None:
    h5py = pytest.importorskip("h5py", reason="h5py not installed (needed only for MATLAB v7.3 files)")
    path = tmp_path / "v73.mat"
    with h5py.File(path, "w", userblock_size=512) as fh:
        fh.create_dataset("truth", data=LOWER.T)  # HDF5 holds MATLAB's column-major matrix transposed
    header = (
        b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    )
    with path.open("r+b") as fh:
        fh.write(header.ljust(116) + b"\x00" * 8 + b"\x00\x02IM")
    gt = load_ground_truth(path)
    assert gt.variable == "truth" and not gt.transposed
    np.testing.assert_array_equal(gt.matrix, LOWER.astype(bool))


@pytest.mark.parametrize("dtype", [np.uint8, bool, np.float64, np.int32])
def test_nonzero_scan_matches_numpy(dtype: type) -> None:
    from stablecues.groundtruth import _nonzero_indices

    rng = np.random.default_rng(1)
    a = (rng.random((37, 37)) < 0.1).astype(dtype)
    for arr in (a, np.asfortranarray(a), a[::2, ::2]):
        rows, cols = _nonzero_indices(arr)
        want = set(zip(*np.nonzero(arr), strict=True))
        assert set(zip(rows.tolist(), cols.tolist(), strict=True)) == {(int(i), int(j)) for i, j in want}


def test_fit_view_per_camera_or_interleaved() -> None:
    from stablecues.groundtruth import fit_view

    full = np.zeros((6, 6), bool)
    full[4, 0] = full[5, 3] = True
    gt = GroundTruth(full)
    left = fit_view(gt, "left", 3)
    assert left.n == 3 and left.view == "left" and left.matrix[2, 0]
    assert fit_view(gt, "left", 6) is gt  # already one row per frame: a per-camera copy
    assert fit_view(gt, "all", 3) is gt
    with pytest.raises(DatasetError, match="fits neither"):
        fit_view(gt, "right", 5)
    odd = GroundTruth(np.zeros((7, 7), bool))
    assert fit_view(odd, "right", 3).n == 3


# ----------------------------------------------------------------------------------------------
# loops_from_poses


def test_square_path_hand_computed() -> None:
    # 0 -> 1 -> 2 -> 3 -> back near 0 (frame 4), then near 1 (frame 5)
    pos = np.array([[0, 0, 0], [5, 0, 0], [5, 5, 0], [0, 5, 0], [0.5, 0, 0], [5, 0.9, 0]], float)
    gt = loops_from_poses(pos, max_distance=1.0)
    expected = np.zeros((6, 6), bool)
    expected[4, 0] = True
    expected[5, 1] = True
    np.testing.assert_array_equal(gt, expected)
    assert gt.dtype == bool and not np.triu(gt).any()


def test_gaps_yaw_and_nan() -> None:
    pos = np.zeros((5, 3))
    gt = loops_from_poses(pos, max_distance=0.1, min_gap_frames=2)
    assert gt.sum() == 6  # pairs with i - j >= 2 among 5 frames: 3 + 2 + 1
    times = np.array([0.0, 1.0, 2.0, 3.0, 10.0])
    gt = loops_from_poses(pos, max_distance=0.1, times=times, min_gap_s=5.0)
    assert set(zip(*np.nonzero(gt), strict=True)) == {(4, 0), (4, 1), (4, 2), (4, 3)}
    yaws = np.radians([0.0, 170.0, -175.0, 10.0, 359.0])
    gt = loops_from_poses(pos, max_distance=0.1, yaws=yaws, max_angle_deg=20.0)
    pairs = set(zip(*np.nonzero(gt), strict=True))
    assert pairs == {(2, 1), (3, 0), (4, 0), (4, 3)}
    pos_nan = pos.copy()
    pos_nan[2] = np.nan
    gt = loops_from_poses(pos_nan, max_distance=0.1)
    assert not gt[2].any() and not gt[:, 2].any() and gt[3, 1]


def test_matches_brute_force_across_blocks() -> None:
    rng = np.random.default_rng(3)
    n = 700  # more than one row block
    pos = rng.uniform(0, 20, (n, 3))
    gt = loops_from_poses(pos, max_distance=1.5, min_gap_frames=10)
    d = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    i, j = np.indices((n, n))
    np.testing.assert_array_equal(gt, (d <= 1.5) & (i - j >= 10))


def test_bad_inputs() -> None:
    with pytest.raises(InputError):
        loops_from_poses(np.zeros((4, 2)), max_distance=1.0)
    with pytest.raises(InputError):
        loops_from_poses(np.zeros((4, 3)), max_distance=-1.0)
    with pytest.raises(InputError):
        loops_from_poses(np.zeros((4, 3)), max_distance=1.0, min_gap_s=1.0)
    with pytest.raises(InputError):
        loops_from_poses(np.zeros((4, 3)), max_distance=1.0, yaws=np.zeros(4))
    assert loops_from_poses(np.zeros((0, 3)), max_distance=1.0).shape == (0, 0)


def test_vprbench_rows_that_numpy_would_expand_or_allocate_are_refused() -> None:
    nested: list = [1]
    for _ in range(40):  # 2^40 ids once expanded
        nested = [nested, nested]
    for ids in (nested, "abc", [1.5], [2**70]):
        table = np.empty((1, 2), dtype=object)
        table[0] = [0, ids]
        with pytest.raises(DatasetError, match="row 0: expected \\[query id, \\[ref ids\\]\\]"):
            vprbench_matrix(table)
    table = np.empty((1, 2), dtype=object)
    table[0] = [0, [10**9]]  # n_ref taken from the largest id: a 10^9 x 10^9 matrix
    with pytest.raises(DatasetError, match="a loop matrix of 1000000002 frames is outside the 0..40000"):
        vprbench_matrix(table)


def test_a_matrix_of_only_nan_is_refused(tmp_path: Path) -> None:
    np.save(tmp_path / "gt.npy", np.full((5, 5), np.nan))
    with pytest.raises(DatasetError, match=r"gt\.npy: expected a loop matrix of 0/1 values, found only NaN"):
        load_ground_truth(tmp_path / "gt.npy")
    some = np.full((5, 5), np.nan)
    some[3, 1] = 1.0  # NaN cells among loops still count as no loop, as documented
    np.save(tmp_path / "gt.npy", some)
    assert np.flatnonzero(load_ground_truth(tmp_path / "gt.npy").matrix).tolist() == [16]


def test_loops_from_poses_refuses_a_matrix_past_the_limit() -> None:
    from stablecues.limits import MAX_LOOP_FRAMES

    with pytest.raises(InputError, match="positions: a loop matrix of"):
        loops_from_poses(np.zeros((MAX_LOOP_FRAMES + 1, 3)), max_distance=1.0)
