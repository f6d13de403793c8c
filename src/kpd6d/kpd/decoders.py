"""Heatmap decoders (``DECODERS``): heatmaps (B, K, H, W) → coords (B, K, 2) (x, y) heatmap px and
confidences (B, K).

Pixel centres are at integer coordinates; map the coords to crop pixels with
:func:`kpd6d.kpd.heatmaps.heatmap_to_crop` and to image pixels with the crop's inverse affine.

* ``argmax`` — paper Eq. 1: the location of the heatmap maximum; confidence = the maximum.
* ``soft_argmax`` — weighted centroid (kornia ``spatial_soft_argmax2d`` on log-heatmaps: weights ∝
  ``max(H, 0)^temperature``) in a (2·window+1)² window around the argmax (``window=None``: the whole
  map, as DSNT / integral regression); confidence = the maximum.
* ``subpixel`` — argmax refined by a local fit: ``taylor`` (one Newton step on log H with the 2-D
  Hessian by central differences; exact for the Gaussian targets), ``dark`` (DARK: Gaussian-smooth
  the map first, then ``taylor``), ``quadratic`` (per-axis parabola through the 3 values around
  the maximum); confidence = the maximum.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from kpd6d.registry import DECODERS

__all__ = ["ArgmaxDecoder", "SoftArgmaxDecoder", "SubpixelDecoder"]


def _check(heatmaps) -> torch.Tensor:
    if not isinstance(heatmaps, torch.Tensor) or heatmaps.ndim != 4:
        shape = tuple(getattr(heatmaps, "shape", ()))
        raise ValueError(f"decoder input must be a torch tensor (B, K, H, W), got {type(heatmaps).__name__} {shape}")
    return heatmaps.float()


def _argmax(hm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Integer (x, y) of the maximum (B, K, 2) and the maximum (B, K)."""
    B, K, H, W = hm.shape
    conf, idx = hm.reshape(B, K, H * W).max(dim=-1)
    xy = torch.stack([idx % W, torch.div(idx, W, rounding_mode="floor")], dim=-1).to(hm.dtype)
    return xy, conf


class ArgmaxDecoder:
    """Paper Eq. 1: ``x̂ = argmax_p H(p)``, confidence ``max_p H(p)``."""

    def __call__(self, heatmaps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return _argmax(_check(heatmaps))


class SoftArgmaxDecoder:
    """Weighted centroid of ``max(H, 0)^temperature`` around the argmax (or over the whole map)."""

    def __init__(self, temperature: float = 1.0, window: int | None = 5) -> None:
        if temperature <= 0:
            raise ValueError(f"soft_argmax: temperature must be > 0, got {temperature}")
        if window is not None and int(window) < 1:
            raise ValueError(f"soft_argmax: window must be >= 1 heatmap px or None, got {window}")
        self.temperature = float(temperature)
        self.window = None if window is None else int(window)

    def __call__(self, heatmaps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        from kornia.geometry.subpix import spatial_soft_argmax2d

        hm = _check(heatmaps)
        B, K, H, W = hm.shape
        peak, conf = _argmax(hm)
        logh = torch.log(hm.clamp(min=1e-12))
        if self.window is None:
            return spatial_soft_argmax2d(logh, self.temperature, normalized_coordinates=False), conf
        r = self.window
        # window (2r+1)^2 around the argmax; outside the map the weight is 0 (log = -inf ~ -1e4)
        padded = F.pad(logh.reshape(B * K, 1, H, W), (r, r, r, r), value=-1e4)
        offs = torch.arange(-r, r + 1, device=hm.device)
        px = peak.reshape(B * K, 2).long()
        ys = (px[:, 1:2] + r + offs)[:, :, None]  # (N, 2r+1, 1)
        xs = (px[:, 0:1] + r + offs)[:, None, :]  # (N, 1, 2r+1)
        n = torch.arange(B * K, device=hm.device)[:, None, None]
        patch = padded[n, 0, ys, xs]  # (N, 2r+1, 2r+1)
        local = spatial_soft_argmax2d(patch[:, None], self.temperature, normalized_coordinates=False)[:, 0]
        coords = px.to(hm.dtype) - r + local
        return coords.reshape(B, K, 2), conf


class SubpixelDecoder:
    """Argmax refined by a local ``taylor`` / ``dark`` / ``quadratic`` fit (offset clamped to ±1 px)."""

    METHODS = ("taylor", "dark", "quadratic")

    def __init__(self, method: str = "dark", blur_sigma: float = 1.0) -> None:
        if method not in self.METHODS:
            raise ValueError(f"subpixel: unknown method {method!r}; known: {', '.join(self.METHODS)}")
        if method == "dark" and blur_sigma <= 0:
            raise ValueError(f"subpixel: blur_sigma must be > 0, got {blur_sigma}")
        self.method = method
        self.blur_sigma = float(blur_sigma)

    def __call__(self, heatmaps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        hm = _check(heatmaps)
        B, K, H, W = hm.shape
        peak, conf = _argmax(hm)
        src = hm
        if self.method == "dark":
            from kornia.filters import gaussian_blur2d

            k = 2 * round(3 * self.blur_sigma) + 1
            src = gaussian_blur2d(hm, (k, k), (self.blur_sigma, self.blur_sigma), border_type="replicate")
        if self.method in ("taylor", "dark"):
            src = torch.log(src.clamp(min=1e-10))
        # 3x3 neighbourhood around the peak (replicate at the border -> zero derivative there)
        padded = F.pad(src.reshape(B * K, 1, H, W), (1, 1, 1, 1), mode="replicate")[:, 0]
        px = peak.reshape(B * K, 2).long()
        n = torch.arange(B * K, device=hm.device)

        def at(dx: int, dy: int) -> torch.Tensor:
            return padded[n, px[:, 1] + 1 + dy, px[:, 0] + 1 + dx]

        c = at(0, 0)
        dx = 0.5 * (at(1, 0) - at(-1, 0))
        dy = 0.5 * (at(0, 1) - at(0, -1))
        dxx = at(1, 0) - 2 * c + at(-1, 0)
        dyy = at(0, 1) - 2 * c + at(0, -1)
        zero = torch.zeros_like(c)
        if self.method == "quadratic":
            ox = torch.where(dxx < 0, -dx / dxx.clamp(max=-1e-12), zero)
            oy = torch.where(dyy < 0, -dy / dyy.clamp(max=-1e-12), zero)
        else:
            dxy = 0.25 * (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1))
            det = dxx * dyy - dxy * dxy
            ok = (det > 1e-12) & (dxx < 0)  # Hessian negative definite: a proper maximum
            sdet = torch.where(ok, det, torch.ones_like(det))
            ox = torch.where(ok, -(dyy * dx - dxy * dy) / sdet, zero)
            oy = torch.where(ok, -(dxx * dy - dxy * dx) / sdet, zero)
        off = torch.stack([ox, oy], dim=-1).clamp(-1.0, 1.0)
        off = torch.nan_to_num(off, nan=0.0, posinf=0.0, neginf=0.0)
        return peak + off.reshape(B, K, 2), conf


@DECODERS.register("argmax")
def argmax() -> ArgmaxDecoder:
    return ArgmaxDecoder()


@DECODERS.register("soft_argmax")
def soft_argmax(temperature: float = 1.0, window: int | None = 5) -> SoftArgmaxDecoder:
    return SoftArgmaxDecoder(temperature=temperature, window=window)


@DECODERS.register("subpixel")
def subpixel(method: str = "dark", blur_sigma: float = 1.0) -> SubpixelDecoder:
    return SubpixelDecoder(method=method, blur_sigma=blur_sigma)
