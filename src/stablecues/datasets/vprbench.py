"""Two-pass place-recognition sets in the VPR-Bench layout, evaluated as one sequence.

Layout::

    DIR/ref/*         reference traverse (sorted by name)
    DIR/query/*       query traverse
    DIR/ground_truth_new.npy   object array, rows [query i, [matching ref ids]] (a pickle,
                               read by a restricted unpickler: arrays, lists, ints only)

The sequence is every reference image, then every query: frame ``k < R`` is ``ref`` image ``k``
and frame ``R + i`` is query ``i``; the reference frames are session 0 and the queries session 1
(:attr:`~stablecues.types.Frame.session`: two traversals recorded apart). The loop ground truth
maps onto these combined indices and marks only the query frames as queries
(:class:`~stablecues.groundtruth.GroundTruth` ``query_mask``), so detections made during the
reference pass are not scored.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import DatasetError
from ..imageio import list_images
from .base import FrameRecord, SequenceDataset

GT_NAME = "ground_truth_new.npy"


def open_vprbench(path: str | Path, *, grey: bool = False) -> SequenceDataset:
    """Open a VPR-Bench two-pass set as one sequence (reference pass, then query pass).

    Args:
        path: the set's folder, holding ``ref/`` and ``query/``.
        grey: read images as (H, W) grey.

    Raises:
        DatasetError: missing ``ref/`` or ``query/`` folder or images.
    """
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(f"{root}: VPR-Bench set folder not found")
    for sub in ("ref", "query"):
        if not (root / sub).is_dir():
            raise DatasetError(
                f"{root}: expected a VPR-Bench set with ref/ and query/ folders, {sub}/ is missing"
            )
    refs = list_images(root / "ref", "reference images")
    queries = list_images(root / "query", "query images")
    records = [FrameRecord(image=p, name=f"ref/{p.name}", session=0) for p in refs]
    records += [FrameRecord(image=p, name=f"query/{p.name}", session=1) for p in queries]
    gt = root / GT_NAME
    return SequenceDataset(
        root=root,
        records=records,
        format="vprbench",
        gt_path=gt if gt.is_file() else None,
        grey=grey,
        gt_options={"n_ref": len(refs)},
    )
