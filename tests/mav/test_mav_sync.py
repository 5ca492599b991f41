"""The deprecated ``stablecues.mav.sync``: it warns, re-exports the new modules' objects, and its
old TUM helpers (positions and (x, y, z, w) quaternions) still round-trip (no shared data)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

pytest.importorskip("pymap3d")

from stablecues import imageio, trajectory  # noqa: E402
from stablecues.errors import DatasetError  # noqa: E402
from stablecues.geometry.rotations import quat_normalize  # noqa: E402
from stablecues.mav import clock, export, frames, geo, loops, poses, solutions  # noqa: E402


def _import_sync() -> ModuleType:
    sys.modules.pop("stablecues.mav.sync", None)
    with pytest.warns(DeprecationWarning, match="stablecues.mav.sync is deprecated"):
        return importlib.import_module("stablecues.mav.sync")


def test_old_path_warns_and_re_exports() -> None:
    sync = _import_sync()
    homes = {
        frames: ("FrameSet", "read_frames"),
        clock: ("Clock", "frame_log_times", "estimate_clock_offset"),
        solutions: ("PoseSource", "gnss_solution", "log_solution", "resample_solution"),
        poses: ("Mount", "MOUNTS", "FramePoses", "poses_for_frames"),
        loops: ("loops_from_trajectory",),
        export: ("write_image_folder", "tum_comments"),
    }
    for module, names in homes.items():
        for name in names:
            assert getattr(sync, name) is getattr(module, name), name
    assert sync.IMAGE_SUFFIXES is imageio.IMAGE_SUFFIXES
    assert sync.yaw_of is geo.known_yaw
    assert set(sync.__all__) == {n for names in homes.values() for n in names} | {
        "IMAGE_SUFFIXES",
        "yaw_of",
        "read_tum",
        "write_tum",
    }


def test_tum_round_trip_and_errors(tmp_path: Path) -> None:
    sync = _import_sync()
    rng = np.random.default_rng(0)
    q = quat_normalize(rng.normal(size=(5, 4)))
    p = rng.normal(size=(5, 3))
    t = np.arange(5) * 0.1 + 1e9
    p[2] = np.nan  # skipped
    n = sync.write_tum(tmp_path / "a.txt", t, p, q, comments=("hello",))
    assert n == 4
    t2, p2, q2 = sync.read_tum(tmp_path / "a.txt")
    keep = [0, 1, 3, 4]
    np.testing.assert_allclose(t2, t[keep], atol=1e-6)
    np.testing.assert_allclose(p2, p[keep], atol=1e-4)
    np.testing.assert_allclose(q2, q[keep], atol=1e-6)
    (tmp_path / "b.txt").write_text("1 2 3\n")
    with pytest.raises(DatasetError, match="8 numbers"):
        sync.read_tum(tmp_path / "b.txt")
    # the same file as stablecues.trajectory reads it: qx qy qz qw in the file's last columns
    rows = np.loadtxt(tmp_path / "a.txt")
    np.testing.assert_allclose(rows[:, 4:8], q[keep], atol=1e-6)
    t3, poses3 = trajectory.read_tum(tmp_path / "a.txt")
    np.testing.assert_array_equal(t3, t2)
    np.testing.assert_allclose(poses3[:, :3, 3], p2)
