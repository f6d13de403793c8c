"""``DetectorModule``: trains any trainable ``DETECTORS`` entry with Lightning.

Training: batch augmentation (:mod:`kpd6d.detection.augment`) then the detector's own losses.
Validation: mAP@0.5 and mAP@0.5:0.95 (torchmetrics ``MeanAveragePrecision``, pycocotools backend)
and the box-error statistics of matched predictions (original image px), which are kept on the
detector (``detector.box_stats``), written to ``stats_path`` and stored in every checkpoint.
Checkpoints carry the detector record, so ``kpd6d.detection.load_detector(ckpt)`` works on them.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import pytorch_lightning as pl
import torch

from kpd6d.detection.detectors import CHECKPOINT_KEY, detector_record
from kpd6d.registry import DETECTORS, build_from_cfg

__all__ = ["DEFAULT_AUGMENT", "DEFAULT_OPTIMIZER", "DetectorModule"]

#: The paper's YOLO recipe: SGD, lr 1e-3 divided by 10 every 100 epochs.
DEFAULT_OPTIMIZER = {"name": "sgd", "lr": 1e-3, "momentum": 0.9, "weight_decay": 5e-4,
                     "schedule": "step", "step_epochs": 100, "gamma": 0.1, "warmup_steps": 0,
                     "minutes": 0.0}
#: HSV changes up to 1.5x, random scale ±20%.
DEFAULT_AUGMENT = {"enabled": True, "hsv": 1.5, "hue": 0.0, "scale": 0.2, "translate": 0.0}


class DetectorModule(pl.LightningModule):
    def __init__(self, detector: Mapping[str, Any], optimizer: Mapping[str, Any] | None = None,
                 augment: Mapping[str, Any] | None = None, eval_score_threshold: float = 0.01,
                 box_stats_iou: float = 0.5, stats_path: str | None = None, seed: int = 0,
                 channels_last: bool = True, finetune: Mapping[str, Any] | None = None) -> None:
        super().__init__()
        self.save_hyperparameters()
        from kpd6d.finetune import finetune_config

        self.finetune = finetune_config(finetune, "stage.finetune")
        self.detector = build_from_cfg(DETECTORS, dict(detector))
        if not self.detector.trainable:
            raise ValueError(f"detector {detector.get('name')!r} is not trainable; known trainable detectors: "
                             + ", ".join(n for n in DETECTORS.names() if n != "oracle"))
        unknown = set(optimizer or {}) - set(DEFAULT_OPTIMIZER)
        if unknown:
            raise ValueError(f"unknown optimizer setting(s) {sorted(unknown)}; known: {sorted(DEFAULT_OPTIMIZER)}")
        unknown = set(augment or {}) - set(DEFAULT_AUGMENT)
        if unknown:
            raise ValueError(f"unknown augment setting(s) {sorted(unknown)}; known: {sorted(DEFAULT_AUGMENT)}")
        self.opt_cfg = {**DEFAULT_OPTIMIZER, **(optimizer or {})}
        self.aug_cfg = {**DEFAULT_AUGMENT, **(augment or {})}
        self.eval_score_threshold = float(eval_score_threshold)
        self.stats_path = stats_path
        self._gen = torch.Generator().manual_seed(int(seed))
        self.box_stats_iou = float(box_stats_iou)
        self.channels_last = bool(channels_last)
        if self.channels_last:  # NHWC convolutions: markedly faster on CPU (oneDNN), neutral elsewhere
            self.detector.to(memory_format=torch.channels_last)
        if (self.finetune["backbone_lr_mult"] != 1.0 or self.finetune["freeze_bn"]) and self._backbone() is None:
            raise ValueError(f"stage.finetune: detector {detector.get('name')!r} exposes no .backbone module, so "
                             "backbone_lr_mult / freeze_bn cannot apply to it")

    def _backbone(self):
        bb = getattr(self.detector, "backbone", None)
        return bb if isinstance(bb, torch.nn.Module) else None

    def train(self, mode: bool = True):
        super().train(mode)
        if mode and self.finetune["freeze_bn"]:
            from kpd6d.finetune import apply_freeze_bn

            apply_freeze_bn(self._backbone())  # keep the pretrained BatchNorm statistics
        return self

    # -- training -----------------------------------------------------------------------------
    def training_step(self, batch, batch_idx):
        images, targets = batch
        if self.aug_cfg["enabled"]:
            from kpd6d.detection.augment import augment_batch

            a = self.aug_cfg
            images, targets = augment_batch(images, targets, self._gen, a["hsv"], a["hue"], a["scale"], a["translate"])
        if self.channels_last:
            images = images.contiguous(memory_format=torch.channels_last)
        losses = self.detector.training_losses(images, targets)
        B = images.shape[0]
        for k, v in losses.items():
            self.log(f"train/{k}", v.detach(), prog_bar=(k == "loss"), on_step=True, on_epoch=True, batch_size=B)
        return losses["loss"]

    # -- validation ---------------------------------------------------------------------------
    def on_validation_epoch_start(self) -> None:
        from kpd6d.detection.metrics import DetectionEvaluator

        self._evaluator = DetectionEvaluator(self.detector.score_threshold, self.box_stats_iou)

    def validation_step(self, batch, batch_idx):
        images, targets = batch
        saved = self.detector.score_threshold
        self.detector.score_threshold = min(saved, self.eval_score_threshold)
        try:
            dets = self.detector.predict(images)
        finally:
            self.detector.score_threshold = saved
        self._evaluator.update(dets, targets)

    def on_validation_epoch_end(self) -> None:
        res = self._evaluator.compute()
        self.log("val/map_50", res["map_50"], prog_bar=True, batch_size=1)
        self.log("val/map", res["map"], prog_bar=True, batch_size=1)
        self.log("val/recall_at_iou", res["recall_at_iou"], batch_size=1)
        stats = res["box_stats"]
        if stats is not None and not self.trainer.sanity_checking:
            self.detector.box_stats = stats
            if self.stats_path:
                from kpd6d.box_errors import save_box_error_stats

                save_box_error_stats(self.stats_path, stats)
        self.last_metrics = {k: v for k, v in res.items() if k != "box_stats"}

    # -- optimisation -------------------------------------------------------------------------
    def configure_optimizers(self):
        c = self.opt_cfg
        params = [p for p in self.parameters() if p.requires_grad]
        if self._backbone() is not None and self.finetune["backbone_lr_mult"] != 1.0:
            from kpd6d.finetune import param_groups

            params = param_groups(self, self._backbone(), c["lr"], self.finetune["backbone_lr_mult"])
        if c["name"] == "sgd":
            opt = torch.optim.SGD(params, lr=c["lr"], momentum=c["momentum"], weight_decay=c["weight_decay"])
        elif c["name"] in ("adam", "adamw"):
            cls = torch.optim.AdamW if c["name"] == "adamw" else torch.optim.Adam
            opt = cls(params, lr=c["lr"], weight_decay=c["weight_decay"])
        else:
            raise ValueError(f"unknown optimizer {c['name']!r}; known: sgd, adam, adamw")
        warm = int(c["warmup_steps"])
        if c["schedule"] == "step":  # the paper's: lr / 10 every step_epochs epochs (no warm-up)
            sched = torch.optim.lr_scheduler.StepLR(opt, int(c["step_epochs"]), c["gamma"])
            return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch"}}
        if c["schedule"] in ("cosine", "cosine_time"):
            from kpd6d.schedules import WarmupCosine

            if c["schedule"] == "cosine":
                est = self.trainer.estimated_stepping_batches
                factor = WarmupCosine(warm, 0.02, total_steps=max(int(est), 1) if est != float("inf") else 100_000)
            else:  # cosine over a wall-clock budget (CPU runs capped by max_time)
                if float(c["minutes"]) <= 0:
                    raise ValueError("schedule cosine_time needs optimizer.minutes > 0 (the training time budget)")
                factor = WarmupCosine(warm, 0.02, budget_s=float(c["minutes"]) * 60.0)
        elif c["schedule"] == "constant":
            def factor(it: int) -> float:
                return min(1.0, (it + 1) / warm) if warm else 1.0
        else:
            raise ValueError(f"unknown schedule {c['schedule']!r}; known: step, cosine, cosine_time, constant")
        sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    # -- checkpoints --------------------------------------------------------------------------
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint[CHECKPOINT_KEY] = detector_record(self.detector)
        checkpoint["state_dict_prefix"] = "detector."

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        rec = checkpoint.get(CHECKPOINT_KEY) or {}
        self.detector.box_stats = rec.get("box_stats")
