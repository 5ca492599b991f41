"""The FAB-MAP New College and City Centre releases (Cummins and Newman, 2008).

Each release is a folder of JPEG images taken alternately by the robot's left and right
cameras (which face sideways, they are not a stereo pair): image 0001 left, 0002 right, 0003
left, ... In 0-based frame order the even indices are the left camera. The ground truth
(``NewCollegeGroundTruth.mat``, ``CityCentreGroundTruth.mat``) covers every image in that
interleaved order, so it is reduced the same way as the images (see
:func:`stablecues.groundtruth.select_view`).

Layout::

    DIR/Images/*.jpg          (or DIR/images/, or the images directly in DIR)
    DIR/*GroundTruth*.mat     optional
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from ..errors import DatasetError
from ..groundtruth import GroundTruth, fit_view, load_ground_truth
from ..imageio import list_images
from .base import FrameRecord, SequenceDataset

FabmapView = Literal["left", "right", "all"]


@dataclass
class FabmapDataset(SequenceDataset):
    """A FAB-MAP release seen through one camera ("left", "right") or every image ("all")."""

    view: str = "left"

    def ground_truth(self) -> GroundTruth | None:
        """The release's loop matrix reduced to this dataset's view.

        A matrix over every image (2M x 2M) is reduced to the view; one already of this
        dataset's length (a per-camera copy, like ``city_GT_final.mat``) is taken as is.

        Raises:
            DatasetError: the matrix fits neither.
        """
        if self.gt_path is None:
            return None
        gt = load_ground_truth(self.gt_path)
        if self.view == "all":
            if gt.n != len(self):
                raise DatasetError(
                    f"{self.gt_path}: expected a {len(self)} x {len(self)} matrix, found {gt.n}"
                )
            return gt
        return fit_view(gt, "left" if self.view == "left" else "right", len(self))

    def describe(self) -> dict[str, Any]:
        """As :meth:`SequenceDataset.describe`, plus the ground-truth view for ``stablecues eval``."""
        return {**super().describe(), "gt_view": self.view}


def open_fabmap(path: str | Path, *, view: FabmapView = "left", grey: bool = False) -> FabmapDataset:
    """Open a FAB-MAP release folder.

    Args:
        path: the release folder.
        view: "left" (images 1, 3, 5, ...), "right" (2, 4, 6, ...) or "all" (every image in
            the interleaved order).
        grey: read images as (H, W) grey.

    Raises:
        DatasetError: missing folder or images, or an unknown view.
    """
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(f"{root}: FAB-MAP release folder not found")
    if view not in ("left", "right", "all"):
        raise DatasetError(f"view: expected 'left', 'right' or 'all', got {view!r}")
    image_dir = next((root / d for d in ("Images", "images") if (root / d).is_dir()), root)
    images = list_images(image_dir)
    if view == "left":
        images = images[0::2]
    elif view == "right":
        images = images[1::2]
    gts = sorted(p for p in root.glob("*[Gg]round[Tt]ruth*.mat") if p.is_file())
    if len(gts) > 1:
        raise DatasetError(f"{root}: expected one *GroundTruth*.mat, found {[p.name for p in gts]}")
    return FabmapDataset(
        root=root,
        records=[FrameRecord(image=p) for p in images],
        format="fabmap",
        gt_path=gts[0] if gts else None,
        grey=grey,
        view=view,
    )
