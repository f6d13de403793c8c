"""Heatmap heads and the keypoint network (backbone + head → heatmaps at the output stride).

* ``deconv`` — SimpleBaselines: from the stride-32 feature, ``n`` × (4×4 transposed conv stride 2 +
  BN + ReLU) up to the output stride (3 deconvs for stride 4), then a 1×1 conv to the heatmaps.
* ``fpn`` — FPN-style top-down path: 1×1 laterals on the features from the output stride to 32,
  nearest-upsample-and-add, a 3×3 conv, then a 1×1 conv to the heatmaps.

:class:`KeypointNet` normalises [0, 1] images with its backbone's mean/std itself, and outputs
``num_groups × num_keypoints`` maps: one heatmap group per object when one network serves several
objects; :meth:`KeypointNet.select` picks each sample's group by its object index.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import torch
from torch import nn

from kpd6d.pretrained import IMAGENET
from kpd6d.registry import HEADS

__all__ = ["HEADS", "DeconvHead", "FPNHead", "KeypointNet"]

def _n_upsamplings(reduction: int, out_stride: int) -> int:
    n = math.log2(reduction / out_stride)
    if n < 0 or n != int(n):
        raise ValueError(
            f"head: cannot go from feature stride {reduction} to output stride {out_stride} "
            "with factor-2 upsamplings (output stride must be a power-of-2 divisor of the feature stride)"
        )
    return int(n)


@HEADS.register("deconv")
class DeconvHead(nn.Module):
    """SimpleBaselines deconvolution head on the last (stride-32) feature."""

    def __init__(self, channels: list[int], reductions: list[int], num_outputs: int, out_stride: int = 4,
                 deconv_channels: int = 256, final_kernel: int = 1) -> None:
        super().__init__()
        n = _n_upsamplings(reductions[-1], out_stride)
        layers: list[nn.Module] = []
        cin = channels[-1]
        for _ in range(n):
            layers += [nn.ConvTranspose2d(cin, deconv_channels, 4, stride=2, padding=1, bias=False),
                       nn.BatchNorm2d(deconv_channels), nn.ReLU(inplace=True)]
            cin = deconv_channels
        self.deconv = nn.Sequential(*layers)
        self.final = nn.Conv2d(cin, num_outputs, final_kernel, padding=final_kernel // 2)
        nn.init.normal_(self.final.weight, std=1e-3)
        nn.init.zeros_(self.final.bias)

    def forward(self, feats: list[torch.Tensor]) -> torch.Tensor:
        return self.final(self.deconv(feats[-1]))


@HEADS.register("fpn")
class FPNHead(nn.Module):
    """FPN-style top-down upsampling head to the output stride."""

    def __init__(self, channels: list[int], reductions: list[int], num_outputs: int, out_stride: int = 4,
                 fpn_channels: int = 128) -> None:
        super().__init__()
        if out_stride not in reductions:
            raise ValueError(f"fpn head: the backbone has no feature at output stride {out_stride} "
                             f"(its strides: {reductions})")
        self.start = reductions.index(out_stride)
        self.laterals = nn.ModuleList(nn.Conv2d(c, fpn_channels, 1) for c in channels[self.start:])
        self.smooth = nn.Sequential(nn.Conv2d(fpn_channels, fpn_channels, 3, padding=1, bias=False),
                                    nn.BatchNorm2d(fpn_channels), nn.ReLU(inplace=True))
        self.final = nn.Conv2d(fpn_channels, num_outputs, 1)
        nn.init.normal_(self.final.weight, std=1e-3)
        nn.init.zeros_(self.final.bias)

    def forward(self, feats: list[torch.Tensor]) -> torch.Tensor:
        feats = feats[self.start:]
        x = self.laterals[-1](feats[-1])
        for lat, f in zip(reversed(self.laterals[:-1]), reversed(feats[:-1])):
            x = nn.functional.interpolate(x, size=f.shape[-2:], mode="nearest") + lat(f)
        return self.final(self.smooth(x))


class KeypointNet(nn.Module):
    """Backbone + head: images (B, 3, H, W) in [0, 1] → heatmaps (B, G·K, H/s, W/s)."""

    def __init__(self, backbone: Mapping[str, Any], head: Mapping[str, Any], num_keypoints: int,
                 num_groups: int = 1, out_stride: int = 4) -> None:
        super().__init__()
        from kpd6d.registry import BACKBONES, build_from_cfg

        self.num_keypoints = int(num_keypoints)
        self.num_groups = int(num_groups)
        self.out_stride = int(out_stride)
        self.backbone = build_from_cfg(BACKBONES, backbone)
        # null entries are unset: a preset that inherits another can switch head kinds
        head = {k: v for k, v in dict(head).items() if v is not None}
        kind = head.pop("name", "deconv")
        if kind not in HEADS:
            raise ValueError(f"unknown head {kind!r}; known heads: {', '.join(HEADS.names())}")
        self.head = HEADS.get(kind)(self.backbone.channels, self.backbone.reductions,
                                self.num_groups * self.num_keypoints, out_stride=self.out_stride, **head)
        # the normalisation the backbone's weights expect (each backbone states it)
        self.register_buffer("mean", torch.tensor(getattr(self.backbone, "mean", IMAGENET[0])).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(getattr(self.backbone, "std", IMAGENET[1])).view(1, 3, 1, 1), persistent=False)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = (images - self.mean.to(images.dtype)) / self.std.to(images.dtype)
        return self.head(self.backbone(x))

    def select(self, heatmaps: torch.Tensor, group: torch.Tensor | None) -> torch.Tensor:
        """(B, G·K, h, w) → (B, K, h, w): each sample's heatmap group (``group`` (B,) object indices)."""
        if self.num_groups == 1:
            return heatmaps
        if group is None:
            raise ValueError("KeypointNet serves several objects: pass each sample's object index")
        B, _, h, w = heatmaps.shape
        hm = heatmaps.view(B, self.num_groups, self.num_keypoints, h, w)
        return hm[torch.arange(B, device=heatmaps.device), group.long()]
