"""The flight-log structure: mode spans, and navigation solutions (attitude, origin, interpolation)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pymap3d")

from stablecues.geometry.rotations import euler_zyx_to_quat  # noqa: E402
from stablecues.mav import ModeChange, NavSolution, geo, mode_spans  # noqa: E402

ORIGIN = (52.8, -4.1, 20.0)


def test_mode_spans_merge_repeats() -> None:
    changes = [
        ModeChange(0.0, "A", 1),
        ModeChange(0.0, "A", 1),
        ModeChange(5.0, "B", 2),
        ModeChange(7.0, "A", 1),
    ]
    spans = mode_spans(changes, 10.0)
    assert [(s.name, s.start, s.end) for s in spans] == [("A", 0.0, 5.0), ("B", 5.0, 7.0), ("A", 7.0, 10.0)]
    assert mode_spans([], 10.0) == ()


def _solution(n: int = 5) -> NavSolution:
    t = np.arange(n, dtype=np.float64)
    pos = np.column_stack([t, 2 * t, np.zeros(n)])
    rpy = np.column_stack([np.full(n, 0.1), np.full(n, -0.2), np.linspace(-1.0, 1.0, n)])
    q = geo.ned_to_enu_quat(euler_zyx_to_quat(rpy[:, 0], rpy[:, 1], rpy[:, 2]))
    return NavSolution("s", ORIGIN, t, pos, np.ones((n, 3)), q)


def test_solution_rpy_is_relative_to_ned_and_nan_where_unknown() -> None:
    s = _solution()
    np.testing.assert_allclose(s.rpy[:, :2], [[0.1, -0.2]] * 5, atol=1e-12)
    np.testing.assert_allclose(s.rpy[:, 2], np.linspace(-1.0, 1.0, 5), atol=1e-12)
    q = s.quaternion.copy()
    q[2] = np.nan
    partly = NavSolution("p", ORIGIN, s.t, s.position, s.velocity, q)
    assert not partly.has_attitude
    assert np.isnan(partly.rpy[2]).all() and np.isfinite(partly.rpy[[0, 1, 3, 4]]).all()


def test_solution_reframed_round_trip_keeps_unknown_attitude() -> None:
    s = _solution()
    q = s.quaternion.copy()
    q[1] = np.nan
    s = NavSolution("s", ORIGIN, s.t, s.position, s.velocity, q)
    other = (52.81, -4.09, 35.0)
    back = s.reframed(other).reframed(ORIGIN)
    np.testing.assert_allclose(back.position, s.position, atol=1e-6)
    np.testing.assert_allclose(back.velocity, s.velocity, atol=1e-9)
    np.testing.assert_allclose(back.quaternion[[0, 2, 3, 4]], q[[0, 2, 3, 4]], atol=1e-9)
    assert np.isnan(back.quaternion[1]).all()
    # ~1 km east the local vertical tilts by ~0.01 deg: the attitude turns by that much, no more
    moved = s.reframed(other)
    assert np.nanmax(np.abs(moved.rpy - s.rpy)) < np.radians(0.05)


def test_solution_interpolate_slerps_and_leaves_gaps() -> None:
    s = _solution()
    at = s.interpolate(np.array([-1.0, 0.5, 2.0, 4.0, 9.0]))
    assert np.isnan(at.position[[0, 4]]).all() and np.isnan(at.quaternion[[0, 4]]).all()
    np.testing.assert_allclose(at.position[1:4], [[0.5, 1.0, 0.0], [2.0, 4.0, 0.0], [4.0, 8.0, 0.0]])
    np.testing.assert_allclose(at.rpy[1, 2], -0.75, atol=1e-3)  # half-way between two yaws
    np.testing.assert_allclose(at.quaternion[2], s.quaternion[2], atol=1e-12)
    gappy = NavSolution(
        "g", ORIGIN, np.array([0.0, 1.0, 5.0]), s.position[:3], s.velocity[:3], s.quaternion[:3]
    )
    assert np.isnan(gappy.interpolate(np.array([3.0])).position).all()  # 4 s gap > max_gap
    assert np.isfinite(gappy.interpolate(np.array([3.0]), max_gap=5.0).position).all()
