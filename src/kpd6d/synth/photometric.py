"""Photometric effects applied to the composite image (after pasting): blur, noise, colour shift.

Each effect is applied with probability ``prob`` (independently), with strengths drawn from the
configured ranges. ``prob: 0`` turns them off (e.g. to leave them to GPU augmentation in training).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields

import numpy as np

__all__ = ["PhotometricConfig", "apply_photometric"]


@dataclass(frozen=True)
class PhotometricConfig:
    prob: float = 0.5  # probability of each effect
    blur_sigma: tuple[float, float] = (0.3, 1.2)  # Gaussian blur sigma (px)
    noise_sigma: tuple[float, float] = (1.0, 6.0)  # additive Gaussian noise std (0..255 scale)
    brightness: float = 0.15  # additive shift, fraction of 255, +-
    contrast: tuple[float, float] = (0.8, 1.2)  # multiplicative about the mean
    channel_gain: float = 0.08  # per-channel gain (colour cast), +-

    @classmethod
    def from_mapping(cls, cfg: Mapping | None) -> PhotometricConfig:
        if cfg is None:
            return cls()
        if isinstance(cfg, PhotometricConfig):
            return cfg
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(cfg) - known)
        if unknown:
            raise ValueError(f"photometric: unknown option(s) {unknown}; known: {sorted(known)}")
        kw = {k: tuple(v) if isinstance(v, list | tuple) else v for k, v in cfg.items()}
        out = cls(**kw)
        if not 0.0 <= out.prob <= 1.0:
            raise ValueError(f"photometric.prob must lie in [0, 1], got {out.prob}")
        return out


def apply_photometric(img: np.ndarray, rng: np.random.Generator, cfg: PhotometricConfig) -> np.ndarray:
    """Return a new RGB uint8 image with random blur / colour shift / noise applied."""
    import cv2

    if cfg.prob <= 0:
        return img
    do_blur, do_color, do_noise = rng.random(3) < cfg.prob
    out = img
    if do_blur:
        out = cv2.GaussianBlur(out, (0, 0), float(rng.uniform(*cfg.blur_sigma)))
    if do_color:
        gain = float(rng.uniform(*cfg.contrast)) * (1.0 + rng.uniform(-cfg.channel_gain, cfg.channel_gain, 3))
        bias = rng.uniform(-cfg.brightness, cfg.brightness) * 255.0
        mean = np.asarray(cv2.mean(out)[:3])
        # out = gain * (img - mean) + mean + bias, as a per-channel lookup table (fast)
        lut = np.clip(gain[None, :] * (np.arange(256)[:, None] - mean[None, :]) + mean[None, :] + bias + 0.5, 0, 255)
        out = cv2.LUT(out, lut.astype(np.uint8).reshape(256, 1, 3))
    if do_noise:  # grey (luminance) Gaussian noise; OpenCV's generator, seeded from rng (fast)
        sigma = float(rng.uniform(*cfg.noise_sigma))
        cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
        noise = np.empty(out.shape[:2], np.float32)
        cv2.randn(noise, 0.0, sigma)
        out = cv2.add(out, cv2.merge([noise, noise, noise]), dtype=cv2.CV_8U)
    return np.ascontiguousarray(out)
