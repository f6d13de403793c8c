"""Batch augmentation on the GPU (or CPU) with kornia.augmentation; keypoints follow any geometric transform.

:class:`BatchAugment` applies, in order:

1. geometric (optional): a small random affine (rotation / scale / translation) with
   ``kornia.augmentation.RandomAffine(align_corners=True)``; the keypoints (crop px, pixel centres at
   integer coordinates) are moved with the very same 3×3 matrix (``transform_matrix``);
2. colour: hue and saturation (``ColorJiggle``) and exposure (brightness factor in
   ``[1/exposure, exposure]``, the paper's ×1.5);
3. Gaussian blur, Gaussian noise, random erasing (occlusion);
4. optionally (``paste_p``, off by default), right after the geometric step: occluders cut from the other
   crops of the batch (:func:`paste_occluders`): a random ellipse around another crop's centre, where its
   object is, pasted over this crop's object off-centre, so that a rendered object's surface (not a
   flat rectangle) hides part of the object; the keypoint targets stay (the KPD predicts hidden keypoints);
5. optionally, the changes of :func:`kpd6d.photo_augment.photometric_batch` (the camera response:
   ``contrast``, ``gamma``, ``channel_gain``; amplitude mixing: ``amplitude_p``, ``amplitude_mix``;
   off by default), before the colour step.

Heatmap targets must be made *after* this step from the returned keypoints.
"""

from __future__ import annotations

import torch
from torch import nn

from kpd6d.geometry import affine_apply
from kpd6d.photo_augment import check_photometric, photometric_batch

__all__ = ["BatchAugment", "paste_occluders"]


class BatchAugment(nn.Module):
    def __init__(self, hue: float = 0.05, saturation: float = 1.5, exposure: float = 1.5, color_p: float = 1.0,
                 blur_p: float = 0.2, blur_sigma: tuple[float, float] = (0.1, 1.5), noise_p: float = 0.2,
                 noise_std: float = 0.02, erase_p: float = 0.3, erase_scale: tuple[float, float] = (0.02, 0.15),
                 rotation_deg: float = 0.0, scale: tuple[float, float] | None = None,
                 translate: float = 0.0, geometric_p: float = 0.5, contrast: float = 1.0, gamma: float = 1.0,
                 channel_gain: float = 0.0, amplitude_p: float = 0.0, amplitude_mix: float = 1.0,
                 paste_p: float = 0.0, paste_size: tuple[float, float] = (0.15, 0.35),
                 paste_offset: tuple[float, float] = (0.2, 0.5)) -> None:
        super().__init__()
        import kornia.augmentation as KA

        self.camera = check_photometric({"contrast": contrast, "gamma": gamma, "channel_gain": channel_gain,
                                         "amplitude_p": amplitude_p, "amplitude_mix": amplitude_mix})

        self.paste_p = float(paste_p)
        self.paste_size = _fraction_range(paste_size, "paste_size")
        self.paste_offset = _fraction_range(paste_offset, "paste_offset")
        if not 0.0 <= self.paste_p <= 1.0:
            raise ValueError(f"augment.paste_p is a probability in [0, 1], got {paste_p!r}")
        if exposure < 1 or saturation < 1:
            raise ValueError(f"augment: exposure and saturation are factors >= 1, got {exposure}, {saturation}")
        self.exposure = float(exposure)
        self.color_p = float(color_p)
        geometric = rotation_deg > 0 or translate > 0 or (scale is not None and tuple(scale) != (1.0, 1.0))
        self.geometric = (
            KA.RandomAffine(degrees=float(rotation_deg), translate=(float(translate), float(translate)) if translate else None,
                            scale=tuple(scale) if scale is not None else None, align_corners=True, p=geometric_p)
            if geometric else None
        )
        self.color = KA.ColorJiggle(saturation=(1 / saturation, saturation), hue=(-hue, hue), p=color_p) \
            if (hue > 0 or saturation > 1) and color_p > 0 else None
        self.blur = KA.RandomGaussianBlur((5, 5), tuple(blur_sigma), p=blur_p) if blur_p > 0 else None
        self.noise = KA.RandomGaussianNoise(std=noise_std, p=noise_p) if noise_p > 0 and noise_std > 0 else None
        self.erase = KA.RandomErasing(scale=tuple(erase_scale), p=erase_p) if erase_p > 0 else None

    @torch.no_grad()
    def forward(self, images: torch.Tensor, keypoints: torch.Tensor | None = None):
        """images (B, 3, H, W) in [0, 1], keypoints (B, K, 2) crop px → (images, keypoints, M (B, 3, 3))."""
        B = images.shape[0]
        M = torch.eye(3, dtype=images.dtype, device=images.device).expand(B, 3, 3).clone()
        x = images
        if self.geometric is not None:
            x = self.geometric(x)
            M = self.geometric.transform_matrix.to(x.dtype)
            if keypoints is not None:
                keypoints = affine_apply(M[:, :2, :].to(keypoints.dtype), keypoints)
        if self.paste_p > 0:
            x = paste_occluders(x, self.paste_p, self.paste_size, self.paste_offset)
        x = photometric_batch(x, self.camera)  # the images themselves while every setting is off
        if self.color is not None:
            x = self.color(x)
        if self.exposure > 1 and self.color_p > 0:
            lo, hi = torch.log(torch.tensor(1 / self.exposure)), torch.log(torch.tensor(self.exposure))
            f = torch.exp(torch.empty(B, 1, 1, 1, device=x.device).uniform_(float(lo), float(hi)))
            apply = (torch.rand(B, 1, 1, 1, device=x.device) < self.color_p).to(x.dtype)
            x = x * (1 + apply * (f.to(x.dtype) - 1))
        for aug in (self.blur, self.noise, self.erase):
            if aug is not None:
                x = aug(x)
        return x.clamp(0.0, 1.0), keypoints, M


