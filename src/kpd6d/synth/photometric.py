"""Photometric effects applied to the composite image (after pasting): blur, camera exposure and
saturation, colour shift, noise.

Blur, colour shift and noise are each applied with probability ``prob`` (independently), with
strengths drawn from the configured ranges. ``exposure`` and ``saturation`` model the camera that
took the picture, so every image gets one drawn from its range (log-uniform); their default range
``(1, 1)`` leaves images (and the random stream) as before. ``prob: 0`` turns everything off (e.g.
to leave it to GPU augmentation in training).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields

import numpy as np

__all__ = ["PhotometricConfig", "apply_photometric", "camera_exposure_saturation", "surface_detail"]


@dataclass(frozen=True)
class PhotometricConfig:
    prob: float = 0.5  # probability of each effect
    blur_sigma: tuple[float, float] = (0.3, 1.2)  # Gaussian blur sigma (px)
    noise_sigma: tuple[float, float] = (1.0, 6.0)  # additive Gaussian noise std (0..255 scale)
    brightness: float = 0.15  # additive shift, fraction of 255, +-
    contrast: tuple[float, float] = (0.8, 1.2)  # multiplicative about the mean
    channel_gain: float = 0.08  # per-channel gain (colour cast), +-
    exposure: tuple[float, float] = (1.0, 1.0)  # camera exposure: a gain on linear intensity (2 = one stop brighter), clipped
    saturation: tuple[float, float] = (1.0, 1.0)  # chroma x this about each pixel's luma (1: as rendered)

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
        for name in ("exposure", "saturation"):
            v = getattr(out, name)
            try:
                lo, hi = (float(x) for x in v)
            except (TypeError, ValueError):
                raise ValueError(f"photometric.{name} must be [low, high] with 0 < low <= high, got {v!r}") from None
            if not 0.0 < lo <= hi:
                raise ValueError(f"photometric.{name} must be [low, high] with 0 < low <= high, got {[lo, hi]}")
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
    out = camera_exposure_saturation(out, _log_uniform(rng, cfg.exposure), _log_uniform(rng, cfg.saturation))
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


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    """A factor log-uniform in ``bounds``; a degenerate range draws nothing (the stream stays as it was)."""
    lo, hi = bounds
    return float(lo) if lo == hi else float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def camera_exposure_saturation(img: np.ndarray, exposure: float = 1.0, saturation: float = 1.0) -> np.ndarray:
    """An sRGB uint8 image as a camera with ``exposure`` x the light would record it (linear intensity
    x ``exposure``; with the sRGB curve taken as the power 2.2 that is a gain of ``exposure ** (1 / 2.2)``
    on the stored values, clipped at white), then its chroma scaled by ``saturation`` about each pixel's
    luma (Rec. 601 weights). Factors of 1 return ``img`` itself."""
    import cv2

    out = img
    if exposure != 1.0:
        gain = float(exposure) ** (1.0 / 2.2)
        lut = np.clip(np.arange(256) * gain + 0.5, 0, 255).astype(np.uint8)
        out = cv2.LUT(out, lut)
    if saturation != 1.0:
        f = out.astype(np.float32)
        luma = f @ np.array([0.299, 0.587, 0.114], np.float32)
        f = luma[..., None] + float(saturation) * (f - luma[..., None])
        out = np.clip(f + 0.5, 0, 255).astype(np.uint8)
    return out


def surface_detail(img: np.ndarray, mask: np.ndarray, rng: np.random.Generator,
                   amplitude: tuple[float, float] = (0.04, 0.15), grain: tuple[float, float] = (0.5, 1.5),
                   sharpen: tuple[float, float] = (0.0, 1.0)) -> np.ndarray:
    """Fine surface detail on the pixels of ``mask`` (bool, H x W) of an RGB uint8 image: a grey
    multiplicative grain (Gaussian noise smoothed over ``grain`` px, unit standard deviation, times an
    amplitude drawn from ``amplitude``) and an unsharp mask (amount drawn from ``sharpen``, radius 1 px).
    Rendered vertex-coloured meshes are smoother than photographed objects, whose surfaces show grain,
    print and wear; pixels outside ``mask`` are returned unchanged. Returns a new image."""
    import cv2

    out = img.copy()
    ys, xs = np.nonzero(mask)
    if len(ys) == 0:
        return out
    y0, y1 = max(int(ys.min()) - 3, 0), int(ys.max()) + 4  # the masked region and a margin for the filters
    x0, x1 = max(int(xs.min()) - 3, 0), int(xs.max()) + 4
    win = img[y0:y1, x0:x1].astype(np.float32)
    m = mask[y0:y1, x0:x1]
    a, sigma, k = (float(rng.uniform(*r)) for r in (amplitude, grain, sharpen))
    n = cv2.GaussianBlur(rng.standard_normal(m.shape).astype(np.float32), (0, 0), sigma)
    n *= np.float32(1.0 / max(float(n.std()), 1e-6))
    detailed = win + np.float32(k) * (win - cv2.GaussianBlur(win, (0, 0), 1.0))
    detailed *= (1.0 + np.float32(a) * n)[..., None]
    out[y0:y1, x0:x1][m] = np.clip(detailed[m] + 0.5, 0, 255).astype(np.uint8)
    return out
