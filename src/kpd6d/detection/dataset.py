"""Detection training data over a BOP dataset: images resized to the network input, boxes in
network pixels, labels as class indices of a fixed ``obj_ids`` list.

``box='bbox_visib'`` (default) trains on the visible part's box, ``box='bbox_obj'`` on the full
projected box clipped to the image (an amodal detector). Instances with ``visib_fract < min_visib_fract`` (or an empty box) are left out.

``train_crop=(w, h)`` trains on windows of the network input: each item is a random ``w x h`` window
(containing the centre of one of its kept boxes, drawn uniformly, when there is one) of the image
resized to ``input_size``, its boxes shifted and clipped to the window, those keeping under
``min_kept`` of their area or under ``min_box_size`` px dropped. A detector then trains at the
resolution it runs at (e.g. ``input_size`` 640x480, the full LM-O frame) for the cost of a
``w x h`` input.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from kpd6d.data.bop_io import BOX_FIELDS, DEFAULT_BOX_FIELD
from kpd6d.detection.detections import DetectionInputError
from kpd6d.geometry import clip_xywh_to_image

__all__ = ["DetectionDataset", "collate_detection"]


class DetectionDataset(Dataset):
    """``ds[i] -> (image (3, h, w) float [0, 1], target)``; target holds ``boxes`` (n, 4) xywh network
    px, ``labels`` (n,) class indices, ``obj_ids`` (n,), ``scale`` (2,) = original px per network px,
    ``orig_boxes`` (n, 4) xywh original px and ``frame`` (scene_id, im_id)."""

    def __init__(self, root: str | os.PathLike, split: str = "train", obj_ids: Sequence[int] | None = None,
                 box: str = DEFAULT_BOX_FIELD, min_visib_fract: float = 0.1, input_size: Sequence[int] | None = (320, 240),
                 min_box_size: float = 2.0, train_crop: Sequence[int] | None = None, min_kept: float = 0.3) -> None:
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
        self.train_crop = None
        if train_crop is not None:
            try:
                tc = tuple(int(v) for v in train_crop)
            except (TypeError, ValueError):
                tc = ()
            if len(tc) != 2 or min(tc) <= 0:
                raise DetectionInputError(f"train_crop must be (width, height) > 0, got {train_crop!r}")
            self.train_crop = tc
        if not 0.0 <= float(min_kept) <= 1.0:
            raise DetectionInputError(f"min_kept must be in [0, 1], got {min_kept!r}")
        self.min_kept = float(min_kept)

    def __len__(self) -> int:
        return len(self.bop)

    def annotations(self, i: int, image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Kept (boxes (n, 4) xywh original px, obj_ids (n,)) of frame ``i``, whose image is ``image_size``
        (width, height) px."""
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
            if self.box == "bbox_obj":  # the whole object's box, clipped to the image (the part a detector can see)
                clipped = clip_xywh_to_image(b, *image_size, min_size=0.0)
                if clipped is None:
                    continue
                b = clipped.astype(np.float32)
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
        boxes, ids = self.annotations(i, (W, H))
        scale = np.array([sx, sy, sx, sy], dtype=np.float32)
        net_boxes = boxes / scale
        if self.train_crop is not None:
            rgb, net_boxes, ids, origin = self._crop(rgb, net_boxes, ids)
            boxes = (net_boxes + np.float32([*origin, 0, 0])) * scale  # the kept parts, original px
        image = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float() / 255.0
        target = {
            "boxes": torch.from_numpy(net_boxes),
            "labels": torch.tensor([self._cls[o] for o in ids.tolist()], dtype=torch.long),
            "obj_ids": torch.from_numpy(ids),
            "scale": torch.tensor([sx, sy], dtype=torch.float32),
            "orig_boxes": torch.from_numpy(boxes),
            "frame": (frame.scene_id, frame.im_id),
        }
        return image, target

    def _crop(self, rgb: np.ndarray, boxes: np.ndarray, ids: np.ndarray):
        """A random ``train_crop`` window of ``rgb`` (network px), its boxes and ids (see the module
        docstring) and its origin (x0, y0) in ``rgb``."""
        H, W = rgb.shape[:2]
        cw, ch = min(self.train_crop[0], W), min(self.train_crop[1], H)
        rng = np.random.default_rng(int(torch.randint(0, 2**31 - 1, ()).item()))  # torch's seed / worker seeds
        if len(boxes):
            b = boxes[int(rng.integers(len(boxes)))]
            cx, cy = b[0] + b[2] / 2, b[1] + b[3] / 2  # the window [x0, x0 + cw) holds the centre
            x0, y0 = _window_start(cx, cw, W, rng), _window_start(cy, ch, H, rng)
        else:
            x0, y0 = int(rng.integers(0, W - cw + 1)), int(rng.integers(0, H - ch + 1))
        lo = np.maximum(boxes[:, :2] - (x0, y0), 0.0)
        hi = np.minimum(boxes[:, :2] + boxes[:, 2:] - (x0, y0), (cw, ch))
        wh = np.clip(hi - lo, 0.0, None)
        keep = (wh >= self.min_box_size).all(1) & (wh.prod(1) >= self.min_kept * boxes[:, 2:].prod(1))
        out = np.concatenate([lo, wh], 1)[keep].astype(np.float32).reshape(-1, 4)
        return rgb[y0:y0 + ch, x0:x0 + cw], out, ids[keep], (x0, y0)


def _window_start(c: float, side: int, n: int, rng: np.random.Generator) -> int:
    """A start ``s`` uniform over the windows [s, s + side) within [0, n) that hold pixel ``floor(c)``."""
    p = int(np.floor(c))
    lo, hi = max(0, p - side + 1), min(n - side, max(0, p))
    return int(rng.integers(min(lo, hi), hi + 1))


def collate_detection(batch):
    """Stack same-size images; keep the targets as a list."""
    images = [b[0] for b in batch]
    shapes = {tuple(im.shape) for im in images}
    if len(shapes) != 1:
        raise DetectionInputError(f"images in a batch differ in size {sorted(shapes)}; set input_size")
    return torch.stack(images), [b[1] for b in batch]
