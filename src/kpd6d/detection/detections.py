"""What every detector returns (:class:`Detections`), the common :class:`Detector` base with its
``predict`` API, input validation and the vectorised post-processing (threshold, one per object,
max detections).

Boxes are BOP ``(x, y, w, h)`` in pixels of the image passed to ``predict``; ``obj_ids`` are the
BOP object ids (not class indices); ``scores`` are sorted in descending order.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from kpd6d.data.bop_io import DEFAULT_BOX_FIELD

__all__ = [
    "DetectionInputError",
    "Detections",
    "Detector",
    "check_images",
    "check_test_scales",
    "keep_best_per_class",
    "load_partial_weights",
    "merge_scales",
    "xywh_to_xyxy",
    "xyxy_to_xywh",
]


class DetectionInputError(ValueError):
    """Images, targets or a checkpoint that a detector cannot use; the message says what is wrong."""


@dataclass
class Detections:
    """Detections of one image: ``boxes`` (N, 4) xywh px, ``obj_ids`` (N,) long, ``scores`` (N,) float,
    sorted by descending score; all on the images' device."""

    boxes: torch.Tensor
    obj_ids: torch.Tensor
    scores: torch.Tensor

    def __len__(self) -> int:
        return int(self.scores.shape[0])

    def to(self, device: Any) -> Detections:
        return Detections(self.boxes.to(device), self.obj_ids.to(device), self.scores.to(device))

    @classmethod
    def empty(cls, device: Any = "cpu") -> Detections:
        return cls(
            torch.zeros((0, 4), dtype=torch.float32, device=device),
            torch.zeros((0,), dtype=torch.long, device=device),
            torch.zeros((0,), dtype=torch.float32, device=device),
        )

    def best_per_object(self) -> dict[int, torch.Tensor]:
        """``{obj_id: box (4,)}`` of the highest-scoring box of each object id."""
        out: dict[int, torch.Tensor] = {}
        for box, oid in zip(self.boxes, self.obj_ids.tolist()):
            out.setdefault(int(oid), box)
        return out


def xywh_to_xyxy(b: torch.Tensor) -> torch.Tensor:
    return torch.cat([b[..., :2], b[..., :2] + b[..., 2:4]], dim=-1)


def xyxy_to_xywh(b: torch.Tensor) -> torch.Tensor:
    return torch.cat([b[..., :2], b[..., 2:4] - b[..., :2]], dim=-1)


def check_images(images: Any, *, what: str = "images") -> torch.Tensor:
    """Validate a (B, 3, H, W) float batch in [0, 1] and return it; raise a clear error otherwise.

    uint8 (or other integer) images are rejected rather than silently rescaled: the contract is
    float in [0, 1], and guessing the scale hides bugs. Convert with ``images.float() / 255``.
    """
    if not isinstance(images, torch.Tensor):
        raise DetectionInputError(
            f"{what} must be a torch.Tensor (B, 3, H, W) float in [0, 1], got {type(images).__name__}"
        )
    if images.ndim != 4:
        hint = " (a single image? use images.unsqueeze(0))" if images.ndim == 3 else ""
        raise DetectionInputError(f"{what} must have shape (B, 3, H, W), got {tuple(images.shape)}{hint}")
    if images.shape[1] != 3:
        hint = " (channels-last? use images.permute(0, 3, 1, 2))" if images.shape[-1] == 3 else ""
        raise DetectionInputError(
            f"{what} must have 3 (RGB) channels in dim 1, got {images.shape[1]} "
            f"(shape {tuple(images.shape)}){hint}"
        )
    if images.shape[2] == 0 or images.shape[3] == 0:
        raise DetectionInputError(f"{what} is empty: height x width = {images.shape[2]} x {images.shape[3]}")
    if not images.is_floating_point():
        raise DetectionInputError(
            f"{what} must be float in [0, 1], got dtype {images.dtype}; "
            "convert uint8 images with images.float() / 255"
        )
    if images.numel() and images.shape[0]:
        lo, hi = float(images.amin()), float(images.amax())
        if not (lo >= -1e-3 and hi <= 1.0 + 1e-3):
            raise DetectionInputError(
                f"{what} must be float in [0, 1], got values in [{lo:.3g}, {hi:.3g}]"
                + ("; 0..255 images? divide by 255" if hi > 1.5 else "")
            )
    return images


def keep_best_per_class(labels: torch.Tensor, valid: torch.Tensor, num_classes: int) -> torch.Tensor:
    """Mask (B, K) keeping only the first valid entry of each class per row (rows sorted by score).

    Vectorised over the batch: for every (row, class) the smallest valid position wins.
    """
    B, K = labels.shape
    pos = torch.arange(K, device=labels.device).expand(B, K)
    big = torch.full((B, num_classes), K, dtype=torch.long, device=labels.device)
    cand = torch.where(valid, pos, torch.full_like(pos, K))
    first = big.scatter_reduce(1, labels.clamp(0, num_classes - 1), cand, reduce="amin")
    return valid & (first.gather(1, labels.clamp(0, num_classes - 1)) == pos)


