"""Measuring the detector's box errors: match predicted to ground-truth boxes by IoU and fit the
box-error statistics that the KPD's ``pgpg`` box augmentation samples from (fitting, file format
and loading: :mod:`kpd6d.box_errors`, shared by both stages)."""

from __future__ import annotations

import numpy as np
import torch

from kpd6d.box_errors import fit_box_error_stats
from kpd6d.detection.detections import xywh_to_xyxy

__all__ = ["BoxErrorCollector", "match_boxes"]


def match_boxes(pred_boxes, pred_ids, gt_boxes, gt_ids, iou_threshold: float = 0.5):
    """Greedy one-to-one matching of score-sorted predictions to GT boxes of the same object id.

    Each prediction in order takes the unmatched same-id GT box of highest IoU if that IoU is at
    least ``iou_threshold``. Returns (pred_index, gt_index) long tensors of the matched pairs.
    """
    from torchvision.ops import box_iou

    pb = torch.as_tensor(pred_boxes, dtype=torch.float64).reshape(-1, 4)
    gb = torch.as_tensor(gt_boxes, dtype=torch.float64).reshape(-1, 4).to(pb.device)
    pi = torch.as_tensor(pred_ids).reshape(-1).to(pb.device)
    gi = torch.as_tensor(gt_ids).reshape(-1).to(pb.device)
    if len(pb) == 0 or len(gb) == 0:
        e = torch.zeros(0, dtype=torch.long)
        return e, e
    iou = box_iou(xywh_to_xyxy(pb), xywh_to_xyxy(gb))
    iou = torch.where(pi[:, None] == gi[None, :], iou, torch.full_like(iou, -1.0)).cpu()
    taken = torch.zeros(len(gb), dtype=torch.bool)
    p_idx, g_idx = [], []
    for p in range(len(pb)):
        row = torch.where(taken, torch.full_like(iou[p], -1.0), iou[p])
        j = int(torch.argmax(row))
        if row[j] >= iou_threshold:
            taken[j] = True
            p_idx.append(p)
            g_idx.append(j)
    return torch.tensor(p_idx, dtype=torch.long), torch.tensor(g_idx, dtype=torch.long)


class BoxErrorCollector:
    """Accumulates matched (GT, prediction) box pairs; :meth:`stats` fits the pgpg statistics."""

    def __init__(self, iou_threshold: float = 0.5) -> None:
        self.iou_threshold = float(iou_threshold)
        self.gt: list[np.ndarray] = []
        self.pred: list[np.ndarray] = []
        self.ids: list[np.ndarray] = []
        self.num_gt = 0

    def reset(self) -> None:
        self.__init__(self.iou_threshold)

    def add(self, pred_boxes, pred_ids, gt_boxes, gt_ids) -> None:
        p, g = match_boxes(pred_boxes, pred_ids, gt_boxes, gt_ids, self.iou_threshold)
        self.num_gt += int(torch.as_tensor(gt_ids).numel())
        if len(p):
            self.pred.append(torch.as_tensor(pred_boxes).reshape(-1, 4)[p].double().cpu().numpy())
            self.gt.append(torch.as_tensor(gt_boxes).reshape(-1, 4)[g].double().cpu().numpy())
            self.ids.append(torch.as_tensor(gt_ids).reshape(-1)[g].cpu().numpy())

    def gather(self) -> None:
        """Under DDP: replace this rank's pairs with every rank's (in rank order) so that :meth:`stats`
        sees all of them; nothing happens in one process."""
        from kpd6d.distributed import all_gather_objects

        parts = all_gather_objects((self.gt, self.pred, self.ids, self.num_gt))
        if len(parts) > 1:
            self.gt = [a for p in parts for a in p[0]]
            self.pred = [a for p in parts for a in p[1]]
            self.ids = [a for p in parts for a in p[2]]
            self.num_gt = int(sum(p[3] for p in parts))

    @property
    def num_matched(self) -> int:
        return int(sum(len(x) for x in self.gt))

    def stats(self) -> dict | None:
        """Box-error stats (``fit_box_error_stats``) plus ``recall`` at the IoU threshold; None if no match."""
        if not self.gt:
            return None
        gt, pred = np.concatenate(self.gt), np.concatenate(self.pred)
        ok = (gt[:, 2:] > 0).all(1) & (pred[:, 2:] > 0).all(1)
        stats = fit_box_error_stats(gt[ok], pred[ok], obj_ids=np.concatenate(self.ids)[ok])
        stats["iou_threshold"] = self.iou_threshold
        stats["recall"] = self.num_matched / max(self.num_gt, 1)
        return stats
