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

from kpd6d.data.bop_io import DEFAULT_BOX_FIELD
from kpd6d.detection.detectors import CHECKPOINT_KEY, detector_record
from kpd6d.registry import DETECTORS, build_from_cfg

__all__ = ["DEFAULT_AUGMENT", "DEFAULT_OPTIMIZER", "DEFAULT_SCHEDULER", "DetectorModule", "legacy_optimization"]

#: The paper's YOLO recipe (conf/detector_recipe/paper.yaml): SGD, lr 1e-3 divided by 10 every 100 epochs.
DEFAULT_OPTIMIZER = {"name": "sgd", "lr": 1e-3, "momentum": 0.9, "weight_decay": 5e-4}
DEFAULT_SCHEDULER = {"name": "step", "step_size": 100, "gamma": 0.1}
#: HSV changes up to 1.5x, random scale ±20%.
DEFAULT_AUGMENT = {"enabled": True, "hsv": 1.5, "hue": 0.0, "scale": 0.2, "translate": 0.0,
                   "photometric": None}  # kpd6d.photo_augment settings (camera response, blur, noise); None: off

#: the flat optimiser dictionary of earlier versions (optimiser and schedule in one node)
_LEGACY_OPTIMIZER = {"name": "sgd", "lr": 1e-3, "momentum": 0.9, "weight_decay": 5e-4, "schedule": "step",
                     "step_epochs": 100, "gamma": 0.1, "warmup_steps": 0, "minutes": 0.0}
_LEGACY_ONLY = {"schedule", "step_epochs", "gamma", "warmup_steps", "minutes"}


def legacy_optimization(optimizer: Mapping[str, Any]) -> tuple[dict, dict]:
    """An earlier version's flat ``{name, lr, momentum, weight_decay, schedule, step_epochs, gamma,
    warmup_steps, minutes}`` as the (``optimizer``, ``scheduler``) pair of :mod:`kpd6d.training`
    that trains the same (defaults as they were: the paper's recipe)."""
    unknown = set(optimizer) - set(_LEGACY_OPTIMIZER)
    if unknown:
        raise ValueError(f"unknown optimizer setting(s) {sorted(unknown)}; known: {sorted(_LEGACY_OPTIMIZER)}")
    c = {**_LEGACY_OPTIMIZER, **optimizer}
    opt = {"name": c["name"], "lr": c["lr"], "weight_decay": c["weight_decay"]}
    if c["name"] == "sgd":
        opt["momentum"] = c["momentum"]
    warm, schedule = int(c["warmup_steps"]), c["schedule"]
    if schedule == "step":  # no warm-up
        sched = {"name": "step", "step_size": int(c["step_epochs"]), "gamma": c["gamma"]}
    elif schedule == "cosine":
        sched = {"name": "cosine_steps", "warmup_steps": warm, "min_factor": 0.02}
    elif schedule == "cosine_time":
        if float(c["minutes"]) <= 0:
            raise ValueError("schedule cosine_time needs optimizer.minutes > 0 (the training time budget)")
        sched = {"name": "cosine_time", "warmup_steps": warm, "min_factor": 0.02, "budget_s": float(c["minutes"]) * 60.0}
    elif schedule == "constant":
        sched = {"name": "constant", "warmup_steps": warm}
    else:
        raise ValueError(f"unknown schedule {schedule!r}; known: step, cosine, cosine_time, constant")
    return opt, sched


