"""Training a vocabulary: hierarchical clustering of binary or float descriptors.

As DBoW2's ``TemplatedVocabulary::create``: the descriptors are split into k clusters with
k-means++ seeding, every cluster with more than one descriptor is split again, down to L
levels; a node with at most k descriptors gets one child per descriptor. Binary descriptors
(uint8, any byte width) are clustered with Hamming distance and bitwise-majority centres
(k-majority), float descriptors (float32) with squared Euclidean distance and mean centres
(Lloyd's k-means). Words are the leaves; their IDF weight is ``log(N / N_i)`` over the
training images (N images, N_i of them containing the word).

Seeded and deterministic per subtree: the clustering of a node draws from its own random
stream, ``SeedSequence(seed, spawn_key=path)`` with ``path`` the child slots from the root to
the node, and sees exactly the descriptors under it, in their input order. A subtree is
therefore the same whether it is grown in this process, in any order, or as a task on another
machine (:mod:`.distributed`); node ids are given at the end, breadth first (by depth, then by
path), as DBoW2 numbers them.

Float distances are reproducible to the bit wherever they run: a matrix product (BLAS, whose
rounding depends on its thread count) only ranks the centres, and any descriptor whose two
nearest centres are closer than its rounding bound is decided again by a sum in a fixed order.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from ..errors import InputError
from ..types import DescriptorKind
from .clustering import (  # noqa: F401 (the tree-growing pieces, importable from here as before)
    Nodes,
    assemble_tree,
    expand,
    grow_subtree,
    nearest_centre,
    squared_l2_exact,
)
from .descriptors import check_descriptors
from .scoring import Scoring, Weighting
from .tree import Vocabulary

if TYPE_CHECKING:
    from distributed import Client

log = logging.getLogger(__name__)

def check_training_sets(descriptor_sets: Sequence[np.ndarray]) -> DescriptorKind:
    """The descriptor kind all training images share.

    Raises:
        InputError: an image whose descriptors are not (N, D) uint8 or float32, kinds that
            differ between images, NaN or infinite float values, no descriptor at all.
    """
    kind: DescriptorKind | None = None
    for i, d in enumerate(descriptor_sets):
        name = f"descriptors of training image {i}"
        got = DescriptorKind.of(d, name)
        if kind is None:
            kind = got
        elif got != kind:
            raise InputError(f"{name}: {got}, but the images before are {kind}: one kind per vocabulary")
        check_descriptors(d, name, kind)
    if kind is None or sum(d.shape[0] for d in descriptor_sets) == 0:
        raise InputError("vocabulary training needs at least one descriptor")
    return kind


def train_vocabulary(
    descriptor_sets: Sequence[np.ndarray],
    k: int = 10,
    levels: int = 5,
    weighting: Weighting = Weighting.TF_IDF,
    scoring: Scoring = Scoring.L1,
    seed: int = 0,
    max_iter: int = 15,
    levels_up: int | None = None,
    progress: bool = True,
    client: Client | None = None,
) -> Vocabulary:
    """Train a vocabulary tree from the descriptors of a set of training images.

    Args:
        descriptor_sets: one array per training image, all of one kind: (N_i, B) uint8 binary
            descriptors (ORB's B = 32, or any width) or (N_i, D) float32 ones (SIFT's D = 128,
            or a learned model's).
        k: branching factor (>= 2).
        levels: depth L (>= 1).
        weighting: word weighting.
        scoring: scoring the vocabulary's BoW vectors are normalised for.
        seed: random seed; the same inputs and seed give the same tree, serial or distributed.
        max_iter: clustering iterations per node.
        levels_up: default direct-index level of the returned vocabulary (None: L - 2).
        progress: show a progress bar.
        client: a ``dask.distributed`` client: the subtrees under the root's children are
            clustered as tasks on its workers (:mod:`.distributed`); the vocabulary is the
            one a serial run makes.

    Returns:
        The trained vocabulary, of the descriptors' kind.

    Raises:
        InputError: k < 2 or L < 1, malformed or mixed descriptors, no descriptor at all.
    """
    if k < 2 or levels < 1:
        raise InputError(f"vocabulary training needs k >= 2 and L >= 1, got k={k}, L={levels}")
    kind = check_training_sets(descriptor_sets)
    sets = list(descriptor_sets)
    data = np.ascontiguousarray(np.concatenate(sets, axis=0))
    if client is not None:
        from .distributed import grow_tree_distributed

        nodes = grow_tree_distributed(client, data, k, levels, seed, max_iter)
    else:
        with tqdm(total=data.shape[0] * levels, desc="vocabulary", unit="desc", disable=not progress,
                  leave=False) as bar:
            nodes = grow_subtree(data, (), 0, k, levels, seed, max_iter, bar)
    parents, centres = assemble_tree(nodes, kind.size, kind.dtype)
    return weigh_vocabulary(Vocabulary(k, levels, parents, centres, np.zeros(parents.size), weighting,
                                       scoring, levels_up), sets)


def weigh_vocabulary(voc: Vocabulary, sets: Sequence[np.ndarray]) -> Vocabulary:
    """``voc`` with its word weights set from the training images: IDF ``log(N / N_i)`` for
    TF-IDF and IDF weighting, 1 for TF and binary."""
    weights = np.zeros(voc.n_nodes, np.float64)
    if voc.weighting in (Weighting.TF_IDF, Weighting.IDF):
        counts = np.zeros(voc.n_words, np.int64)
        for d in sets:
            if d.shape[0]:
                counts[np.unique(voc.node_word[voc.leaves_of(d)])] += 1
        weights[voc.word_nodes] = np.log(len(sets) / np.maximum(counts, 1))
    else:
        weights[voc.word_nodes] = 1.0
    log.info("trained vocabulary: %d nodes, %d words", voc.n_nodes, voc.n_words)
    return Vocabulary(voc.k, voc.levels, voc.parents, voc.descriptors, weights, voc.weighting,
                      voc.scoring, voc.levels_up)
