"""Training-time photometric changes of image batches, shared by both stages' augmentation.

The sim-to-real part of the augmentation: what a real camera does to a scene that a render does not
(contrast and gamma of the response curve, white balance, defocus / motion blur, sensor noise, the
sharpening of the camera's image processing), and one change of the image's "style" rather than its
camera: amplitude mixing (each image's Fourier amplitude spectrum blended with another image's of the
batch, its phase kept: textures, contrast and colour statistics change while edges and positions stay,
as in FACT, Xu et al., "A Fourier-based Framework for Domain Generalization", CVPR 2021).
:class:`kpd6d.kpd.augment.BatchAugment` (KPD) and :func:`kpd6d.detection.augment.augment_batch`
(detector) both call :func:`photometric_batch`. Generation-time effects, baked into the saved
images, are :mod:`kpd6d.synth.photometric`.

Images are float (B, 3, H, W) in [0, 1]. Every random draw is per image and comes from ``generator``
(a ``torch.Generator``; None: torch's global generator), so a seeded run is repeatable.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
import torch.nn.functional as F

__all__ = ["PHOTOMETRIC_DEFAULTS", "amplitude_mix_batch", "check_photometric", "gaussian_blur_batch",
           "photometric_batch"]

# all off: a stage that does not name them behaves as before
PHOTOMETRIC_DEFAULTS: dict = {
    "contrast": 1.0,          # factor about the image's mean grey, log-uniform in [1/c, c]
    "gamma": 1.0,             # x ** g, g log-uniform in [1/gamma, gamma] (the camera's response curve)
    "channel_gain": 0.0,      # per-channel gain uniform in 1 +- channel_gain (white balance / colour temperature)
    "blur_p": 0.0,            # probability of a Gaussian blur ...
    "blur_sigma": (0.1, 1.5),  # ... with sigma (px) uniform in this range
    "noise_p": 0.0,           # probability of additive Gaussian noise ...
    "noise_std": 0.02,        # ... with std uniform in [0, noise_std] (0..1 scale)
    "sharpen_p": 0.0,         # probability of an unsharp mask (Gaussian sigma 1 px), after the noise as in a camera ...
    "sharpen_amount": (0.3, 1.5),  # ... x + a (x - blur(x)), amount a uniform in this range
    "amplitude_p": 0.0,       # probability that an image's amplitude spectrum is blended with another's (first) ...
    "amplitude_mix": 1.0,     # ... with a weight uniform in [0, amplitude_mix] on the other's (amplitude_mix_batch)
}


def check_photometric(cfg: Mapping | None, where: str = "augment") -> dict:
    """``cfg`` merged over :data:`PHOTOMETRIC_DEFAULTS`, validated (unknown keys and bad values are
    errors that name the key)."""
    cfg = dict(cfg or {})
    unknown = sorted(set(cfg) - set(PHOTOMETRIC_DEFAULTS))
    if unknown:
        raise ValueError(f"{where}: unknown photometric setting(s) {unknown}; known: {sorted(PHOTOMETRIC_DEFAULTS)}")
    out = {**PHOTOMETRIC_DEFAULTS, **cfg}
    for key in ("contrast", "gamma"):
        if not float(out[key]) >= 1.0:
            raise ValueError(f"{where}.{key} is a factor >= 1 (1 = off), got {out[key]!r}")
    if not 0.0 <= float(out["channel_gain"]) < 1.0:
        raise ValueError(f"{where}.channel_gain must lie in [0, 1), got {out['channel_gain']!r}")
    for key in ("blur_p", "noise_p", "sharpen_p", "amplitude_p"):
        if not 0.0 <= float(out[key]) <= 1.0:
            raise ValueError(f"{where}.{key} is a probability in [0, 1], got {out[key]!r}")
    lo, hi = (float(v) for v in out["blur_sigma"])
    if not 0.0 < lo <= hi:
        raise ValueError(f"{where}.blur_sigma must be [lo, hi] with 0 < lo <= hi, got {list(out['blur_sigma'])}")
    if not float(out["noise_std"]) >= 0.0:
        raise ValueError(f"{where}.noise_std must be >= 0, got {out['noise_std']!r}")
    out["blur_sigma"] = (lo, hi)
    lo, hi = (float(v) for v in out["sharpen_amount"])
    if not 0.0 <= lo <= hi:
        raise ValueError(f"{where}.sharpen_amount must be [lo, hi] with 0 <= lo <= hi, got {list(out['sharpen_amount'])}")
    out["sharpen_amount"] = (lo, hi)
    if not 0.0 <= float(out["amplitude_mix"]) <= 1.0:
        raise ValueError(f"{where}.amplitude_mix is the largest weight of the other image's amplitude, in [0, 1], "
                         f"got {out['amplitude_mix']!r}")
    return out


def _uniform(n: int, lo: float, hi: float, generator, device, dtype) -> torch.Tensor:
    return (torch.rand(n, generator=generator) * (hi - lo) + lo).to(device=device, dtype=dtype)


def gaussian_blur_batch(images: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Blur image b with an isotropic Gaussian of standard deviation ``sigma[b]`` px (separable,
    kernel radius ceil(3 sigma_max), reflect padding); sigma 0 leaves an image unchanged."""
    B, C, H, W = images.shape
    sigma = sigma.to(images).reshape(B)
    r = min(max(1, math.ceil(3.0 * float(sigma.max()))), min(H, W) - 1)  # reflect padding needs r < size
    if r < 1:
        return images
    x = torch.arange(-r, r + 1, device=images.device, dtype=images.dtype)
    s = sigma.clamp(min=1e-6)[:, None]
    k = torch.exp(-0.5 * (x[None, :] / s) ** 2)
    k = torch.where(sigma[:, None] > 0, k / k.sum(1, keepdim=True), (x[None, :] == 0).to(images.dtype))
    # grouped convolution: one kernel per image, applied to its C channels
    kx = k.repeat_interleave(C, 0)[:, None, None, :]  # (B*C, 1, 1, 2r+1)
    ky = k.repeat_interleave(C, 0)[:, None, :, None]
    y = images.reshape(1, B * C, H, W)
    y = F.conv2d(F.pad(y, (r, r, 0, 0), mode="reflect"), kx, groups=B * C)
    y = F.conv2d(F.pad(y, (0, 0, r, r), mode="reflect"), ky, groups=B * C)
    return y.reshape(B, C, H, W)


