"""The ``DECODERS`` strategies of :mod:`kpd6d.kpd.decoders` in numpy, for the torch-free runtime
(:mod:`kpd6d.deploy.runtime`): the same config (``{name: argmax | soft_argmax | subpixel, ...}``), the
same maths, heatmaps (B, K, H, W) → coords (B, K, 2) heatmap px and confidences (B, K).

:func:`build_numpy_decoder` takes a decoder config node; :func:`heatmap_to_crop` is
:func:`kpd6d.kpd.heatmaps.heatmap_to_crop` (that module imports torch). Imports numpy only;
tests/test_deploy.py checks each decoder against its torch twin.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["NUMPY_DECODERS", "build_numpy_decoder", "heatmap_to_crop"]


def heatmap_to_crop(coords, stride: int):
    """Heatmap pixels → crop pixels: ``(hm + 0.5)·s − 0.5`` (as :mod:`kpd6d.kpd.heatmaps`)."""
    return (coords + 0.5) * stride - 0.5


def _check(heatmaps) -> np.ndarray:
    hm = np.asarray(heatmaps)
    if hm.ndim != 4:
        raise ValueError(f"decoder input must be (B, K, H, W), got shape {hm.shape}")
    return hm.astype(np.float32, copy=False)


def _argmax(hm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    B, K, H, W = hm.shape
    flat = hm.reshape(B, K, H * W)
    idx = flat.argmax(-1)
    conf = np.take_along_axis(flat, idx[..., None], -1)[..., 0]
    return np.stack([idx % W, idx // W], axis=-1).astype(np.float32), conf


def _soft_argmax(logits: np.ndarray, temperature: float) -> np.ndarray:
    """kornia ``spatial_soft_argmax2d(normalized_coordinates=False)``: (N, C, h, w) → (N, C, 2) (x, y)."""
    N, C, h, w = logits.shape
    z = logits.reshape(N, C, -1) * temperature
    z = np.exp(z - z.max(-1, keepdims=True))
    p = (z / z.sum(-1, keepdims=True)).reshape(N, C, h, w)
    xs = np.arange(w, dtype=np.float32)
    ys = np.arange(h, dtype=np.float32)
    return np.stack([(p.sum(2) * xs).sum(-1), (p.sum(3) * ys).sum(-1)], axis=-1)


class ArgmaxDecoder:
    def __call__(self, heatmaps):
        return _argmax(_check(heatmaps))


class SoftArgmaxDecoder:
    def __init__(self, temperature: float = 1.0, window: int | None = 5) -> None:
        if temperature <= 0 or (window is not None and int(window) < 1):
            raise ValueError(f"soft_argmax: needs temperature > 0 and window >= 1 or None, got {temperature}, {window}")
        self.temperature = float(temperature)
        self.window = None if window is None else int(window)

    def __call__(self, heatmaps):
        hm = _check(heatmaps)
        B, K, H, W = hm.shape
        peak, conf = _argmax(hm)
        logh = np.log(np.maximum(hm, 1e-12))
        if self.window is None:
            return _soft_argmax(logh, self.temperature), conf
        r = self.window
        padded = np.pad(logh.reshape(B * K, H, W), ((0, 0), (r, r), (r, r)), constant_values=-1e4)
        offs = np.arange(-r, r + 1)
        px = peak.reshape(B * K, 2).astype(np.int64)
        ys = (px[:, 1:2] + r + offs)[:, :, None]
        xs = (px[:, 0:1] + r + offs)[:, None, :]
        n = np.arange(B * K)[:, None, None]
        patch = padded[n, ys, xs]
        local = _soft_argmax(patch[:, None], self.temperature)[:, 0]
        return (px.astype(np.float32) - r + local).reshape(B, K, 2), conf


def _gaussian_blur(hm: np.ndarray, sigma: float) -> np.ndarray:
    """kornia ``gaussian_blur2d((k, k), (σ, σ), border_type="replicate")`` with k = 2·round(3σ)+1."""
    k = 2 * round(3 * sigma) + 1
    x = np.arange(k, dtype=np.float64) - k // 2
    g = np.exp(-(x**2) / (2 * sigma**2))
    g = (g / g.sum()).astype(np.float32)
    r = k // 2
    H, W = hm.shape[-2:]
    p = np.pad(hm, ((0, 0), (0, 0), (0, 0), (r, r)), mode="edge")
    out = sum(g[i] * p[..., i:i + W] for i in range(k))
    p = np.pad(out, ((0, 0), (0, 0), (r, r), (0, 0)), mode="edge")
    return sum(g[i] * p[..., i:i + H, :] for i in range(k)).astype(np.float32)


class SubpixelDecoder:
    METHODS = ("taylor", "dark", "quadratic")

    def __init__(self, method: str = "dark", blur_sigma: float = 1.0) -> None:
        if method not in self.METHODS:
            raise ValueError(f"subpixel: unknown method {method!r}; known: {', '.join(self.METHODS)}")
        self.method, self.blur_sigma = method, float(blur_sigma)

    def __call__(self, heatmaps):
        hm = _check(heatmaps)
        B, K, H, W = hm.shape
        peak, conf = _argmax(hm)
        src = _gaussian_blur(hm, self.blur_sigma) if self.method == "dark" else hm
        if self.method in ("taylor", "dark"):
            src = np.log(np.maximum(src, 1e-10))
        padded = np.pad(src.reshape(B * K, H, W), ((0, 0), (1, 1), (1, 1)), mode="edge")
        px = peak.reshape(B * K, 2).astype(np.int64)
        n = np.arange(B * K)

        def at(dx: int, dy: int) -> np.ndarray:
            return padded[n, px[:, 1] + 1 + dy, px[:, 0] + 1 + dx]

        with np.errstate(divide="ignore", invalid="ignore"):
            c = at(0, 0)
            dx = 0.5 * (at(1, 0) - at(-1, 0))
            dy = 0.5 * (at(0, 1) - at(0, -1))
            dxx = at(1, 0) - 2 * c + at(-1, 0)
            dyy = at(0, 1) - 2 * c + at(0, -1)
            if self.method == "quadratic":
                ox = np.where(dxx < 0, -dx / np.minimum(dxx, -1e-12), 0.0)
                oy = np.where(dyy < 0, -dy / np.minimum(dyy, -1e-12), 0.0)
            else:
                dxy = 0.25 * (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1))
                det = dxx * dyy - dxy * dxy
                ok = (det > 1e-12) & (dxx < 0)
                sdet = np.where(ok, det, 1.0)
                ox = np.where(ok, -(dyy * dx - dxy * dy) / sdet, 0.0)
                oy = np.where(ok, -(dxx * dy - dxy * dx) / sdet, 0.0)
        off = np.clip(np.stack([ox, oy], axis=-1), -1.0, 1.0)
        off = np.nan_to_num(off, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
        return peak + off.reshape(B, K, 2), conf


NUMPY_DECODERS = {"argmax": ArgmaxDecoder, "soft_argmax": SoftArgmaxDecoder, "subpixel": SubpixelDecoder}


def build_numpy_decoder(cfg: Mapping[str, Any] | str | None):
    """The numpy twin of a ``DECODERS`` config (default: ``subpixel``, as the codec's)."""
    cfg = {"name": cfg} if isinstance(cfg, str) else dict(cfg or {"name": "subpixel"})
    name = cfg.pop("name", "subpixel")
    if name not in NUMPY_DECODERS:
        raise ValueError(f"decoder {name!r} has no numpy implementation (the torch-free runtime decodes with "
                         f"{', '.join(sorted(NUMPY_DECODERS))})")
    return NUMPY_DECODERS[name](**cfg)
