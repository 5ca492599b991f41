"""Vocabulary training on a real dask ``LocalCluster`` (separate worker processes): feature
extraction and subtree clustering as tasks give the serial vocabulary, word for word."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.cli.main import main
from stablecues.cli.vocab import dask_client
from stablecues.errors import ConfigError
from stablecues.features import OrbConfig, SiftConfig
from stablecues.vocabulary import Vocabulary, train_vocabulary
from stablecues.vocabulary.distributed import extract_descriptor_sets, grow_tree_distributed
from stablecues.vocabulary.train import assemble_tree, expand, grow_subtree

distributed = pytest.importorskip("distributed", reason="the dask extra is not installed")


@pytest.fixture(scope="module")
def client() -> Iterator[distributed.Client]:
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as c:
        yield c


def write_images(folder: Path, n: int = 10) -> list[Path]:
    folder.mkdir()
    rng = np.random.default_rng(0)
    files = []
    for i in range(n):
        img = np.full((160, 200), 120, np.uint8)
        for _ in range(80):
            x, y = int(rng.integers(0, 190)), int(rng.integers(0, 150))
            cv2.circle(img, (x, y), int(rng.integers(2, 12)), int(rng.integers(0, 256)), -1)
        files.append(folder / f"{i:03d}.png")
        cv2.imwrite(str(files[-1]), img)
    return files


def same(a: Vocabulary, b: Vocabulary) -> None:
    assert a.fingerprint == b.fingerprint
    np.testing.assert_array_equal(a.parents, b.parents)
    np.testing.assert_array_equal(a.descriptors, b.descriptors)  # bit for bit
    np.testing.assert_array_equal(a.weights, b.weights)


def test_subtrees_grown_in_any_order_give_the_same_tree() -> None:
    rng = np.random.default_rng(2)
    data = rng.normal(0, 40, (900, 8)).astype(np.float32)
    whole = grow_subtree(data, (), 0, 4, 4, 7, 15)
    top, pending = expand(data, (), 0, 4, 4, 7, 15, until=2)
    assert len(pending) > 4 and all(len(p[0]) == 2 for p in pending)
    pieces = list(top)
    for path, idx, level in reversed(pending):  # another order, each on its own data
        pieces += grow_subtree(data[idx].copy(), path, level, 4, 4, 7, 15)
    a = assemble_tree(whole, 8, np.dtype(np.float32))
    b = assemble_tree(pieces, 8, np.dtype(np.float32))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


@pytest.mark.parametrize("kind", ["float", "binary"])
def test_distributed_training_equals_serial(client: distributed.Client, kind: str) -> None:
    rng = np.random.default_rng(5)
    if kind == "float":
        sets = [rng.integers(0, 150, (400, 128)).astype(np.float32) for _ in range(8)]
    else:
        sets = [rng.integers(0, 256, (400, 32), dtype=np.uint8) for _ in range(8)]
    serial = train_vocabulary(sets, k=5, levels=4, seed=3, progress=False)
    same(train_vocabulary(sets, k=5, levels=4, seed=3, progress=False, client=client), serial)
    data = np.concatenate(sets)
    deeper = grow_tree_distributed(client, data, 5, 4, 3, 15, task_depth=2)
    parents, centres = assemble_tree(deeper, data.shape[1], data.dtype)
    np.testing.assert_array_equal(parents, serial.parents)
    np.testing.assert_array_equal(centres, serial.descriptors)


def test_feature_extraction_tasks_keep_the_image_order(client: distributed.Client, tmp_path: Path) -> None:
    files = write_images(tmp_path / "imgs", n=11)  # two batches and a partial one
    for config in (OrbConfig(n_features=150), SiftConfig(n_features=150)):
        here = extract_descriptor_sets(files, config, progress=False)
        there = extract_descriptor_sets(files, config, client)
        assert len(there) == len(files)
        for a, b in zip(here, there, strict=True):
            np.testing.assert_array_equal(a, b)


def test_cli_train_with_a_scheduler_writes_the_serial_file(tmp_path: Path,
                                                          client: distributed.Client) -> None:
    write_images(tmp_path / "imgs", n=6)
    serial, dist = tmp_path / "serial.scv", tmp_path / "dist.scv"
    common = ["vocab", "train", str(tmp_path / "imgs"), "--k", "4", "--levels", "3",
              "--features", "sift", "--n-features", "120"]
    assert main([*common, "--out", str(serial)]) == 0
    assert main([*common, "--out", str(dist), "--scheduler", client.scheduler.address]) == 0
    assert serial.read_bytes() == dist.read_bytes()


def test_an_unreachable_scheduler_is_one_line() -> None:
    with (pytest.raises(ConfigError, match="--scheduler tcp://127.0.0.1:9: cannot connect") as err,
          dask_client("tcp://127.0.0.1:9", timeout="1s")):
        pass
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="--workers must be >= 1"), dask_client("local", workers=0):
        pass