class DetectorModule(pl.LightningModule):
    """``optimizer`` / ``scheduler``: :mod:`kpd6d.training`'s schema (defaults: the paper's recipe,
    :data:`DEFAULT_OPTIMIZER`, :data:`DEFAULT_SCHEDULER`; ``scheduler`` null with an ``optimizer``
    given: constant learning rate). An earlier version's flat optimiser dictionary (with
    ``schedule``, ``step_epochs``, ...) is still understood (:func:`legacy_optimization`)."""

    def __init__(self, detector: Mapping[str, Any], optimizer: Mapping[str, Any] | None = None,
                 scheduler: Mapping[str, Any] | None = None, augment: Mapping[str, Any] | None = None,
                 eval_score_threshold: float = 0.01,
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
        from kpd6d.training import check_optimizer

        optimizer = dict(optimizer) if optimizer is not None else None
        if optimizer is None:
            optimizer, scheduler = dict(DEFAULT_OPTIMIZER), dict(scheduler or DEFAULT_SCHEDULER)
        elif _LEGACY_ONLY & set(optimizer):
            if scheduler is not None:
                raise ValueError("DetectorModule: give the schedule either in scheduler or (the earlier flat form) "
                                 "in optimizer.schedule, not both")
            optimizer, scheduler = legacy_optimization(optimizer)
        self.opt_cfg = check_optimizer(optimizer)
        self.sched_cfg = dict(scheduler) if scheduler else None
        unknown = set(augment or {}) - set(DEFAULT_AUGMENT)
        if unknown:
            raise ValueError(f"unknown augment setting(s) {sorted(unknown)}; known: {sorted(DEFAULT_AUGMENT)}")
        self.aug_cfg = {**DEFAULT_AUGMENT, **(augment or {})}
        if self.aug_cfg["photometric"] is not None:
            from kpd6d.photo_augment import check_photometric

            self.aug_cfg["photometric"] = check_photometric(self.aug_cfg["photometric"], "augment.photometric")
        self.eval_score_threshold = float(eval_score_threshold)
        self.stats_path = stats_path
        self._seed = int(seed)
        self._gen = torch.Generator().manual_seed(self._seed)
        self.box_stats_iou = float(box_stats_iou)
        self.channels_last = bool(channels_last)
        if self.channels_last:  # NHWC convolutions: markedly faster on CPU (oneDNN), neutral elsewhere
            self.detector.to(memory_format=torch.channels_last)
        ft = self.finetune
        if (ft["backbone_lr_mult"] != 1.0 or ft["freeze_bn"] or ft["freeze_stages"]) and self._backbone() is None:
            raise ValueError(f"stage.finetune: detector {detector.get('name')!r} exposes no .backbone module, so "
                             "backbone_lr_mult / freeze_bn / freeze_stages cannot apply to it")
        if ft["freeze_stages"]:
            from kpd6d.finetune import apply_freeze_stages

            apply_freeze_stages(self._backbone(), ft["freeze_stages"])

    def _backbone(self):
        bb = getattr(self.detector, "backbone", None)
        return bb if isinstance(bb, torch.nn.Module) else None

    def train(self, mode: bool = True):
        super().train(mode)
        if mode and self._backbone() is not None:
            from kpd6d.finetune import apply_train_mode

            apply_train_mode(self._backbone(), self.finetune)  # keep the pretrained BatchNorm statistics
        return self

    def on_train_epoch_start(self) -> None:
        self.train()  # Lightning leaves the modules' modes as they are: finetune's frozen BatchNorm is applied here

    # -- training -----------------------------------------------------------------------------
    def on_fit_start(self) -> None:
        # under DDP each rank draws its own augmentations (rank 0, and a single process, keep ``seed``)
        self._gen.manual_seed(self._seed + int(self.global_rank))

    def training_step(self, batch, batch_idx):
        images, targets = batch
        if self.aug_cfg["enabled"]:
            from kpd6d.detection.augment import augment_batch

            a = self.aug_cfg
            images, targets = augment_batch(images, targets, self._gen, a["hsv"], a["hue"], a["scale"], a["translate"],
                                            a["photometric"])
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
            if self.stats_path and self.trainer.is_global_zero:  # one writer under DDP
                from kpd6d.box_errors import save_box_error_stats

                save_box_error_stats(self.stats_path, stats)
        self.last_metrics = {k: v for k, v in res.items() if k != "box_stats"}

    # -- optimisation -------------------------------------------------------------------------
    def configure_optimizers(self):
        from kpd6d.training import configure_optimization

        params = [p for p in self.parameters() if p.requires_grad]
        if self._backbone() is not None and self.finetune["backbone_lr_mult"] != 1.0:
            from kpd6d.finetune import param_groups

            lr = self.opt_cfg.get("lr", 1e-3)
            params = param_groups(self, self._backbone(), lr, self.finetune["backbone_lr_mult"])
        return configure_optimization(params, self.opt_cfg, self.sched_cfg,
                                      total_steps=lambda: self.trainer.estimated_stepping_batches)

    # -- checkpoints --------------------------------------------------------------------------
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint[CHECKPOINT_KEY] = detector_record(self.detector)
        checkpoint["state_dict_prefix"] = "detector."

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        rec = checkpoint.get(CHECKPOINT_KEY) or {}
        self.detector.box_stats = rec.get("box_stats")
        self.detector.box_field = rec.get("box") or DEFAULT_BOX_FIELD
