"""Fine-tuning settings shared by the detector and KPD stages (``finetune:`` in either stage's config).

* ``backbone_lr_mult``: the backbone's learning rate is the optimiser's ``lr`` times this (pretrained
  features want smaller steps than a freshly initialised head); 1.0 = one learning rate for all.
* ``freeze_bn``: the backbone's BatchNorm layers stay in eval mode while training: they normalise
  with their (ImageNet) running statistics, which small CPU batches would otherwise overwrite with
  noisy ones; their affine parameters still learn.
* ``freeze_stages``: the backbone's stem and its first ``n`` feature stages (those that produce the
  stride-2, -4, -8 … features, in that order) are frozen: their weights do not learn and their
  BatchNorm layers keep their running statistics. 0 = none; ``-1`` = the whole backbone. Features
  learnt on real photographs stay as they are while the rest adapts to the renders (the finding of
  Hinterstoisser et al., "On pre-trained image features and synthetic images for deep learning",
  2018), and no gradient is computed through the frozen part, so steps are cheaper.

Warm-up belongs to the schedules (``warmup_steps``, :mod:`kpd6d.schedules`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from torch import nn

__all__ = ["FINETUNE_DEFAULTS", "apply_freeze_bn", "apply_freeze_stages", "apply_train_mode", "feature_module_names", "finetune_config",
           "frozen_stage_modules", "param_groups"]

FINETUNE_DEFAULTS: dict[str, Any] = {"backbone_lr_mult": 1.0, "freeze_bn": False, "freeze_stages": 0}


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
    n = out["freeze_stages"]
    if isinstance(n, bool) or not isinstance(n, int) or n < -1:
        raise ValueError(f"{where}.freeze_stages must be an integer >= 0 (or -1: the whole backbone), got {n!r}")
    return out


def feature_module_names(backbone: nn.Module) -> list[str]:
    """The names (within ``backbone``) of the modules that produce its features, shallowest first.

    Works for kpd6d's ``Backbone`` (a timm features model under ``.body``), a bare timm features model
    (``feature_info``, as CenterNet holds it) and ``TinyBackbone`` (``stages``)."""
    prefix, body = "", backbone
    if not hasattr(body, "feature_info") and isinstance(getattr(body, "body", None), nn.Module):
        prefix, body = "body.", body.body
    info = getattr(body, "feature_info", None)
    if info is not None and hasattr(info, "module_name"):
        return [prefix + n for n in info.module_name()]
    stages = getattr(body, "stages", None)
    if isinstance(stages, nn.ModuleList):
        return [f"{prefix}stages.{i}" for i in range(len(stages))]
    raise ValueError(f"freeze_stages: cannot tell the feature stages of a {type(backbone).__name__} "
                     "(no timm feature_info and no .stages)")


def frozen_stage_modules(backbone: nn.Module, n: int) -> list[nn.Module]:
    """The modules of ``backbone`` that come before, or belong to, its ``n``-th feature stage (in
    registration order, which is the forward order of timm's feature models): what ``freeze_stages: n``
    freezes. ``n = -1`` or ``n >=`` the number of stages: every module of the backbone."""
    if n == 0:
        return []
    mods = list(backbone.named_modules())
    if n < 0:
        return [m for _, m in mods]
    names = feature_module_names(backbone)
    if n >= len(names):
        return [m for _, m in mods]
    target = names[n - 1]
    index = {name: j for j, (name, _) in enumerate(mods)}
    if target not in index:
        raise ValueError(f"freeze_stages: feature module {target!r} not found in the backbone")
    last = max(j for name, j in index.items() if name == target or name.startswith(target + "."))
    return [m for _, m in mods[: last + 1]]


def apply_freeze_stages(backbone: nn.Module, n: int) -> int:
    """Freeze the weights of the first ``n`` feature stages (and the stem): ``requires_grad = False``.
    Returns the number of parameters frozen. Their BatchNorm layers go to eval mode with
    :func:`apply_freeze_bn` on the same modules (call after every ``module.train()``)."""
    frozen = 0
    for m in frozen_stage_modules(backbone, n):
        for p in m.parameters(recurse=False):
            if p.requires_grad:
                p.requires_grad_(False)
                frozen += p.numel()
    return frozen


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


def apply_freeze_bn(backbone: nn.Module, freeze_stages: int = -1) -> None:
    """Put the BatchNorm layers of ``backbone`` in eval mode (call after ``module.train()``): all of
    them (``freeze_stages=-1``) or those of the first ``freeze_stages`` stages."""
    for m in frozen_stage_modules(backbone, freeze_stages):
        if isinstance(m, nn.modules.batchnorm._BatchNorm):
            m.eval()


def apply_train_mode(backbone: nn.Module, cfg: Mapping[str, Any]) -> None:
    """What ``finetune`` asks of the backbone after ``module.train()``: frozen BatchNorm everywhere
    (``freeze_bn``) or in the frozen stages (``freeze_stages``)."""
    if cfg["freeze_bn"]:
        apply_freeze_bn(backbone)
    elif cfg["freeze_stages"]:
        apply_freeze_bn(backbone, cfg["freeze_stages"])