def _fraction_range(v, name: str) -> tuple[float, float]:
    try:
        lo, hi = (float(a) for a in v)
    except (TypeError, ValueError):
        raise ValueError(f"augment.{name} must be [lo, hi] fractions of the crop side, got {v!r}") from None
    if not 0.0 <= lo <= hi <= 1.0:
        raise ValueError(f"augment.{name} must be [lo, hi] with 0 <= lo <= hi <= 1 (fractions of the crop side), got {[lo, hi]}")
    return lo, hi


def paste_occluders(images: torch.Tensor, p: float, size: tuple[float, float] = (0.15, 0.35),
                    offset: tuple[float, float] = (0.2, 0.5), generator: torch.Generator | None = None) -> torch.Tensor:
    """Each crop of ``images`` (B, 3, S, S), with probability ``p``, gets an occluder cut from another crop
    of the batch (the batch shifted cyclically by a random step, so never the crop itself): an ellipse with semi-axes ``size`` x S
    (each drawn in that range) and a random orientation, cut around the other crop's centre (where its
    object is) and pasted, by a pure translation, at ``offset`` x S (drawn in that range, random
    direction) from this crop's centre, so it covers part of this crop's object. Hard edges, as an
    occluder in front has. Returns a new tensor; batches of one crop are returned unchanged."""
    B, _, H, W = images.shape
    if B < 2 or p <= 0:
        return images
    dev = images.device

    def rand(*shape):
        return torch.rand(*shape, generator=generator).to(dev)

    other = (torch.arange(B) + torch.randint(1, B, (1,), generator=generator)) % B  # no crop pastes onto itself
    S = float(min(H, W))
    a = (size[0] + rand(B) * (size[1] - size[0])) * S
    b = (size[0] + rand(B) * (size[1] - size[0])) * S
    phi = rand(B) * torch.pi
    r = (offset[0] + rand(B) * (offset[1] - offset[0])) * S
    psi = rand(B) * 2 * torch.pi
    cy, cx = (H - 1) / 2, (W - 1) / 2
    dy, dx = torch.round(r * torch.sin(psi)), torch.round(r * torch.cos(psi))  # paste centre - crop centre
    ys = torch.arange(H, device=dev, dtype=torch.float32).view(1, H, 1)
    xs = torch.arange(W, device=dev, dtype=torch.float32).view(1, 1, W)
    u, v = xs - (cx + dx).view(B, 1, 1), ys - (cy + dy).view(B, 1, 1)
    c, s_ = torch.cos(phi).view(B, 1, 1), torch.sin(phi).view(B, 1, 1)
    inside = ((c * u + s_ * v) / a.view(B, 1, 1)) ** 2 + ((-s_ * u + c * v) / b.view(B, 1, 1)) ** 2 <= 1.0
    inside &= (rand(B) < p).view(B, 1, 1)
    sy = (ys - dy.view(B, 1, 1)).clamp(0, H - 1).long().expand(B, H, W)  # source pixel of each destination
    sx = (xs - dx.view(B, 1, 1)).clamp(0, W - 1).long().expand(B, H, W)
    src = images[other.to(dev)].flatten(2).gather(2, (sy * W + sx).flatten(1).unsqueeze(1).expand(B, 3, H * W))
    return torch.where(inside.unsqueeze(1), src.view(B, 3, H, W), images)
