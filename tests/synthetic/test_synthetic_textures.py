"""Procedural textures: sizes from metres, one texture per seed, clean cut-outs, road markings."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from stablecues.synthetic import textures as tx

GENERATORS: list[tuple[str, Callable[..., np.ndarray], tuple[Any, ...], tuple[int, int, int]]] = [
    ("facade", tx.facade, (12.0, 15.0, 16.0), (240, 192, 3)),
    ("side facade", lambda rng, *a: tx.facade(rng, *a, side=True), (6.0, 9.0, 16.0), (144, 96, 3)),
    ("road", tx.road, (30.0, 12.0, 12.0), (144, 360, 3)),
    ("intersection", tx.intersection, (12.0, 12.0), (144, 144, 3)),
    ("sidewalk", tx.sidewalk, (20.0, 3.5, 16.0), (56, 320, 3)),
    ("gravel", tx.gravel, (4.0, 3.0, 16.0), (48, 64, 3)),
    ("foliage", tx.foliage, (4.0, 3.0, 20.0), (60, 80, 4)),
    ("bark", tx.bark, (0.4, 3.0, 32.0), (96, 13, 3)),
    ("sign plate", tx.sign_plate, (0.7, 64.0), (45, 45, 4)),
    ("fence", tx.fence, (6.0, 1.2, 24.0), (29, 144, 4)),
    ("car side", tx.car_side, (4.4, 1.5, 24.0, (40, 40, 170), False), (36, 106, 4)),
    ("pedestrian", tx.pedestrian, (1.75, 32.0), (56, 19, 4)),
]


@pytest.mark.parametrize(("name", "fn", "args", "shape"), GENERATORS, ids=[g[0] for g in GENERATORS])
def test_one_texture_per_seed(
    name: str, fn: Callable[..., np.ndarray], args: tuple[Any, ...], shape: tuple[int, int, int]
) -> None:
    a = fn(np.random.default_rng([7, 1]), *args)
    assert a.shape == shape and a.dtype == np.uint8, name
    np.testing.assert_array_equal(a, fn(np.random.default_rng([7, 1]), *args))
    assert not np.array_equal(a, fn(np.random.default_rng([7, 2]), *args))
    if shape[2] == 4:  # cut-outs: alpha is 0 or 255 (some fences are solid walls)
        assert set(np.unique(a[..., 3]).tolist()) <= {0, 255}, name
        assert name == "fence" or not a[..., 3].all(), name


def test_car_ends_follow_the_colour_and_plate() -> None:
    """Front and back of a car draw no random numbers: they match its colour and plate only."""
    args = (1.8, 1.5, 64.0, (40, 40, 170), True, "AB123")  # at 64 px/m the plate is legible
    a = tx.car_end(np.random.default_rng(1), *args)
    assert a.shape == (96, 115, 4) and a.dtype == np.uint8
    small = tx.car_end(np.random.default_rng(1), 1.8, 1.5, 24.0, (40, 40, 170), True, "AB123")
    assert small.shape == (36, 43, 4) and set(np.unique(small[..., 3]).tolist()) == {0, 255}
    np.testing.assert_array_equal(a, tx.car_end(np.random.default_rng(2), *args))
    rng = np.random.default_rng(1)
    assert not np.array_equal(a, tx.car_end(rng, 1.8, 1.5, 64.0, (40, 40, 170), True, "XY987"))
    assert not np.array_equal(a, tx.car_end(rng, 1.8, 1.5, 64.0, (150, 60, 30), True, "AB123"))


def test_value_noise_is_smooth_and_unit_scaled() -> None:
    n = tx.value_noise(np.random.default_rng(0), 200, 300, cell=20.0)
    assert n.shape == (200, 300) and n.dtype == np.float32
    assert 0.5 < float(n.std()) < 1.5
    assert float(np.abs(np.diff(n, axis=1)).mean()) < 0.2 * float(n.std())  # white noise: 1.13


def test_words_and_text_boxes() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        word = tx.random_word(rng, 2, 5)
        assert 2 <= len(word) <= 5 and word.isalpha() and word.isupper()
    img = np.zeros((60, 100, 3), np.uint8)
    tx.put_text_box(img, "SHOP", 20, 10, 80, 40, (255, 255, 255))
    ink = np.argwhere(img.max(axis=2) > 0)
    assert len(ink) > 50
    assert ink[:, 0].min() >= 10 and ink[:, 0].max() < 40 and ink[:, 1].min() >= 20 and ink[:, 1].max() < 80
    blank = np.zeros((60, 100, 3), np.uint8)
    tx.put_text_box(blank, "", 0, 0, 100, 60, (255, 255, 255))
    tx.put_text_box(blank, "X", 0, 0, 3, 60, (255, 255, 255))  # a box too small to write in
    assert not blank.any()


def test_zebra_crossings_sit_at_the_chosen_ends() -> None:
    """Crossings draw no random numbers: with one seed, roads differ only within 5 m of an end."""
    ppm, length = 12.0, 40.0
    plain = tx.road(np.random.default_rng(5), length, 12.0, ppm, zebra=(False, False))
    start = tx.road(np.random.default_rng(5), length, 12.0, ppm, zebra=(True, False))
    both = tx.road(np.random.default_rng(5), length, 12.0, ppm, zebra=(True, True))
    reach = int(round(4.8 * ppm)) + 2  # crossing from 0.6 m, 3 m wide, stop line 0.9..1.2 m beyond
    cols = np.nonzero((start != plain).any(axis=(0, 2)))[0]
    assert len(cols) and cols.max() < reach
    cols = np.nonzero((both != start).any(axis=(0, 2)))[0]
    assert len(cols) and cols.min() >= plain.shape[1] - reach


def test_sky_panorama_wraps_around() -> None:
    horizon, zenith, cloud = (230.0, 210.0, 200.0), (200.0, 150.0, 90.0), (240.0, 240.0, 245.0)
    sky = tx.sky_panorama(np.random.default_rng(1), 512, 64, horizon, zenith, 0.4, cloud)
    assert sky.shape == (64, 512, 3) and sky.dtype == np.uint8
    seam = np.abs(sky[:, 0].astype(int) - sky[:, -1].astype(int)).mean()
    apart = np.abs(sky[:, 0].astype(int) - sky[:, 256].astype(int)).mean()
    assert seam < 0.5 * apart + 1.0