class Detector(nn.Module):
    """Base of the detectors: validation, resizing to ``input_size`` and post-processing.

    Subclasses implement :meth:`raw_predict` (network-size images -> padded, score-sorted
    ``boxes (B, K, 4)`` xywh in network px, ``labels (B, K)`` class indices, ``scores (B, K)``,
    entries with score < 0 are padding) and, if trainable, :meth:`training_losses`.
    Class index ``i`` is object id ``obj_ids[i]``.
    """

    trainable = True
    #: whether ``predict`` can run the network at other input sizes (``test_scales``); detectors that
    #: resize inside their own model (torchvision's) or have no network (the oracle) cannot
    rescalable = True
    #: IoU above which boxes of one object found at two test scales are one detection (the higher score's)
    SCALE_NMS_IOU = 0.5

    def __init__(self, obj_ids: Sequence[int] | None, input_size: Sequence[int] | None = None,
                 score_threshold: float = 0.1, max_detections: int = 100, one_per_object: bool = False,
                 requires_obj_ids: bool = True) -> None:
        super().__init__()
        if obj_ids is None:
            if requires_obj_ids:
                raise DetectionInputError(
                    f"{type(self).__name__}: obj_ids is required (the object ids this detector's classes "
                    "stand for, e.g. obj_ids=[1, 2, 3])"
                )
            self.obj_ids: list[int] | None = None
        else:
            ids = [int(i) for i in obj_ids]
            if not ids or len(set(ids)) != len(ids) or min(ids) < 0:
                raise DetectionInputError(
                    f"{type(self).__name__}: obj_ids must be distinct non-negative ids, got {list(obj_ids)}"
                )
            self.obj_ids = ids
        if input_size is not None:
            if len(input_size) != 2 or min(int(s) for s in input_size) <= 0:
                raise DetectionInputError(f"input_size must be (width, height) > 0, got {input_size!r}")
            input_size = (int(input_size[0]), int(input_size[1]))
        self.input_size: tuple[int, int] | None = input_size
        if not 0.0 <= float(score_threshold) <= 1.0:
            raise DetectionInputError(f"score_threshold must be in [0, 1], got {score_threshold}")
        if int(max_detections) < 1:
            raise DetectionInputError(f"max_detections must be >= 1, got {max_detections}")
        self.score_threshold = float(score_threshold)
        self.max_detections = int(max_detections)
        self.one_per_object = bool(one_per_object)
        self.box_stats: dict | None = None  # validation box-error statistics, kept with the checkpoint
        # the GT box field it was trained on (kept with the checkpoint): "bbox_visib" (the visible part's box) or
        # "bbox_obj" (the whole object's box clipped to the image: an amodal detector); its AP is scored on the same
        self.box_field: str = DEFAULT_BOX_FIELD
        self.test_scales: tuple[float, ...] = (1.0,)  # network input sizes at inference, as factors of input_size
        self.register_buffer("_obj_id_table", torch.tensor(self.obj_ids or [], dtype=torch.long),
                             persistent=False)

    @property
    def num_classes(self) -> int:
        return len(self.obj_ids or [])

    # -- to implement -------------------------------------------------------------------------
    def raw_predict(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        raise NotImplementedError

    def training_losses(self, images: torch.Tensor, targets: list[dict]) -> dict[str, torch.Tensor]:
        raise NotImplementedError(f"{type(self).__name__} is not trainable")

    # -- inference ----------------------------------------------------------------------------
    def set_test_scales(self, scales: Sequence[float] | None) -> None:
        """Run the network at each of these input sizes (factors of ``input_size``, or of the image size
        when it is None) and merge what they find (:func:`merge_scales`); None or ``[1]``: one size.
        Larger scales find small objects that the training size misses (test-time augmentation)."""
        scales = check_test_scales(scales, DetectionInputError, "test_scales")
        if scales != (1.0,) and not self.rescalable:
            raise DetectionInputError(f"{type(self).__name__} cannot run at other input sizes (test_scales "
                                      f"{list(scales)}); use a CenterNet detector or test_scales [1]")
        self.test_scales = scales

    def network_images(self, images: torch.Tensor, scale: float = 1.0) -> tuple[torch.Tensor, float, float]:
        """Resize to ``input_size`` (times ``scale``); returns (images, sx, sy) with input px = network px * (sx, sy)."""
        H, W = images.shape[-2:]
        w, h = self.input_size or (W, H)
        w, h = max(1, round(w * scale)), max(1, round(h * scale))
        if (W, H) == (w, h):
            return images, 1.0, 1.0
        x = nn.functional.interpolate(images, size=(h, w), mode="bilinear", align_corners=False,
                                      antialias=True)
        return x, W / w, H / h

    @torch.no_grad()
    def predict(self, images: torch.Tensor, targets: list[dict] | None = None) -> list[Detections]:
        """Detect objects in ``images`` (B, 3, H, W) float [0, 1]; one :class:`Detections` per image."""
        images = check_images(images)
        if images.shape[0] == 0:
            return []
        was_training = self.training
        self.eval()
        outs = []
        try:
            for s in self.test_scales:
                x, sx, sy = self.network_images(images, s)
                boxes, labels, scores = self.raw_predict(x)
                outs.append((boxes * torch.tensor([sx, sy, sx, sy], dtype=boxes.dtype, device=boxes.device),
                             labels, scores))
        finally:
            self.train(was_training)
        return self.postprocess(*(outs[0] if len(outs) == 1 else merge_scales(outs, self.SCALE_NMS_IOU)))

    def postprocess(self, boxes: torch.Tensor, labels: torch.Tensor, scores: torch.Tensor) -> list[Detections]:
        """Padded (B, K, ...) score-sorted outputs -> list of :class:`Detections` (vectorised masks)."""
        valid = (scores >= self.score_threshold) & (scores > 0)  # 0: suppressed / padding entries
        if self.one_per_object and labels.shape[1]:
            valid = keep_best_per_class(labels, valid, max(self.num_classes, int(labels.max()) + 1))
        # stable order: valid entries first (already score-sorted), then cap at max_detections
        rank = torch.cumsum(valid.long(), dim=1)
        valid = valid & (rank <= self.max_detections)
        ids = self._obj_id_table[labels.clamp(min=0)] if self.num_classes else labels
        out = []
        for b in range(boxes.shape[0]):  # split only; all decisions above are batched
            m = valid[b]
            out.append(Detections(boxes[b][m].float(), ids[b][m].long(), scores[b][m].float()))
        return out

    # -- checkpoint spec ----------------------------------------------------------------------
    def spec(self) -> dict:
        """Constructor parameters to rebuild this detector (see :func:`kpd6d.detection.load_detector`)."""
        return dict(getattr(self, "_spec", {}))


def check_test_scales(value: Any, error: type[Exception] = ValueError, key: str = "test_scales") -> tuple[float, ...]:
    """None -> ``(1.0,)``; else a non-empty list of positive numbers (duplicates dropped, order kept)."""
    if value is None:
        return (1.0,)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value]
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or not value:
        raise error(f"{key} must be a non-empty list of positive numbers (input-size factors, e.g. [1, 1.5]), "
                    f"got {value!r}")
    out: list[float] = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 < float(v) < float("inf"):
            raise error(f"{key} must hold positive numbers (input-size factors, e.g. [1, 1.5]), got {v!r} in {list(value)}")
        if float(v) not in out:
            out.append(float(v))
    return tuple(out)


