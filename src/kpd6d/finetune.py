"""Fine-tuning settings shared by the detector and KPD stages (``finetune:`` in either stage's config).

* ``backbone_lr_mult``: the backbone's learning rate is the optimiser's ``lr`` times this (pretrained
  features want smaller steps than a freshly initialised head); 1.0 = one learning rate for all.
* ``freeze_bn``: the backbone's BatchNorm layers stay in eval mode while training: they normalise
  with their (ImageNet) running statistics, which small CPU batches would otherwise overwrite with
  noisy ones; their affine parameters still learn.

Warm-up belongs to the schedules (``warmup_steps``, :mod:`kpd6d.schedules`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from torch import nn

__all__ = ["FINETUNE_DEFAULTS", "apply_freeze_bn", "finetune_config", "param_groups"]

FINETUNE_DEFAULTS: dict[str, Any] = {"backbone_lr_mult": 1.0, "freeze_bn": False}


def finetune_config(cfg: Mapping[str, Any] | None, where: str = "finetune") -> dict[str, Any]:
    """``cfg`` over :data:`FINETUNE_DEFAULTS`, checked: unknown keys and bad values name the key."""
    cfg = dict(cfg or {})
    unknown = sorted(set(cfg) - set(FINETUNE_DEFAULTS))
    if unknown:
        raise ValueError(f"{where}: unknown setting(s) {unknown}; known: {sorted(FINETUNE_DEFAULTS)}")
    out = {**FINETUNE_DEFAULTS, **{k: v for k, v in cfg.items() if v is not None}}
    try:
        out["backbone_lr_mult"] = float(out["backbone_lr_mult"])
    except (TypeError, ValueError):
        raise ValueError(f"{where}.backbone_lr_mult must be a number >= 0, got {out['backbone_lr_mult']!r}") from None
    if out["backbone_lr_mult"] < 0:
        raise ValueError(f"{where}.backbone_lr_mult must be >= 0, got {out['backbone_lr_mult']}")
    if not isinstance(out["freeze_bn"], bool):
        raise ValueError(f"{where}.freeze_bn must be true or false, got {out['freeze_bn']!r}")
    return out


def param_groups(module: nn.Module, backbone: nn.Module, lr: float, backbone_lr_mult: float) -> list[dict]:
    """Optimiser parameter groups: the backbone's trainable parameters at ``lr * backbone_lr_mult``,
    the rest at ``lr``. A multiplier of 0 leaves the backbone out (frozen weights)."""
    ids = {id(p) for p in backbone.parameters()}
    rest = [p for p in module.parameters() if p.requires_grad and id(p) not in ids]
    groups = [{"params": rest, "lr": float(lr), "name": "head"}]
    if backbone_lr_mult > 0:
        groups.append({"params": [p for p in backbone.parameters() if p.requires_grad],
                       "lr": float(lr) * backbone_lr_mult, "name": "backbone"})
    return [g for g in groups if g["params"]]


def apply_freeze_bn(backbone: nn.Module) -> None:
    """Put every BatchNorm layer of ``backbone`` in eval mode (call after ``module.train()``)."""
    for m in backbone.modules():
        if isinstance(m, nn.modules.batchnorm._BatchNorm):
            m.eval()