def _on_images(x: torch.Tensor, on: torch.Tensor, fn) -> torch.Tensor:
    """``x`` with ``fn(x[i], i)`` in place of the images ``i`` where ``on`` (bool, (B,)) holds, out of place: the
    filters run on the chosen images only."""
    i = on.nonzero()[:, 0].to(x.device)
    return x.index_copy(0, i, fn(x[i], i)) if len(i) else x


@torch.no_grad()
def amplitude_mix_batch(images: torch.Tensor, weight: torch.Tensor, partner: torch.Tensor) -> torch.Tensor:
    """Each image ``i`` of ``images`` (B, C, H, W) with its per-channel Fourier amplitude replaced by
    ``(1 - weight[i]) |F(x_i)| + weight[i] |F(x_partner[i])|`` and its phase kept (``weight`` (B,) in
    [0, 1]; ``partner`` (B,) indices into the batch). Weight 0 returns the image (up to float rounding);
    the result is not clipped."""
    H, W = images.shape[-2:]
    f = torch.fft.rfft2(images.float(), norm="ortho")
    amp, phase = f.abs(), f.angle()
    w = weight.to(amp)[:, None, None, None]
    mixed = (1.0 - w) * amp + w * amp[partner]
    return torch.fft.irfft2(torch.polar(mixed, phase), s=(H, W), norm="ortho").to(images.dtype)


@torch.no_grad()
def photometric_batch(images: torch.Tensor, cfg: Mapping, generator: torch.Generator | None = None) -> torch.Tensor:
    """Apply, per image and in this order: amplitude mixing (with ``amplitude_p``, the partner another image
    of the batch), gamma, contrast, channel gains, blur (with ``blur_p``),
    noise (with ``noise_p``), an unsharp mask (with ``sharpen_p``: x + a (x - blur(x)), blur sigma 1 px;
    it sharpens the noise too, as a camera's processing does); ``cfg`` as :func:`check_photometric`
    returns it. The result is clipped to [0, 1]. With every setting off the images are returned unchanged."""
    B = images.shape[0]
    dev, dt = images.device, images.dtype
    x = images
    if cfg["amplitude_p"] > 0.0 and B > 1:
        on = torch.rand(B, generator=generator) < cfg["amplitude_p"]
        w = _uniform(B, 0.0, cfg["amplitude_mix"], generator, dev, dt)
        # a partner other than the image itself: a random non-zero shift of the index
        partner = (torch.arange(B) + torch.randint(1, B, (B,), generator=generator)) % B
        if on.any():
            x = torch.where(on.to(dev)[:, None, None, None], amplitude_mix_batch(x, w, partner.to(dev)), x)
    if cfg["gamma"] > 1.0:
        lg = math.log(cfg["gamma"])
        g = torch.exp(_uniform(B, -lg, lg, generator, dev, dt))
        x = x.clamp(min=0.0) ** g[:, None, None, None]
    if cfg["contrast"] > 1.0:
        lc = math.log(cfg["contrast"])
        c = torch.exp(_uniform(B, -lc, lc, generator, dev, dt))[:, None, None, None]
        mean = x.mean(dim=(1, 2, 3), keepdim=True)
        x = (x - mean) * c + mean
    if cfg["channel_gain"] > 0.0:
        gain = 1.0 + (torch.rand((B, 3), generator=generator) * 2 - 1).to(dev, dt) * cfg["channel_gain"]
        x = x * gain[:, :, None, None]
    if cfg["blur_p"] > 0.0:
        on = torch.rand(B, generator=generator) < cfg["blur_p"]
        sigma = _uniform(B, *cfg["blur_sigma"], generator, dev, dt)
        x = _on_images(x, on, lambda y, i: gaussian_blur_batch(y, sigma[i]))
    if cfg["noise_p"] > 0.0 and cfg["noise_std"] > 0.0:
        on = (torch.rand(B, generator=generator) < cfg["noise_p"]).to(dev, dt)
        std = _uniform(B, 0.0, cfg["noise_std"], generator, dev, dt) * on
        noise = torch.randn(x.shape, generator=generator).to(dev, dt)
        x = x + noise * std[:, None, None, None]
    if cfg["sharpen_p"] > 0.0:
        on = torch.rand(B, generator=generator) < cfg["sharpen_p"]
        a = _uniform(B, *cfg["sharpen_amount"], generator, dev, dt)[:, None, None, None]
        x = _on_images(x, on, lambda y, i: y + a[i] * (y - gaussian_blur_batch(y, torch.ones(len(i), device=dev, dtype=dt))))
    return x.clamp(0.0, 1.0) if x is not images else images