def merge_scales(outputs: Sequence[tuple[torch.Tensor, torch.Tensor, torch.Tensor]],
                 iou: float = 0.5) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Padded ``(boxes (B, K, 4) xywh, labels (B, K), scores (B, K))`` of one image batch found at several
    input sizes (boxes already in the same pixels) -> one padded, score-sorted triple: per image and
    class, a box that overlaps a higher-scored one by IoU > ``iou`` is dropped (padding: score -1)."""
    from torchvision.ops import batched_nms

    boxes = torch.cat([o[0] for o in outputs], 1)
    labels = torch.cat([o[1] for o in outputs], 1)
    scores = torch.cat([o[2] for o in outputs], 1)
    keep = torch.zeros_like(scores, dtype=torch.bool)
    for b in range(scores.shape[0]):  # a few hundred boxes per image
        idx = torch.nonzero(scores[b] > 0).flatten()
        kept = batched_nms(xywh_to_xyxy(boxes[b, idx].float()), scores[b, idx].float(), labels[b, idx], float(iou))
        keep[b, idx[kept]] = True
    scores, order = torch.where(keep, scores, torch.full_like(scores, -1)).sort(dim=1, descending=True)
    return boxes.gather(1, order[..., None].expand(-1, -1, 4)), labels.gather(1, order), scores


def load_partial_weights(module: nn.Module, path: str, what: str) -> None:
    """Load a local state dict, skipping entries whose shapes differ (e.g. a head for other classes)."""
    from pathlib import Path

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{what} {str(p)!r} does not exist")
    state = torch.load(p, map_location="cpu", weights_only=True)
    if isinstance(state, dict) and "state_dict" in state:
        state = state["state_dict"]
    own = module.state_dict()
    usable = {k: v for k, v in state.items() if k in own and own[k].shape == v.shape}
    if not usable:
        raise DetectionInputError(f"{what} {str(p)!r} matches none of the model's parameters")
    module.load_state_dict(usable, strict=False)
