"""Detector evaluation: mAP@0.5 and mAP@0.5:0.95 (torchmetrics ``MeanAveragePrecision`` with the
pycocotools backend) and the box-error statistics of IoU-matched predictions, in original image px."""

from __future__ import annotations

import torch

from kpd6d.detection.box_stats import BoxErrorCollector
from kpd6d.detection.detections import Detections

__all__ = ["DetectionEvaluator", "evaluate_detector"]


class DetectionEvaluator:
    """``update(detections, targets)`` per batch (targets as from ``DetectionDataset``: network-px
    ``boxes``, ``obj_ids`` and ``scale``), then ``compute()``. Predictions with score below
    ``stats_score_threshold`` count for mAP but not for the box-error statistics."""

    def __init__(self, stats_score_threshold: float = 0.1, box_stats_iou: float = 0.5, per_object: bool = False) -> None:
        from torchmetrics.detection import MeanAveragePrecision

        # torchmetrics' own DDP sync is off: compute() gathers the boxes itself (an empty list state on
        # one rank makes torchmetrics skip a collective the others run)
        self.map = MeanAveragePrecision(box_format="xywh", iou_type="bbox", backend="pycocotools",
                                        sync_on_compute=False)
        # per_object: AP@0.5 of each object id as well (a second, single-threshold AP with class metrics)
        self.map50 = (MeanAveragePrecision(box_format="xywh", iou_type="bbox", backend="pycocotools",
                                           iou_thresholds=[0.5], class_metrics=True, sync_on_compute=False)
                      if per_object else None)
        self._preds: list[dict] = []
        self._gts: list[dict] = []
        self.errors = BoxErrorCollector(box_stats_iou)
        self.stats_score_threshold = float(stats_score_threshold)

    def reset(self) -> None:
        self.map.reset()
        self._preds, self._gts = [], []
        if self.map50 is not None:
            self.map50.reset()
        self.errors.reset()

    def update(self, detections: list[Detections], targets: list[dict]) -> None:
        preds, gts = [], []
        for d, t in zip(detections, targets):
            scale = torch.cat([t["scale"], t["scale"]]).to(d.boxes) if "scale" in t else torch.ones(4).to(d.boxes)
            boxes = d.boxes * scale
            gt_boxes = torch.as_tensor(t["boxes"]).to(d.boxes).reshape(-1, 4) * scale
            gt_ids = torch.as_tensor(t["obj_ids"]).reshape(-1)
            preds.append({"boxes": boxes.cpu(), "scores": d.scores.cpu(), "labels": d.obj_ids.cpu()})
            gts.append({"boxes": gt_boxes.cpu(), "labels": gt_ids.cpu()})
            keep = d.scores >= self.stats_score_threshold
            self.errors.add(boxes[keep], d.obj_ids[keep], gt_boxes, gt_ids)
        self._preds += preds
        self._gts += gts

    def compute(self) -> dict:
        """``{"map_50", "map", "recall_at_iou", "num_gt", "box_stats"}`` (box_stats None without matches),
        and with ``per_object`` ``"ap50_per_object"``: {obj_id: AP@0.5} over the objects with ground truth."""
        from kpd6d.distributed import all_gather_objects

        parts = all_gather_objects((self._preds, self._gts))  # every rank's images (one process: its own)
        preds = [p for part in parts for p in part[0]]
        gts = [g for part in parts for g in part[1]]
        self.map.reset()
        self.map.update(preds, gts)
        if self.map50 is not None:
            self.map50.reset()
            self.map50.update(preds, gts)
        res = self.map.compute()
        self.errors.gather()
        stats = self.errors.stats()
        out = {"map_50": float(res["map_50"]), "map": float(res["map"]),
               "recall_at_iou": self.errors.num_matched / max(self.errors.num_gt, 1),
               "num_gt": self.errors.num_gt, "box_stats": stats}
        if self.map50 is not None:
            r50 = self.map50.compute()
            classes = r50["classes"].reshape(-1).tolist()
            values = r50["map_per_class"].reshape(-1).tolist()
            out["ap50_per_object"] = {int(c): float(v) for c, v in zip(classes, values) if v >= 0}
        return out


@torch.no_grad()
def evaluate_detector(detector, dataset, batch_size: int = 8, score_threshold: float = 0.01,
                      progress: bool = True, per_object: bool = False) -> dict:
    """Evaluate ``detector`` on a ``DetectionDataset`` (see :meth:`DetectionEvaluator.compute`)."""
    from torch.utils.data import DataLoader
    from tqdm import tqdm

    from kpd6d.detection.dataset import collate_detection

    ev = DetectionEvaluator(stats_score_threshold=detector.score_threshold, per_object=per_object)
    saved = detector.score_threshold
    detector.score_threshold = min(saved, score_threshold)
    device = next(iter(detector.parameters()), torch.zeros(0)).device
    try:
        loader = DataLoader(dataset, batch_size=batch_size, shuffle=False, collate_fn=collate_detection)
        for images, targets in tqdm(loader, desc="evaluate detector", disable=not progress):
            ev.update(detector.predict(images.to(device)), targets)
    finally:
        detector.score_threshold = saved
    return ev.compute()
