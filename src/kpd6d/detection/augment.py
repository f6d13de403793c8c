"""Batch augmentation for detector training, on the device (the paper's YOLO recipe by default):
HSV changes (saturation and value scaled by factors up to ``hsv``x either way, optional hue shift)
and a random scale (±``scale``) and shift (±``translate`` of the image size) about the image centre,
with the boxes transformed by the same affine and clipped to the image."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["adjust_hsv", "augment_batch", "hsv_jitter", "random_scale_shift"]


def adjust_hsv(images: torch.Tensor, saturation: torch.Tensor, value: torch.Tensor, hue_shift: torch.Tensor) -> torch.Tensor:
    """Per image (B,) factors: saturation x ``saturation``, value x ``value`` (both clipped to [0, 1])
    and hue + ``hue_shift`` turns (kornia's HSV)."""
    import kornia

    x = kornia.color.rgb_to_hsv(images.clamp(0, 1))
    h = torch.remainder(x[:, 0] + hue_shift.to(images)[:, None, None] * 2 * math.pi, 2 * math.pi)
    s = (x[:, 1] * saturation.to(images)[:, None, None]).clamp(0, 1)
    v = (x[:, 2] * value.to(images)[:, None, None]).clamp(0, 1)
    return kornia.color.hsv_to_rgb(torch.stack([h, s, v], dim=1)).clamp(0, 1)


def hsv_jitter(images: torch.Tensor, generator: torch.Generator, hsv: float = 1.5, hue: float = 0.0) -> torch.Tensor:
    """Scale saturation and value by log-uniform factors in [1/hsv, hsv]; shift hue by U(-hue, hue) turns."""
    if hsv <= 1.0 and hue <= 0:
        return images
    B = images.shape[0]
    lim = math.log(max(hsv, 1.0))
    f = torch.exp((torch.rand((B, 2), generator=generator) * 2 - 1) * lim)
    dh = (torch.rand((B,), generator=generator) * 2 - 1) * hue
    return adjust_hsv(images, f[:, 0], f[:, 1], dh)


def random_scale_shift(images: torch.Tensor, targets: list[dict], generator: torch.Generator, scale: float = 0.2,
                       translate: float = 0.0, min_size: float = 2.0, min_kept: float = 0.3):
    """Zoom each image by U(1-scale, 1+scale) about its centre and shift it by U(-translate, translate)
    of its size (black borders). A point p (pixel centres at integers) moves to
    ``s (p - c) + c + t`` with ``c = ((W-1)/2, (H-1)/2)``. Boxes follow, are clipped to the image and
    dropped when under ``min_size`` px or under ``min_kept`` of their transformed area."""
    B, _, H, W = images.shape
    if scale <= 0 and translate <= 0:
        return images, targets
    s = 1 + (torch.rand(B, generator=generator) * 2 - 1) * scale
    t = (torch.rand((B, 2), generator=generator) * 2 - 1) * translate * torch.tensor([W, H])
    # output q samples input p = (q - c - t) / s + c; in align_corners=True normalised coordinates
    # (x_n = 2u / (W-1) - 1, c -> 0) that is p_n = q_n / s - t_n / s.
    tn = t / torch.tensor([(W - 1) / 2, (H - 1) / 2])
    theta = torch.zeros((B, 2, 3))
    theta[:, 0, 0] = 1 / s
    theta[:, 1, 1] = 1 / s
    theta[:, :, 2] = -tn / s[:, None]
    theta = theta.to(images)
    grid = F.affine_grid(theta, list(images.shape), align_corners=True)
    out = F.grid_sample(images, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    c = torch.tensor([(W - 1) / 2, (H - 1) / 2])
    new_targets = []
    for b, tg in enumerate(targets):  # a handful of boxes per image
        boxes = torch.as_tensor(tg["boxes"], dtype=torch.float32).reshape(-1, 4).cpu()
        lo = s[b] * (boxes[:, :2] - c) + c + t[b]
        wh = boxes[:, 2:] * s[b]
        hi = lo + wh
        lo_c = torch.maximum(lo, torch.zeros(2))
        hi_c = torch.minimum(hi, torch.tensor([float(W), float(H)]))
        wh_c = (hi_c - lo_c).clamp(min=0)
        area, area_c = wh.prod(1), wh_c.prod(1)
        keep = (wh_c >= min_size).all(1) & (area_c >= min_kept * area.clamp(min=1e-6))
        nt = dict(tg)
        nt["boxes"] = torch.cat([lo_c, wh_c], 1)[keep].to(torch.as_tensor(tg["boxes"]).device)
        for key in ("labels", "obj_ids"):
            if key in tg:
                nt[key] = torch.as_tensor(tg[key])[keep.to(torch.as_tensor(tg[key]).device)]
        nt.pop("orig_boxes", None)  # no longer corresponds
        new_targets.append(nt)
    return out, new_targets


def augment_batch(images: torch.Tensor, targets: list[dict], generator: torch.Generator, hsv: float = 1.5,
                  hue: float = 0.0, scale: float = 0.2, translate: float = 0.0, photometric: dict | None = None):
    """HSV jitter, then (``photometric``: :func:`kpd6d.photo_augment.check_photometric`'s dict; None:
    none) the camera-response, blur and noise changes, then the random scale / shift."""
    images = hsv_jitter(images, generator, hsv, hue)
    if photometric is not None:
        from kpd6d.photo_augment import photometric_batch

        images = photometric_batch(images, photometric, generator)
    return random_scale_shift(images, targets, generator, scale, translate)
