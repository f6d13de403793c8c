"""``fcos`` and ``faster_rcnn`` from ``torchvision.models.detection``, one class per object id.

Backbones: torchvision ResNets with an FPN (``resnet18``, ``resnet34``, ``resnet50``) or any timm
model with ``features_only`` support (``timm:<name>``, e.g. ``timm:resnet18``), adapted by
:class:`TimmFPN`. Nothing is downloaded: ``weights=None, weights_backbone=None`` always;
``backbone_weights_path`` (a local state dict of the backbone network) and ``weights_path`` (a local
state dict of the whole detector, e.g. a previous export) are optional.

torchvision's class 0 is the background, so class index ``i`` (object id ``obj_ids[i]``) is
torchvision label ``i + 1``.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence

import torch
from torch import nn

from kpd6d.detection.detections import (
    DetectionInputError,
    Detector,
    load_partial_weights,
    xywh_to_xyxy,
    xyxy_to_xywh,
)

__all__ = ["TimmFPN", "TorchvisionDetector", "build_fpn_backbone"]

TORCHVISION_BACKBONES = ("resnet18", "resnet34", "resnet50", "resnet101")


class TimmFPN(nn.Module):
    """timm ``features_only`` backbone + torchvision ``FeaturePyramidNetwork``: an FPN-style
    ``OrderedDict`` of feature maps with ``out_channels`` channels each, as torchvision expects."""

    def __init__(self, name: str, out_indices: Sequence[int], out_channels: int = 256, extra_blocks=None,
                 weights_path: str | None = None, pretrained: str | None = None) -> None:
        super().__init__()
        from torchvision.ops.feature_pyramid_network import FeaturePyramidNetwork

        from kpd6d.pretrained import create_timm_model

        try:
            self.body = create_timm_model(name, pretrained=pretrained, features_only=True, out_indices=tuple(out_indices))
        except (RuntimeError, IndexError) as exc:
            raise DetectionInputError(f"cannot build timm backbone {name!r} with out_indices "
                                      f"{tuple(out_indices)}: {exc}") from exc
        if weights_path:
            load_partial_weights(self.body, weights_path, "backbone_weights_path")
        self.fpn = FeaturePyramidNetwork(self.body.feature_info.channels(), out_channels, extra_blocks=extra_blocks)
        self.out_channels = out_channels

    def forward(self, x: torch.Tensor) -> OrderedDict[str, torch.Tensor]:
        feats = self.body(x)
        return self.fpn(OrderedDict((str(i), f) for i, f in enumerate(feats)))


def build_fpn_backbone(backbone: str, levels: str, weights_path: str | None = None,
                       pretrained: str | None = None) -> nn.Module:
    """FPN backbone. ``levels='rcnn'``: strides 4..32 + max-pool P6 (Faster R-CNN's layout);
    ``levels='fcos'``: strides 8..32 + P6, P7 (FCOS's layout). ``pretrained="imagenet"``: the packaged
    ImageNet weights of a ``timm:`` backbone that has them (``timm:efficientnet_lite0``)."""
    from torchvision.ops.feature_pyramid_network import LastLevelMaxPool, LastLevelP6P7

    if levels == "rcnn":
        returned, extra = [1, 2, 3, 4], LastLevelMaxPool()
    else:
        returned, extra = [2, 3, 4], LastLevelP6P7(256, 256)
    if backbone.startswith("timm:"):
        return TimmFPN(backbone[5:], out_indices=returned, extra_blocks=extra, weights_path=weights_path,
                       pretrained=pretrained)
    if pretrained:
        raise DetectionInputError(f"backbone_pretrained={pretrained!r} needs a timm backbone with packaged weights "
                                  f"(e.g. timm:efficientnet_lite0), not {backbone!r}")
    if backbone not in TORCHVISION_BACKBONES:
        raise DetectionInputError(f"unknown backbone {backbone!r}; known: {', '.join(TORCHVISION_BACKBONES)} "
                                  "or timm:<timm model name>")
    from torchvision.models.detection.backbone_utils import resnet_fpn_backbone

    fpn = resnet_fpn_backbone(backbone_name=backbone, weights=None, trainable_layers=5, returned_layers=returned,
                              extra_blocks=extra, norm_layer=nn.BatchNorm2d)
    if weights_path:
        load_partial_weights(fpn.body, weights_path, "backbone_weights_path")
    return fpn


class TorchvisionDetector(Detector):
    """A torchvision detection model (``kind`` = ``fcos`` or ``faster_rcnn``) behind the common API."""

    rescalable = False  # torchvision's transform resizes every image to min_size / max_size itself

    def __init__(self, kind: str, obj_ids: Sequence[int] | None = None, backbone: str = "resnet18",
                 input_size: Sequence[int] | None = (320, 240), score_threshold: float = 0.1,
                 max_detections: int = 100, one_per_object: bool = False, backbone_weights_path: str | None = None,
                 weights_path: str | None = None, nms_threshold: float = 0.5, backbone_pretrained: str | None = None,
                 mean: Sequence[float] | None = None, std: Sequence[float] | None = None) -> None:
        super().__init__(obj_ids, input_size, score_threshold, max_detections, one_per_object)
        from kpd6d.pretrained import IMAGENET, resolve_normalization

        if backbone_pretrained not in (None, "imagenet"):  # a local file: the backbone weights path
            if backbone_weights_path:
                raise DetectionInputError(f"{kind}: give backbone_pretrained or backbone_weights_path, not both")
            backbone_weights_path, backbone_pretrained = backbone_pretrained, None

        w, h = self.input_size or (640, 480)
        # the normalisation the backbone's weights expect (torchvision's transform applies it)
        if mean is None and std is None and not backbone.startswith("timm:"):
            mean, std = IMAGENET
        try:
            mean, std = resolve_normalization(backbone.removeprefix("timm:"), mean, std)
        except ValueError as exc:
            raise DetectionInputError(f"{kind}: {exc}") from exc
        self.resolved_params = {"mean": mean, "std": std}
        common = dict(num_classes=self.num_classes + 1, min_size=min(w, h), max_size=max(w, h), image_mean=mean,
                      image_std=std)
        if kind == "fcos":
            from torchvision.models.detection import FCOS
            from torchvision.models.detection.anchor_utils import AnchorGenerator

            anchors = AnchorGenerator(sizes=((8,), (16,), (32,), (64,), (128,)), aspect_ratios=((1.0,),) * 5)
            self.model = FCOS(build_fpn_backbone(backbone, "fcos", backbone_weights_path, backbone_pretrained), anchor_generator=anchors,
                              score_thresh=0.05, nms_thresh=nms_threshold, detections_per_img=max(self.max_detections, 100),
                              **common)
        elif kind == "faster_rcnn":
            from torchvision.models.detection import FasterRCNN

            self.model = FasterRCNN(build_fpn_backbone(backbone, "rcnn", backbone_weights_path, backbone_pretrained),
                                    box_score_thresh=0.05, box_nms_thresh=nms_threshold,
                                    box_detections_per_img=max(self.max_detections, 100), **common)
        else:
            raise DetectionInputError(f"unknown torchvision detector kind {kind!r}; known: fcos, faster_rcnn")
        self.kind = kind
        if weights_path:
            load_partial_weights(self.model, weights_path, "weights_path")

    def raw_predict(self, images: torch.Tensor):
        outs = self.model(list(images))
        B = len(outs)
        K = max([len(o["scores"]) for o in outs] + [1])
        boxes = images.new_zeros((B, K, 4))
        labels = torch.zeros((B, K), dtype=torch.long, device=images.device)
        scores = images.new_full((B, K), -1.0)
        for b, o in enumerate(outs):  # torchvision already returns per-image lists; pad them
            n = len(o["scores"])
            order = torch.argsort(o["scores"], descending=True)
            boxes[b, :n] = xyxy_to_xywh(o["boxes"][order])
            labels[b, :n] = o["labels"][order] - 1
            scores[b, :n] = o["scores"][order]
        return boxes, labels, scores

    def training_losses(self, images: torch.Tensor, targets: list[dict]) -> dict[str, torch.Tensor]:
        tv_targets = [{"boxes": xywh_to_xyxy(torch.as_tensor(t["boxes"], dtype=torch.float32,
                                                             device=images.device).reshape(-1, 4)),
                       "labels": torch.as_tensor(t["labels"], dtype=torch.long, device=images.device) + 1}
                      for t in targets]
        was = self.model.training
        self.model.train()
        try:
            losses = self.model(list(images), tv_targets)
        finally:
            self.model.train(was)
        losses = dict(losses)
        losses["loss"] = sum(losses.values())
        return losses


