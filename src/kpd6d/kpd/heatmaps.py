"""Gaussian target heatmaps and the heatmap ↔ crop pixel mapping.

The paper's target for a keypoint at ``x`` (heatmap pixels) is ``H(p) = exp(-‖p − x‖² / σ²)``
(note: σ², not 2σ²), evaluated at every heatmap pixel centre ``p`` (integer coordinates).

A heatmap at output stride ``s`` covers the crop exactly (crop size = s × heatmap size), and pixel
centres sit at integer coordinates in both images, so heatmap pixel ``i`` covers crop pixels
``[s·i, s·(i+1))`` whose centre is ``s·i + (s − 1)/2``:

    crop = (hm + 0.5) · s − 0.5          hm = (crop + 0.5) / s − 0.5
"""

from __future__ import annotations

import torch

__all__ = ["crop_to_heatmap", "gaussian_heatmaps", "heatmap_to_crop"]


def heatmap_to_crop(coords, stride: int):
    """Heatmap pixels → crop pixels (pixel centres at integers in both): ``(hm + 0.5)·s − 0.5``."""
    return (coords + 0.5) * stride - 0.5


def crop_to_heatmap(coords, stride: int):
    """Crop pixels → heatmap pixels: ``(crop + 0.5)/s − 0.5`` (inverse of :func:`heatmap_to_crop`)."""
    return (coords + 0.5) / stride - 0.5


def gaussian_heatmaps(coords: torch.Tensor, size: tuple[int, int] | int, sigma: float) -> torch.Tensor:
    """Target heatmaps ``exp(-‖p − x‖² / σ²)`` for keypoints ``coords`` (..., K, 2) (x, y) heatmap px.

    ``size`` is the heatmap (width, height) (or one int for a square one); returns (..., K, H, W)
    with the dtype / device of ``coords``. Keypoints outside the heatmap still get their (partial or
    all-zero) Gaussian: the target is defined for invisible keypoints too. Non-finite coordinates
    give all-zero maps.
    """
    if not isinstance(coords, torch.Tensor):
        coords = torch.as_tensor(coords, dtype=torch.float32)
    if not coords.is_floating_point():
        coords = coords.float()
    if coords.shape[-1] != 2:
        raise ValueError(f"gaussian_heatmaps: coords must be (..., K, 2), got shape {tuple(coords.shape)}")
    if sigma <= 0:
        raise ValueError(f"gaussian_heatmaps: sigma must be > 0, got {sigma}")
    W, H = (size, size) if isinstance(size, int) else size
    xs = torch.arange(W, dtype=coords.dtype, device=coords.device)
    ys = torch.arange(H, dtype=coords.dtype, device=coords.device)
    finite = torch.isfinite(coords).all(-1)
    c = torch.where(finite[..., None], coords, torch.full_like(coords, -1e6))
    dx2 = (xs - c[..., 0:1]) ** 2  # (..., K, W)
    dy2 = (ys - c[..., 1:2]) ** 2  # (..., K, H)
    return torch.exp(-(dy2[..., :, None] + dx2[..., None, :]) / (sigma * sigma))
