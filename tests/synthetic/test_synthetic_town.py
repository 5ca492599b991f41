"""The town: layout helpers, occlusion by blocks, per-lap movers and cast shadows."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues.synthetic.route import lap_lanes, plan_laps
from stablecues.synthetic.scene import LIT_FOLIAGE, QuadSet, TextureBank, make_lighting
from stablecues.synthetic.town import (
    DRIVE_LANE,
    PARKING,
    ROAD_HALF,
    Movers,
    Town,
    facade_u,
    grid_size_for,
)

CYCLE_LANE = ROAD_HALF - PARKING - 0.6


@pytest.fixture(scope="module")
def town() -> Town:
    return Town(4, 6, 6, 1.0, TextureBank())


def test_grid_and_facade_direction() -> None:
    assert grid_size_for((2, 1)) == (6, 5)
    # a viewer facing a south-facing facade looks north: the texture's columns run east
    np.testing.assert_allclose(facade_u(np.array([0.0, -1.0, 0.0])), [1.0, 0.0, 0.0])
    np.testing.assert_allclose(facade_u(np.array([1.0, 0.0, 0.0])), [0.0, 1.0, 0.0])


def test_layout_is_seeded(town: Town) -> None:
    again = Town(4, 6, 6, 1.0, TextureBank())
    np.testing.assert_array_equal(again.xs, town.xs)
    np.testing.assert_array_equal(again.static.origin, town.static.origin)
    other = Town(5, 6, 6, 1.0, TextureBank())
    assert not np.array_equal(other.xs, town.xs)
    assert len(town.street_lines()) == (6 - 1) + (6 - 1)
    np.testing.assert_allclose(town.node(2, 3), [town.xs[2], town.ys[3], 0.0])


def test_movers_move_along_their_lines() -> None:
    mv = Movers(
        start=np.array([[0.0, 0.0, 0.0], [10.0, 5.0, 0.0]]),
        direction=np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
        length=np.array([20.0, 1.0]),
        s0=np.array([2.0, 0.0]),
        speed=np.array([3.0, 0.0]),
        quads=QuadSet.empty(),
        half=np.array([[2.0, 1.0], [0.3, 0.3]]),
    )
    assert len(mv) == 2
    np.testing.assert_allclose(mv.positions(1.0), [[5.0, 0.0, 0.0], [10.0, 5.0, 0.0]])
    np.testing.assert_allclose(mv.positions(7.0)[0], [3.0, 0.0, 0.0])  # 2 + 21 wraps to 3 on a 20 m line
    # footprint 2 x 1 m half sizes, grown by 0.4 m
    assert mv.contains(1.0, np.array([7.3, 1.3]))[0]
    assert not mv.contains(1.0, np.array([7.5, 0.0]))[0]
    assert not mv.contains(1.0, np.array([5.0, 1.5]))[0]


def test_occluded_hides_what_lies_behind_a_block(town: Town) -> None:
    lo, hi = town.block_lo[0], town.block_hi[0]
    cy = (lo[1] + hi[1]) / 2
    camera = np.array([lo[0] - 8.0, cy, 1.5])  # in the street west of the block
    height = hi[2]

    def wall(x: float, z0: float, z1: float) -> np.ndarray:
        return np.array([[[x, cy - 1, z1], [x, cy + 1, z1], [x, cy + 1, z0], [x, cy - 1, z0]]])

    behind = wall(hi[0] + 5.0, 0.0, 0.5 * height)  # low, east of the block
    # high enough that every sight line passes over the block's near roof edge
    z_over = 1.5 + 2.0 * (height - 1.5) * (hi[0] - lo[0] + 13.0) / 8.0
    above = wall(hi[0] + 5.0, z_over, z_over + 2.0)
    assert town.occluded(behind, [camera]).tolist() == [True]
    assert town.occluded(above, [camera]).tolist() == [False]
    # hidden only when hidden from every camera given (this one sees it from the east)
    east = np.array([hi[0] + 20.0, cy, 1.5])
    assert town.occluded(behind, [camera, east]).tolist() == [False]
    assert town.occluded(np.zeros((0, 4, 3)), [camera]).shape == (0,)


def test_lap_movers_are_seeded_per_lap_and_keep_out_of_camera_lanes(town: Town) -> None:
    laps = plan_laps(3, (2, 2, 2, 2), seed=4)
    lanes = lap_lanes(laps[1])
    a, b = town.lap_movers(1, lanes), town.lap_movers(1, lanes)
    np.testing.assert_array_equal(a.start, b.start)
    np.testing.assert_array_equal(a.quads.origin, b.quads.origin)
    other = town.lap_movers(2, lap_lanes(laps[2]))
    assert not (len(other) == len(a) and np.allclose(other.start, a.start))
    assert a.half.shape == (len(a), 2) and np.all(a.half > 0)
    # no car or cyclist drives in a lane the camera drives in
    driving = np.nonzero(a.speed >= 3.0)[0]
    assert len(driving) > 5
    for k in driving:
        d, p = a.direction[k], a.start[k]
        axis = 0 if abs(d[1]) > 0.5 else 1
        lines = town.xs if axis == 0 else town.ys
        idx = int(np.argmin(np.abs(lines - p[axis])))
        sign = int(np.sign(d[1] if axis == 0 else d[0]))
        assert (axis, idx, sign) not in lanes
        # cars in the driving lane, cyclists beside the parking strip
        assert min(abs(abs(p[axis] - lines[idx]) - off) for off in (DRIVE_LANE, CYCLE_LANE)) < 1e-9


def test_an_empty_town_has_no_movers() -> None:
    empty = Town(1, 4, 4, 0.0, TextureBank()).lap_movers(0, set())
    assert len(empty) == 0 and empty.start.shape == (0, 3) and empty.half.shape == (0, 2)


def test_lap_decals_darken_and_need_sun(town: Town) -> None:
    noon = town.lap_decals(make_lighting(12.0, False, 0))
    assert len(noon) > 0
    assert np.all(noon.gain < 1.0) and np.all(noon.gain > 0.0)
    np.testing.assert_allclose(np.linalg.norm(noon.normal, axis=1), 1.0)
    assert noon.alpha.dtype == bool and noon.alpha.any() and not noon.alpha.all()  # canopies and walls
    assert noon.centre.shape == (len(noon), 3) and np.all(noon.radius > 0)
    assert len(town.lap_decals(make_lighting(12.0, True, 0))) == 0  # overcast: no shadows
    foliage = np.count_nonzero(town.prop_casters.lit == LIT_FOLIAGE)
    assert np.count_nonzero(noon.alpha) <= foliage  # of a crossed canopy pair one quad casts
