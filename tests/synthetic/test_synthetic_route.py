"""The drive: laps around the route rectangle, their detours, driving lines and lanes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stablecues.synthetic.route import LANE_OFFSETS, Lap, Path, lap_lanes, lap_path, plan_laps
from stablecues.synthetic.scene import TextureBank
from stablecues.synthetic.town import Town


def test_laps_cycle_through_the_revisit_variants() -> None:
    laps = plan_laps(5, (2, 2, 2, 1), seed=0)
    assert [lap.index for lap in laps] == [0, 1, 2, 3, 4]
    assert [lap.clockwise for lap in laps] == [True, True, False, True, True]
    assert [lap.offset for lap in laps] == [LANE_OFFSETS[v] for v in (0, 1, 2, 3, 1)]
    assert laps[0].detour == -1 and all(lap.detour >= 0 for lap in laps[1:])
    assert [lap.overcast for lap in laps] == [False, False, False, True, False]
    assert len({round(lap.hour, 3) for lap in laps}) == 5
    again = plan_laps(5, (2, 2, 2, 1), seed=0)
    assert [lap.hour for lap in again] == [lap.hour for lap in laps]


def test_lap_nodes_form_a_closed_grid_loop() -> None:
    for lap in plan_laps(4, (2, 2, 3, 2), seed=1):
        steps = np.roll(lap.nodes, -1, axis=0) - lap.nodes
        assert np.all(np.abs(steps).sum(axis=1) == 1)  # one block edge at a time, closed
    first = plan_laps(1, (2, 2, 3, 2), seed=1)[0]
    assert len(first.nodes) == 2 * (3 + 2)  # the rectangle's perimeter in block edges
    # a detour adds the two corners of the neighbouring block
    assert len(plan_laps(2, (2, 2, 3, 2), seed=1)[1].nodes) == len(first.nodes) + 2


def test_path_samples_positions_and_headings() -> None:
    square = Path(np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]), np.arange(5) * 10.0, 0.0)
    assert square.length == 40.0
    pos, heading = square.sample(np.array([5.0, 15.0, 45.0]))
    np.testing.assert_allclose(pos, [[5.0, 0.0], [10.0, 5.0], [5.0, 0.0]])
    np.testing.assert_allclose(heading, [0.0, math.pi / 2, 0.0])
    late = Path(square.points, square.s, start=10.0)
    np.testing.assert_allclose(late.sample(np.array([0.0]))[0], [[10.0, 0.0]])


def test_lanes_of_a_hand_made_lap() -> None:
    lap = Lap(0, np.array([[0, 0], [0, 1], [1, 1], [1, 0]]), True, 2.6, 10.0, False, -1)
    assert lap_lanes(lap) == {(0, 0, 1), (1, 1, 1), (0, 1, -1), (1, 0, -1)}


def test_driving_line_keeps_to_the_right_of_the_street() -> None:
    town = Town(2, 6, 6, 0.0, TextureBank())
    lap = plan_laps(1, (2, 2, 2, 2), seed=2)[0]
    path = lap_path(town, lap)
    xs, ys = town.xs[2:5], town.ys[2:5]
    perimeter = 2 * ((xs[-1] - xs[0]) + (ys[-1] - ys[0]))
    assert 0.8 * perimeter < path.length < perimeter  # inside the rectangle, corners cut
    pos, heading = path.sample(np.linspace(0.0, path.length, 400, endpoint=False))
    # on straight stretches the camera is lap.offset to the right of the nearest street line
    right = np.stack([np.sin(heading), -np.cos(heading)], axis=1)
    along_x = np.abs(np.sin(heading)) < 1e-6
    along_y = np.abs(np.cos(heading)) < 1e-6
    line_y = ys[np.argmin(np.abs(pos[along_x, 1:2] - ys[None, :]), axis=1)]
    line_x = xs[np.argmin(np.abs(pos[along_y, 0:1] - xs[None, :]), axis=1)]
    assert along_x.sum() > 50 and along_y.sum() > 50
    np.testing.assert_allclose((pos[along_x, 1] - line_y) * right[along_x, 1], lap.offset, atol=1e-9)
    np.testing.assert_allclose((pos[along_y, 0] - line_x) * right[along_y, 0], lap.offset, atol=1e-9)
    assert pytest.approx(lap.offset) == LANE_OFFSETS[0]
