"""Vocabulary training on a ``dask.distributed`` cluster (the ``dask`` extra).

Two kinds of tasks: feature extraction (a batch of training images each) and the clustering
of subtrees. The client clusters the top of the tree itself (the root, or the first
``task_depth`` levels), then every node left to split at that depth becomes one task that grows
its whole subtree on a worker (:func:`.train.grow_subtree`). Each node's clustering draws from
its own random stream and sees exactly the descriptors a serial run gives it, and float
distances do not depend on the machine's BLAS, so the vocabulary is the serial one, word for
word (``tests/vocabulary/test_vocab_distributed.py`` checks it on a ``LocalCluster`` with
separate worker processes).

``dask`` is imported by the caller's client only; this module imports nothing of it at load.
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from .clustering import Nodes, expand, grow_subtree

if TYPE_CHECKING:
    from distributed import Client

    from ..features import ExtractorConfig

#: training images per feature-extraction task
IMAGES_PER_TASK = 8


def grow_tree_distributed(
    client: Client, data: np.ndarray, k: int, levels: int, seed: int, max_iter: int,
    task_depth: int = 1,
) -> Nodes:
    """Every node of the tree over ``data`` (see :func:`.train.expand`), the subtrees below
    depth ``task_depth`` grown as tasks on the client's workers.

    Args:
        client: a connected ``distributed.Client``.
        data: (N, D) all training descriptors, in input order.
        k, levels, seed, max_iter: as :func:`.train.train_vocabulary`.
        task_depth: depth (>= 1) of the nodes whose subtrees are tasks: about ``k ** task_depth``
            tasks. The result does not depend on it.

    Returns:
        (path, centre) of every node but the root.
    """
    from distributed import as_completed

    nodes, pending = expand(data, (), 0, k, levels, seed, max_iter, until=max(1, task_depth))
    token = uuid.uuid4().hex[:12]
    futures = []
    for path, idx, level in pending:
        name = ".".join(map(str, path))
        part = client.scatter(data[idx], hash=False)
        futures.append(client.submit(grow_subtree, part, path, level, k, levels, seed, max_iter,
                                     key=f"stablecues-vocab-subtree-{token}-{name}"))
    for future in as_completed(futures):
        nodes += future.result()
    return nodes


def _extract_batch(
    files: Sequence[Path], config: ExtractorConfig, progress: bool = False
) -> list[np.ndarray]:
    """Descriptors of a batch of images (grey) with the extractor ``config`` describes."""
    from ..features import make_extractor
    from ..imageio import read_image

    extractor = make_extractor(config)
    return [extractor.extract(read_image(f, "grey")).descriptors
            for f in tqdm(files, desc=config.name.upper(), disable=not progress)]


def extract_descriptor_sets(
    files: Sequence[Path], config: ExtractorConfig, client: Client | None = None,
    progress: bool = True,
) -> list[np.ndarray]:
    """The descriptors of each training image, in the order of ``files``.

    Args:
        files: image files.
        config: the extractor's settings (e.g. ``OrbConfig()``, ``SiftConfig()``).
        client: a ``distributed.Client``: batches of :data:`IMAGES_PER_TASK` images become
            tasks on its workers; None: extracted here.
        progress: show a progress bar.

    Raises:
        InputError (or another StableCuesError): an image that cannot be read.
    """
    if client is None:
        return _extract_batch(files, config, progress)
    from distributed import wait

    batches = [list(files[i : i + IMAGES_PER_TASK]) for i in range(0, len(files), IMAGES_PER_TASK)]
    token = uuid.uuid4().hex[:12]
    futures = [client.submit(_extract_batch, b, config, key=f"stablecues-vocab-features-{token}-{i}")
               for i, b in enumerate(batches)]
    wait(futures)
    return [d for f in futures for d in f.result()]
