"""Detection training data over a BOP dataset: images resized to the network input, boxes in
network pixels, labels as class indices of a fixed ``obj_ids`` list.

``box='bbox_visib'`` (default) trains on the visible part's box, ``box='bbox_obj'`` on the full
projected box. Instances with ``visib_fract < min_visib_fract`` (or an empty box) are left out.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from kpd6d.detection.detections import DetectionInputError

__all__ = ["BOX_FIELDS", "DetectionDataset", "collate_detection"]

BOX_FIELDS = ("bbox_visib", "bbox_obj")


class DetectionDataset(Dataset):
    """``ds[i] -> (image (3, h, w) float [0, 1], target)``; target holds ``boxes`` (n, 4) xywh network
    px, ``labels`` (n,) class indices, ``obj_ids`` (n,), ``scale`` (2,) = original px per network px,
    ``orig_boxes`` (n, 4) xywh original px and ``frame`` (scene_id, im_id)."""

    def __init__(self, root: str | os.PathLike, split: str = "train", obj_ids: Sequence[int] | None = None,
                 box: str = "bbox_visib", min_visib_fract: float = 0.1, input_size: Sequence[int] | None = (320, 240),
                 min_box_size: float = 2.0) -> None:
        from kpd6d.data import BopDataset

        if box not in BOX_FIELDS:
            raise DetectionInputError(f"box must be one of {BOX_FIELDS}, got {box!r}")
        self.bop = BopDataset(root, split)
        self.obj_ids = sorted(int(o) for o in obj_ids) if obj_ids is not None else self.bop.instance_obj_ids()
        if not self.obj_ids:
            raise DetectionInputError(f"{self.bop.split_dir}: no annotated object instances")
        self.box, self.min_visib_fract, self.min_box_size = box, float(min_visib_fract), float(min_box_size)
        self.input_size = tuple(int(s) for s in input_size) if input_size is not None else None
        self._cls = {oid: i for i, oid in enumerate(self.obj_ids)}

    def __len__(self) -> int:
        return len(self.bop)

    def annotations(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Kept (boxes (n, 4) xywh original px, obj_ids (n,)) of frame ``i``."""
        frame = self.bop[i]
        boxes, ids = [], []
        for inst in frame.instances:
            if inst.obj_id not in self._cls:
                continue
            b = getattr(inst, self.box)
            if b is None:
                raise DetectionInputError(f"{frame.scene_dir}: instance {inst.gt_index} of image {frame.im_id} has no "
                                          f"{self.box} (scene_gt_info.json missing?)")
            if inst.visib_fract is not None and inst.visib_fract < self.min_visib_fract:
                continue
            b = np.asarray(b, dtype=np.float32)
            if b[2] < self.min_box_size or b[3] < self.min_box_size:
                continue
            boxes.append(b)
            ids.append(inst.obj_id)
        return np.asarray(boxes, dtype=np.float32).reshape(-1, 4), np.asarray(ids, dtype=np.int64)

    def __getitem__(self, i: int):
        frame = self.bop[i]
        rgb = frame.load_rgb()
        H, W = rgb.shape[:2]
        sx = sy = 1.0
        if self.input_size is not None and (W, H) != self.input_size:
            w, h = self.input_size
            rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
            sx, sy = W / w, H / h
        boxes, ids = self.annotations(i)
        scale = np.array([sx, sy, sx, sy], dtype=np.float32)
        image = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float() / 255.0
        target = {
            "boxes": torch.from_numpy(boxes / scale),
            "labels": torch.tensor([self._cls[o] for o in ids.tolist()], dtype=torch.long),
            "obj_ids": torch.from_numpy(ids),
            "scale": torch.tensor([sx, sy], dtype=torch.float32),
            "orig_boxes": torch.from_numpy(boxes),
            "frame": (frame.scene_id, frame.im_id),
        }
        return image, target


def collate_detection(batch):
    """Stack same-size images; keep the targets as a list."""
    images = [b[0] for b in batch]
    shapes = {tuple(im.shape) for im in images}
    if len(shapes) != 1:
        raise DetectionInputError(f"images in a batch differ in size {sorted(shapes)}; set input_size")
    return torch.stack(images), [b[1] for b in batch]
