"""ORB extractor: shapes, dtypes, descriptor kind, spread, empty results, bad input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import textured as _textured
from stablecues.errors import ConfigError, InputError
from stablecues.features import OrbConfig, OrbExtractor, distribute_quadtree
from stablecues.features.orb import level_quotas, select_keypoints
from stablecues.types import ORB_DESCRIPTOR, DescriptorKind


def textured(h: int = 240, w: int = 320, seed: int = 0) -> np.ndarray:
    return _textured(h, w, seed, blur=False)


def test_output_shapes_and_dtypes() -> None:
    f = OrbExtractor(OrbConfig(n_features=300)).extract(textured())
    assert 0 < len(f) <= 300
    assert f.keypoints.dtype == np.float32 and f.keypoints.shape == (len(f), 2)
    assert f.descriptors.dtype == np.uint8 and f.descriptors.shape == (len(f), 32)
    assert f.octaves.shape == f.angles.shape == f.responses.shape == f.sizes.shape == (len(f),)
    assert f.image_size == (320, 240)
    assert (f.keypoints[:, 0] >= 0).all() and (f.keypoints[:, 0] < 320).all()


def test_extractor_states_its_descriptor_kind_and_level_scale() -> None:
    ex = OrbExtractor(OrbConfig(n_features=200, scale_factor=1.3))
    assert ex.descriptor_kind == ORB_DESCRIPTOR == DescriptorKind("binary", 32)
    assert ex.level_scale == 1.3
    f = ex.extract(textured())
    assert f.descriptor_kind == ex.descriptor_kind
    # octaves are pyramid levels: keypoint sizes grow with level_scale ** octave
    assert set(np.unique(f.octaves).tolist()) <= set(range(8)) and len(np.unique(f.octaves)) > 1
    np.testing.assert_allclose(f.sizes, 31 * 1.3 ** f.octaves.astype(np.float64), rtol=1e-4)
    assert ex.extract(np.zeros((20, 20), np.uint8)).descriptor_kind == ORB_DESCRIPTOR


def test_config_is_named_orb() -> None:
    assert OrbConfig().name == "orb"
    with pytest.raises(ConfigError, match="'orb'"):
        OrbConfig(name="sift")


def test_colour_and_grey_give_the_same_features() -> None:
    grey = textured()
    colour = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    ex = OrbExtractor(OrbConfig(n_features=200))
    a, b = ex.extract(grey), ex.extract(colour)
    np.testing.assert_array_equal(a.descriptors, b.descriptors)


@pytest.mark.parametrize("shape", [(0, 0), (20, 20), (37, 101)])
def test_tiny_or_blank_images_give_empty_features(shape: tuple[int, int]) -> None:
    f = OrbExtractor().extract(np.zeros(shape, np.uint8))
    assert len(f) == 0 and f.descriptors.shape == (0, 32)


def test_blank_image_of_normal_size_is_empty() -> None:
    assert len(OrbExtractor().extract(np.full((240, 320), 77, np.uint8))) == 0


def test_mask_restricts_keypoints() -> None:
    img = textured()
    mask = np.zeros_like(img)
    mask[:, :160] = 255
    f = OrbExtractor(OrbConfig(n_features=300)).extract(img, mask)
    assert len(f) > 0 and (f.keypoints[:, 0] < 160 + 1).all()


def test_quadtree_spreads_keypoints_more_than_plain_orb() -> None:
    # strong texture in one corner, weak texture elsewhere
    rng = np.random.default_rng(3)
    img = (rng.random((240, 320)) * 40 + 100).astype(np.uint8)
    img[:80, :100] = textured(80, 100, 1)
    img = cv2.GaussianBlur(img, (3, 3), 0)

    def corner_share(cfg: OrbConfig) -> float:
        f = OrbExtractor(cfg).extract(img)
        return float(np.mean((f.keypoints[:, 0] < 100) & (f.keypoints[:, 1] < 80)))

    assert corner_share(OrbConfig(n_features=300)) < corner_share(
        OrbConfig(n_features=300, distribute="none")
    )


def test_level_quotas_sum_and_decrease() -> None:
    q = level_quotas(1000, 1.2, 8)
    assert q.sum() == 1000 and (np.diff(q[:-1]) <= 0).all()


def test_distribute_quadtree_picks_one_per_cell_strongest_first() -> None:
    pts = np.array([[1, 1], [2, 2], [90, 90], [91, 91], [10, 90]], np.float32)
    resp = np.array([1.0, 5.0, 2.0, 1.0, 3.0], np.float32)
    idx = distribute_quadtree(pts, resp, 3, (100, 100))
    assert sorted(idx.tolist()) == [1, 2, 4]
    assert idx.tolist() == [1, 4, 2]


def test_bad_inputs_raise() -> None:
    with pytest.raises(InputError, match="uint8"):
        OrbExtractor().extract(np.zeros((50, 50), np.float32))
    with pytest.raises(InputError, match="shape"):
        OrbExtractor().extract(np.zeros((50, 50, 2), np.uint8))
    with pytest.raises(InputError, match="mask"):
        OrbExtractor().extract(textured(), np.zeros((3, 3), np.uint8))
    with pytest.raises(ConfigError):
        OrbConfig(scale_factor=1.0)


def test_compiled_keypoint_selection_equals_numpy() -> None:
    """The compiled pick over all levels equals the NumPy one per level, ties included: integer
    coordinates on cell borders, equal responses, empty levels, zero quotas, quota carried."""
    pytest.importorskip("numba")
    rng = np.random.default_rng(0)
    for trial in range(400):
        n = int(rng.integers(0, 300))
        levels = int(rng.integers(1, 5))
        w, h = float(rng.integers(1, 200)), float(rng.integers(1, 200))
        grid_x, grid_y = rng.integers(0, int(w), n), rng.integers(0, int(h), n)
        x = grid_x.astype(np.float32) if trial % 2 else rng.random(n, np.float32) * np.float32(w)
        y = grid_y.astype(np.float32) if trial % 3 else rng.random(n, np.float32) * np.float32(h)
        pts = np.stack([x, y], axis=1)
        resp = rng.integers(0, 4, n).astype(np.float32) if trial % 2 else rng.random(n, np.float32)
        octv = rng.integers(0, levels, n).astype(np.int64)
        quotas = rng.integers(0, 120, levels).astype(np.int64)
        if trial % 5 == 0 and n:  # NaN of both signs (0/0 sets the sign bit on x86), infinities, -0
            resp[rng.integers(0, n, 4)] = [np.nan, -np.float32(np.nan), np.inf, -0.0]
        a = select_keypoints(pts, resp, octv, quotas, (w, h), engine="compiled")
        b = select_keypoints(pts, resp, octv, quotas, (w, h), engine="numpy")
        np.testing.assert_array_equal(a, b)


def test_extraction_is_the_same_on_both_engines(monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("numba")
    img = textured(360, 480, seed=4)
    got = {}
    for engine in ("compiled", "numpy"):
        monkeypatch.setenv("STABLECUES_ENGINE", engine)
        got[engine] = OrbExtractor().extract(img)
    a, b = got["compiled"], got["numpy"]
    assert len(a) > 500
    for name in ("keypoints", "descriptors", "octaves", "angles", "responses", "sizes"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_keypoint_spread_without_the_compiler(monkeypatch: pytest.MonkeyPatch) -> None:
    """Where numba is missing or fails, "auto" runs NumPy and "compiled" says how to get it."""
    from stablecues.engine import Kernels
    from stablecues.features import orb

    def no_numba() -> None:
        raise ImportError("No module named 'numba'")

    missing: Kernels[None] = Kernels(no_numba, "ORB's keypoint spread")
    assert missing.get(wait=True) is None and missing.failed()
    monkeypatch.setattr(orb, "_PICK", missing)
    pts = np.array([[1, 1], [50, 50], [90, 10]], np.float32)
    resp = np.array([1.0, 3.0, 2.0], np.float32)
    args = (pts, resp, np.zeros(3, np.int64), np.array([2]), (100, 100))
    assert select_keypoints(*args, engine="auto").tolist() == [1, 2]
    with pytest.raises(ImportError, match="pip install numba"):
        select_keypoints(*args, engine="compiled")
    monkeypatch.setenv("STABLECUES_ENGINE", "gpu")
    with pytest.raises(ConfigError, match="STABLECUES_ENGINE"):
        select_keypoints(*args)


def test_clahe_lifts_a_dark_frame_and_is_checked() -> None:
    """A texture at a twentieth of its contrast (a night frame): ORB's FAST thresholds find few
    corners (11), with CLAHE first most of the budget; off, the frame is used as it is."""
    dark = (textured().astype(np.float32) / 20.0 + 5.0).astype(np.uint8)
    plain = OrbExtractor(OrbConfig(n_features=300)).extract(dark)
    lifted = OrbExtractor(OrbConfig(n_features=300, clahe=2.0)).extract(dark)
    assert len(plain) < 50 and len(lifted) > 200
    same = OrbExtractor(OrbConfig(n_features=300, clahe=0.0)).extract(dark)
    np.testing.assert_array_equal(same.keypoints, plain.keypoints)
    with pytest.raises(ConfigError, match="clahe"):
        OrbConfig(clahe=-1.0)
