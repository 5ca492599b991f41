"""Quads (geometry, pieces, sets), the texture bank, and the lighting model."""

from __future__ import annotations

import numpy as np
import pytest

from stablecues.synthetic.scene import (
    BUILDING,
    CAMVID_CLASSES,
    LIT_EMISSIVE,
    LIT_NORMAL,
    LOD_ALWAYS,
    LOD_PIECE,
    LOD_WHOLE,
    UP,
    QuadBuilder,
    QuadSet,
    TextureBank,
    ground_quad,
    make_lighting,
    right_of,
    sky_colours,
    vertical_quad,
)


def test_classes_and_directions() -> None:
    assert len(CAMVID_CLASSES) == 12 and CAMVID_CLASSES[BUILDING] == "Building"
    np.testing.assert_allclose(right_of(np.array([1.0, 0.0, 0.0])), [0.0, -1.0, 0.0])
    np.testing.assert_allclose(right_of(np.array([0.0, 1.0, 0.0])), [1.0, 0.0, 0.0])


def test_vertical_quad_corners_and_normal() -> None:
    b = QuadBuilder()
    vertical_quad(b, np.array([1.0, 2.0, 0.0]), np.array([1.0, 0.0, 0.0]), 2.0, 0.0, 3.0, 7, 10.0, BUILDING)
    q = b.build(static=True)
    assert len(q) == 1 and q.lod[0] == LOD_ALWAYS and q.parent[0] == -1 and q.vis[0] == 0
    np.testing.assert_allclose(q.rect[0], [0.0, 0.0, 20.0, 30.0])  # 10 texels per metre
    np.testing.assert_allclose(q.corners()[0], [[1, 2, 3], [3, 2, 3], [3, 2, 0], [1, 2, 0]])
    # seen upright with x to the right from the south: the front faces -y
    np.testing.assert_allclose(q.normals()[0], [0.0, -1.0, 0.0])
    centre, radius = q.spheres()
    np.testing.assert_allclose(centre[0], [2.0, 2.0, 1.5])
    assert radius[0] == pytest.approx(np.hypot(1.0, 1.5))


def test_ground_quad_lies_to_the_right_and_faces_up() -> None:
    b = QuadBuilder()
    ground_quad(b, np.zeros(3), np.array([1.0, 0.0, 0.0]), 4.0, 2.0, 0, 8.0, 3)
    q = b.build(static=False)
    np.testing.assert_allclose(q.normals()[0], UP)
    np.testing.assert_allclose(q.corners()[0][2], [4.0, -2.0, 0.0])
    assert q.vis[0] == -1  # dynamic quads take no visibility id


def test_long_quads_come_whole_and_in_pieces() -> None:
    b = QuadBuilder()
    b.add(np.zeros(3), np.array([1.0, 0, 0]), -UP, 10.0, 2.0, 1, 4.0, BUILDING, chunk_m=4.0)
    q = b.build(static=True)
    assert q.lod.tolist() == [LOD_WHOLE, LOD_PIECE, LOD_PIECE, LOD_PIECE]
    assert q.parent.tolist() == [0, 0, 0, 0]
    pieces = q.rect[1:]
    np.testing.assert_allclose(pieces[0, 0], 0.0)
    np.testing.assert_allclose(pieces[-1, 2], q.rect[0, 2])
    np.testing.assert_allclose(pieces[1:, 0], pieces[:-1, 2])  # pieces tile the whole
    assert np.all(pieces[:, 2] - pieces[:, 0] <= 4.0 * 4.0 + 1e-9)


def test_quad_sets_subset_and_concat() -> None:
    b = QuadBuilder()
    for k in range(3):
        vertical_quad(b, np.array([k, 0.0, 0.0]), np.array([1.0, 0, 0]), 1.0, 0.0, 1.0, k, 4.0, k)
    q = b.build(static=True)
    sub = q.subset(np.array([2, 0]))
    assert sub.tex.tolist() == [2, 0]
    both = QuadSet.concat([QuadSet.empty(), sub, q])
    assert len(both) == 5 and both.tex.tolist() == [2, 0, 0, 1, 2]
    assert QuadSet.concat([QuadSet.empty()]).corners().shape == (0, 4, 3)
    assert len(QuadBuilder().build(static=True)) == 0


def _noise_texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_texture_bank_makes_textures_on_first_use_and_again_after_eviction() -> None:
    bank = TextureBank(budget_bytes=1)  # keeps only the latest texture
    a = bank.register(_noise_texture, 64, 48, seed=(1, 2))
    b = bank.register(_noise_texture, 64, 48, seed=(1, 3))
    assert len(bank) == 2 and bank.generated == 0
    first = [lv.copy() for lv in bank.levels(a)]
    assert [lv.shape for lv in first] == [(64, 48, 3), (32, 24, 3), (16, 12, 3)]  # down to 16 px
    assert bank.levels(a)[0] is bank.levels(a)[0] and bank.generated == 1  # cached
    other = bank.levels(b)[0]
    assert not np.array_equal(other, first[0])  # another seed, another texture
    again = bank.levels(a)  # evicted by b, made again: same pixels
    assert bank.generated == 3
    for x, y in zip(first, again, strict=True):
        np.testing.assert_array_equal(x, y)


def test_lighting_follows_the_sun() -> None:
    noon = make_lighting(12.0, False, sky_tex=0)
    assert noon.sun[2] > 0.8 and noon.sun[1] < 0  # high, in the south
    np.testing.assert_allclose(np.linalg.norm(noon.sun), 1.0)
    assert make_lighting(19.0, False, 0).sun[2] == pytest.approx(np.sin(np.radians(4.0)))  # dusk: 4 deg
    normals = np.array([noon.sun, -noon.sun, UP])
    g = noon.gains(normals, np.array([LIT_NORMAL, LIT_NORMAL, LIT_EMISSIVE]))
    assert np.all(g[0] > g[1])  # lit side brighter than the side turned away
    np.testing.assert_allclose(g[2], noon.exposure)  # lamps ignore the sun
    np.testing.assert_allclose(noon.shadow_gain(-noon.sun), 1.0)  # no sun, nothing to take away
    assert np.all(noon.shadow_gain(UP) < 1.0)
    dull = make_lighting(12.0, True, 0)
    assert np.all(dull.shadow_gain(UP) > noon.shadow_gain(UP))  # overcast: faint shadows
    horizon, zenith, cloud, _ = sky_colours(12.0, False)
    assert zenith[0] > zenith[2] and cloud < sky_colours(12.0, True)[2]  # blue sky, fewer clouds
    assert len(horizon) == 3
