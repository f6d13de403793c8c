"""The ``oracle`` detector: ground-truth boxes read from ``targets`` (optionally jittered, seeded).

For ablations that isolate the KPD from the detector, and for evaluation with known boxes.
``targets[b]`` is a dict with ``boxes`` (n, 4) xywh px in the image's pixel frame and ``obj_ids``
(n,); optional ``scores`` (n,) (default 1). The jitter scales the box size by
``exp(N(0, scale_sigma))`` and shifts the centre by ``N(0, shift_sigma) * (w, h)``, independently
per coordinate, from a generator seeded with ``seed`` (the same call sequence gives the same boxes).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from kpd6d.detection.detections import DetectionInputError, Detections, Detector

__all__ = ["OracleDetector"]


class OracleDetector(Detector):
    trainable = False
    rescalable = False

    def __init__(self, obj_ids: Sequence[int] | None = None, scale_sigma: float = 0.0, shift_sigma: float = 0.0,
                 seed: int = 0, score_threshold: float = 0.0, max_detections: int = 100,
                 one_per_object: bool = False) -> None:
        super().__init__(obj_ids, None, score_threshold, max_detections, one_per_object, requires_obj_ids=False)
        if scale_sigma < 0 or shift_sigma < 0:
            raise DetectionInputError(f"oracle: jitter sigmas must be >= 0, got scale_sigma={scale_sigma}, "
                                      f"shift_sigma={shift_sigma}")
        self.scale_sigma, self.shift_sigma, self.seed = float(scale_sigma), float(shift_sigma), int(seed)
        self.generator = torch.Generator().manual_seed(self.seed)

    def reset_seed(self, seed: int | None = None) -> None:
        """Restart the jitter sequence (from ``seed`` or the configured one)."""
        self.generator.manual_seed(self.seed if seed is None else int(seed))

    def jitter(self, boxes: torch.Tensor) -> torch.Tensor:
        """Jittered copies of xywh ``boxes`` (n, 4) (float64 noise from the seeded CPU generator)."""
        if boxes.shape[0] == 0 or (self.scale_sigma == 0 and self.shift_sigma == 0):
            return boxes
        n = boxes.shape[0]
        noise = torch.randn((n, 4), generator=self.generator, dtype=torch.float64).to(boxes.device)
        b = boxes.double()
        wh = b[:, 2:]
        ctr = b[:, :2] + wh / 2 + noise[:, :2] * self.shift_sigma * wh
        wh = wh * torch.exp(noise[:, 2:] * self.scale_sigma)
        return torch.cat([ctr - wh / 2, wh], dim=1).to(boxes.dtype)

    @torch.no_grad()
    def predict(self, images: torch.Tensor | None, targets: list[dict] | None = None) -> list[Detections]:
        if targets is None:
            raise DetectionInputError("oracle detector needs targets: a list (one per image) of dicts with "
                                      "'boxes' (n, 4) xywh and 'obj_ids' (n,)")
        device = "cpu"
        if images is not None:
            from kpd6d.detection.detections import check_images

            images = check_images(images)
            device = images.device
            if len(targets) != images.shape[0]:
                raise DetectionInputError(f"oracle: got {len(targets)} targets for {images.shape[0]} images")
        out = []
        for i, t in enumerate(targets):
            if not isinstance(t, dict) or "boxes" not in t or "obj_ids" not in t:
                raise DetectionInputError(f"oracle: targets[{i}] must be a dict with 'boxes' and 'obj_ids', "
                                          f"got {type(t).__name__} {list(t) if isinstance(t, dict) else ''}")
            boxes = torch.as_tensor(t["boxes"], dtype=torch.float32, device=device).reshape(-1, 4)
            ids = torch.as_tensor(t["obj_ids"], dtype=torch.long, device=device).reshape(-1)
            if ids.shape[0] != boxes.shape[0]:
                raise DetectionInputError(f"oracle: targets[{i}] has {boxes.shape[0]} boxes but "
                                          f"{ids.shape[0]} obj_ids")
            scores = (torch.as_tensor(t["scores"], dtype=torch.float32, device=device).reshape(-1)
                      if "scores" in t else torch.ones(ids.shape[0], device=device))
            if self.obj_ids is not None:
                keep = torch.isin(ids, torch.tensor(self.obj_ids, device=device))
                boxes, ids, scores = boxes[keep], ids[keep], scores[keep]
            order = torch.argsort(scores, descending=True, stable=True)
            boxes, ids, scores = self.jitter(boxes[order]), ids[order], scores[order]
            keep = scores >= self.score_threshold
            if self.one_per_object:
                first = torch.zeros_like(keep)
                seen: set[int] = set()
                for j, oid in enumerate(ids.tolist()):  # n is the number of GT objects: tiny
                    if keep[j] and oid not in seen:
                        seen.add(oid)
                        first[j] = True
                keep = first
            keep &= torch.cumsum(keep.long(), 0) <= self.max_detections
            out.append(Detections(boxes[keep], ids[keep], scores[keep]))
        return out
