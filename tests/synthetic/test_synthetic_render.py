"""The quad renderer: the camera model, culling, near-plane clipping, exact depth, z-buffer, labels."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stablecues.synthetic.render import Intrinsics, Renderer, _clip_near, cull
from stablecues.synthetic.scene import (
    BUILDING,
    CAR,
    SKY,
    Lighting,
    QuadBuilder,
    QuadSet,
    TextureBank,
    make_lighting,
)

CAM = Intrinsics.from_fov(64, 48, 70.0)


def _flat(rng: np.random.Generator, h: int, w: int, value: int) -> np.ndarray:
    img = np.full((h, w, 3), value, np.uint8)
    img[::4] = 255 - value  # some texture, so the image is not one colour
    return img


def _scene() -> tuple[Renderer, QuadSet, Lighting]:
    """A wall 5 m ahead (from 1 m above the camera down) and a car-sized board 3 m ahead."""
    bank = TextureBank()
    wall_tex = bank.register(_flat, 64, 64, 90, seed=(1,))
    board_tex = bank.register(_flat, 32, 32, 200, seed=(2,))
    sky = bank.register(_flat, 64, 256, 180, seed=(3,))
    b = QuadBuilder()
    # camera frame = world frame here: x right, y down, z forward; u x v = +z, so the front faces -z
    b.add(
        np.array([-10.0, -1.0, 5.0]),
        np.array([1.0, 0, 0]),
        np.array([0, 1.0, 0]),
        20.0,
        11.0,
        wall_tex,
        4.0,
        BUILDING,
    )
    b.add(
        np.array([-0.5, 0.0, 3.0]),
        np.array([1.0, 0, 0]),
        np.array([0, 1.0, 0]),
        1.0,
        1.0,
        board_tex,
        16.0,
        CAR,
    )
    quads = b.build(static=True)
    return Renderer(CAM, bank), quads, make_lighting(12.0, False, sky)


def test_intrinsics_from_field_of_view() -> None:
    assert CAM.fx == pytest.approx(32.0 / math.tan(math.radians(35.0)))
    assert (CAM.cx, CAM.cy) == (31.5, 23.5)
    np.testing.assert_allclose(CAM.K, [[CAM.fx, 0, 31.5], [0, CAM.fy, 23.5], [0, 0, 1]])


def test_cull_keeps_spheres_in_the_view_frustum() -> None:
    centres = np.array(
        [[0.0, 0.0, 10.0], [0.0, 0.0, -10.0], [0.0, 0.0, 300.0], [40.0, 0.0, 10.0], [8.0, 0, 10]]
    )
    keep = cull(np.eye(3), np.zeros(3), centres, np.full(5, 1.0), CAM, far=250.0)
    assert keep.tolist() == [0, 4]  # ahead, and just inside the 70 deg view; not behind, too far, aside
    grown = cull(np.eye(3), np.zeros(3), centres, np.full(5, 1.0), CAM, far=250.0, margin=60.0)
    assert grown.tolist() == [0, 1, 2, 3, 4]  # a margin grows every sphere


def test_clip_near_keeps_the_part_in_front() -> None:
    poly = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, -1.0], [1.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    out = _clip_near(poly, 0.5)
    assert len(out) == 4 and np.all(out[:, 2] >= 0.5 - 1e-12)
    np.testing.assert_allclose(sorted(out[:, 2].tolist()), [0.5, 0.5, 1.0, 1.0])
    assert _clip_near(poly, 2.0).shape == (0, 3)


def test_depth_is_exact_and_nearer_quads_win() -> None:
    renderer, quads, light = _scene()
    for order in ([0, 1], [1, 0]):  # the z-buffer, not the order, decides
        sub = quads.subset(np.array(order))
        view = renderer.render(np.eye(3), np.zeros(3), sub, sub.normals(), light)
        lab, depth = view.labels, view.depth
        assert lab is not None and view.image.shape == (48, 64, 3)
        wall, board, sky = lab == BUILDING, lab == CAR, lab == SKY
        assert wall.sum() > 500 and board.sum() > 50 and sky.sum() > 200
        np.testing.assert_allclose(depth[wall], 5.0, rtol=1e-5)  # a fronto-parallel plane: exact
        np.testing.assert_allclose(depth[board], 3.0, rtol=1e-5)
        assert np.all(depth[sky] == 0)
        # the wall's top edge (1 m up at 5 m) lands on row cy - fy / 5 (filling may take the pixel above)
        rows = np.nonzero(wall.any(axis=1) | board.any(axis=1))[0]
        assert abs(rows.min() - (CAM.cy - CAM.fy / 5.0)) <= 1.0
        # the board covers x in [-0.5, 0.5] m at 3 m: columns around cx
        cols = np.nonzero(board.any(axis=0))[0]
        assert (
            abs(cols.min() - (CAM.cx - CAM.fx / 6.0)) <= 1 and abs(cols.max() - (CAM.cx + CAM.fx / 6.0)) <= 1
        )
    assert view.levels.shape == (2,) and np.all(view.levels >= 0)


def test_backs_of_one_sided_quads_are_not_drawn() -> None:
    renderer, quads, light = _scene()
    behind = np.diag([-1.0, 1.0, -1.0])  # turned round, 10 m beyond the wall: sees its back
    view = renderer.render(behind, np.array([0.0, 0.0, 10.0]), quads, quads.normals(), light)
    assert view.labels is not None and not np.isin(view.labels, [BUILDING, CAR]).any()


def test_noise_follows_its_generator() -> None:
    renderer, quads, light = _scene()
    args = (np.eye(3), np.zeros(3), quads, quads.normals(), light)

    def noisy(seed: int) -> np.ndarray:
        return renderer.render(*args, noise=3.0, noise_rng=np.random.default_rng(seed)).image

    clean = renderer.render(*args).image
    np.testing.assert_array_equal(noisy(1), noisy(1))
    assert not np.array_equal(noisy(1), noisy(2))
    assert 1.0 < np.abs(noisy(1).astype(int) - clean.astype(int)).mean() < 4.0
    assert renderer.render(*args, labels=False).labels is None
