"""ONNX export parity, MC-dropout sampling, output shapes and clear errors of the inference wrapper."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stablecues.errors import ConfigError, InputError, ModelError
from stablecues.semantics import SegmentationModel
from stablecues.semantics.data import read_rgb
from stablecues.semantics.inference import class_map, default_weights_path, summarize_samples
from stablecues.vocabulary.engine import compiled_kernels

TINY_WIDTHS = (4, 8, 8, 16)
TINY_SIZE = (48, 64)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> tuple[object, Path]:
    """A randomly initialised small network and its ONNX export (needs torch)."""
    torch = pytest.importorskip("torch", reason="torch not installed (the train extra)")
    pytest.importorskip("onnx", reason="onnx not installed (the train extra)")
    from stablecues.semantics.export import export_onnx
    from stablecues.semantics.model import BayesLiteSeg

    torch.manual_seed(0)
    net = BayesLiteSeg(TINY_WIDTHS)
    # non-trivial batch-norm statistics, so that folding them is exercised
    net.train()
    with torch.no_grad():
        for _ in range(3):
            net(torch.rand(2, 3, *TINY_SIZE))
    net.eval()
    path = tmp_path_factory.mktemp("onnx") / "tiny.onnx"
    export_onnx(net, path, TINY_SIZE)
    (path.with_suffix(".json")).write_text('{"input_size": [48, 64], "default_t": 4, "dropout_p": 0.5}')
    return net, path


def test_onnx_matches_pytorch(tiny: tuple[object, Path]) -> None:
    import torch

    net, path = tiny
    model = SegmentationModel.load(path, threads=1)
    rng = np.random.default_rng(1)
    for size, t in ((TINY_SIZE, 1), (TINY_SIZE, 3), ((37, 53), 2)):  # also a size the export never saw
        x = rng.random((1, 3, *size), dtype=np.float32)
        m16, m8 = model.masks(t, *size)
        out = model.sample(x, t)
        with torch.no_grad():
            ref = torch.softmax(net(torch.from_numpy(x), torch.from_numpy(m16), torch.from_numpy(m8)), 1)  # type: ignore[operator]
        assert out.shape == (t, 11, -(-size[0] // 4), -(-size[1] // 4))
        np.testing.assert_allclose(out, ref.numpy(), atol=1e-4)


def test_mc_dropout_variance(tiny: tuple[object, Path]) -> None:
    _, path = tiny
    model = SegmentationModel.load(path, threads=1, seed=3)
    image = np.random.default_rng(2).integers(0, 256, (60, 80, 3), dtype=np.uint8)
    det = model.predict(image, 1)
    assert det.samples == 1 and float(np.abs(det.uncertainty).max()) == 0.0
    mc = model.predict(image, 8)
    assert mc.samples == 8 and float(mc.uncertainty.max()) > 0.0
    assert float(mc.uncertainty.min()) >= 0.0 and float(mc.uncertainty.max()) <= 0.25
    mi = model.predict(image, 8, uncertainty="mutual_information")
    assert float(mi.uncertainty.max()) > 0.0
    # masks come from a seeded generator: same seed, same result; another seed differs
    again = SegmentationModel.load(path, threads=1, seed=3).predict(image, 8)
    np.testing.assert_array_equal(again.uncertainty, mc.uncertainty)
    other = SegmentationModel.load(path, threads=1, seed=4).predict(image, 8)
    assert not np.array_equal(other.uncertainty, mc.uncertainty)
    # masks: zeros or 1/(1-p), about half dropped
    m16, m8 = model.masks(8, 48, 64)
    assert set(np.unique(m8).tolist()) == {0.0, 2.0} and 0.4 < float((m8 == 0).mean()) < 0.6
    assert model.predict(image).samples == 4  # the metadata's default T


@pytest.mark.parametrize("shape", [(77, 101), (77, 101, 3), (77, 101, 1), (77, 101, 4), (5, 3)])
def test_output_has_the_image_size(tiny: tuple[object, Path], shape: tuple[int, ...]) -> None:
    _, path = tiny
    model = SegmentationModel.load(path, threads=1)
    image = np.random.default_rng(0).integers(0, 256, shape, dtype=np.uint8)
    r = model.predict(image, 2)
    assert r.labels.shape == (77, 101) if shape[0] == 77 else r.labels.shape == shape[:2]
    assert r.labels.dtype == np.uint8 and int(r.labels.max()) < 11
    assert r.uncertainty.shape == r.labels.shape and r.uncertainty.dtype == np.float32
    assert r.confidence.shape == r.labels.shape and float(r.confidence.max()) <= 1.0 + 1e-6
    assert r.image_size == (shape[1], shape[0])


def test_bad_inputs_raise(tiny: tuple[object, Path]) -> None:
    _, path = tiny
    model = SegmentationModel.load(path, threads=1)
    with pytest.raises(InputError, match="uint8"):
        model.predict(np.zeros((10, 10), np.float32))
    with pytest.raises(InputError, match="shape"):
        model.predict(np.zeros((10, 10, 2), np.uint8))
    with pytest.raises(InputError, match="non-empty"):
        model.predict(np.zeros((0, 10), np.uint8))
    with pytest.raises(ConfigError, match="T"):
        model.predict(np.zeros((10, 10), np.uint8), 0)
    with pytest.raises(ConfigError, match="uncertainty"):
        model.predict(np.zeros((10, 10), np.uint8), 2, uncertainty="entropy")


def test_missing_or_corrupt_weights_name_the_file(tmp_path: Path) -> None:
    missing = tmp_path / "nothere.onnx"
    with pytest.raises(ModelError, match="nothere.onnx"):
        SegmentationModel.load(missing)
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(b"this is not a protobuf" * 10)
    with pytest.raises(ModelError, match="corrupt.onnx"):
        SegmentationModel.load(corrupt)


def test_corrupt_image_file_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "frame.png"
    bad.write_bytes(b"\x89PNG garbage")
    with pytest.raises(InputError, match="frame.png"):
        read_rgb(bad)
    with pytest.raises(InputError, match="not found"):
        read_rgb(tmp_path / "absent.jpg")


def test_summarize_hand_made_samples() -> None:
    # two samples, two classes, 1x2 pixels: pixel 0 agrees, pixel 1 flips
    probs = np.zeros((2, 11, 1, 2), np.float32)
    probs[:, 0, 0, 0] = 0.9
    probs[:, 1, 0, 0] = 0.1
    probs[0, 0, 0, 1], probs[0, 1, 0, 1] = 0.8, 0.2
    probs[1, 0, 0, 1], probs[1, 1, 0, 1] = 0.4, 0.6
    r = summarize_samples(probs, (1, 2))
    assert r.labels.tolist() == [[0, 0]]  # mean 0.6 vs 0.4 at pixel 1
    np.testing.assert_allclose(r.uncertainty, [[0.0, 0.04]], atol=1e-6)  # var of (0.8, 0.4)
    np.testing.assert_allclose(r.confidence, [[0.9, 0.6]], atol=1e-6)


def test_shipped_weights_load_and_segment() -> None:
    if not default_weights_path().is_file():
        pytest.skip(f"shipped weights not built yet: {default_weights_path()}")
    model = SegmentationModel.load()
    assert model.input_size[0] % 16 == 0 and model.default_t >= 1
    r = model.predict(np.full((77, 101, 3), 128, np.uint8))
    assert r.labels.shape == (77, 101)


@pytest.mark.skipif(compiled_kernels() is None, reason="numba is not available")
def test_class_map_engines_agree_with_argmax_on_ties() -> None:
    rng = np.random.default_rng(4)
    scores = rng.random((37, 53, 11), dtype=np.float32)
    scores[::3, ::2] = np.round(scores[::3, ::2], 1)  # many equal maxima: the first one wins
    scores[5, 7, :] = 0.25
    expected = scores.argmax(axis=2).astype(np.uint8)
    for engine in ("numpy", "compiled"):
        out = class_map(scores, engine)
        assert out.dtype == np.uint8 and out.shape == (37, 53)
        np.testing.assert_array_equal(out, expected)
    assert class_map(scores, "compiled")[5, 7] == 0


def _agreement(a: SegmentationModel, b: SegmentationModel, image: np.ndarray) -> tuple[float, float]:
    ra, rb = a.predict(image, 1), b.predict(image, 1)
    return float(np.mean(ra.labels == rb.labels)), abs(ra.frame_certainty() - rb.frame_certainty())


def test_int8_weights_segment_as_the_float_ones() -> None:
    """The shipped int8 quantisation gives (nearly) the float network's classes and certainty:
    on a rendered street frame always, on real CamVid val frames when the data is there."""
    from stablecues.synthetic import SyntheticTownConfig, generate

    fp32, int8 = SegmentationModel.load(threads=1), SegmentationModel.load(threads=1, precision="int8")
    assert int8.path.name == "segnet_camvid_int8.onnx" and int8.input_size == fp32.input_size
    frame = next(iter(generate(SyntheticTownConfig(frames=1, width=480, height=360))))
    same, dcert = _agreement(fp32, int8, frame.image)
    assert same > 0.95 and dcert < 0.02, (same, dcert)
    t = int8.predict(frame.image, 3)  # Monte-Carlo dropout still works: the masks stay float inputs
    assert t.samples == 3 and float(t.uncertainty.max()) > 0
    shared = Path(__file__).resolve().parents[2].parent / "shared" / "data"
    val = sorted((shared / "camvid" / "val").glob("*.jpg"))
    if not val:
        pytest.skip("../shared/data/camvid/val is absent: the real frames' check did not run")
    for f in val[::40]:
        same, dcert = _agreement(fp32, int8, read_rgb(f)[..., ::-1].copy())
        assert same > 0.98 and dcert < 0.01, (f.name, same, dcert)


def test_unknown_precision_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="int4"):
        SegmentationModel.load(precision="int4")
    from stablecues.detection import preset

    with pytest.raises(ConfigError, match="segmentation_precision"):
        preset("default", {"segmentation_precision": "float16"})
    assert preset("default").segmentation_precision == "int8"
    assert preset("paper").segmentation_precision == "float32"


@pytest.mark.parametrize("precision", ["float32", "int8"])
def test_shipped_weights_match_their_metadata(precision: str) -> None:
    """Each shipped ONNX file is the one its metadata describes (the int8 one also names the
    float file it was quantised from)."""
    import hashlib
    import json

    path = default_weights_path(precision)
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["onnx"] == path.name
    assert meta["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    if precision == "int8":
        src = default_weights_path("float32")
        assert meta["quantization"]["from_sha256"] == hashlib.sha256(src.read_bytes()).hexdigest()
