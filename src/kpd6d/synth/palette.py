"""Colour palettes for the procedural content (backgrounds, table tops, rooms, distractors).

* ``uniform``: every RGB channel uniform in [0, 255] (saturated, cartoon-like colours: classic
  domain randomisation).
* ``natural``: the colours of everyday indoor things, as a prior about photographs (not measured on
  any real frame): hue uniform, saturation mostly low (Beta(1.2, 3), mean 0.29, a tail up to fully
  saturated), value spread over the range (0.05 + 0.9 Beta(2, 2)). Procedural clutter coloured this
  way does not stand out from the scanned objects by colour alone, so a network has to learn the
  objects' shapes and textures rather than "muted = object, saturated = background".
"""

from __future__ import annotations

import numpy as np

__all__ = ["PALETTES", "check_palette", "random_color", "random_colors"]

PALETTES = ("uniform", "natural")


def check_palette(palette: str) -> str:
    if palette not in PALETTES:
        raise ValueError(f"palette must be one of {list(PALETTES)}, got {palette!r}")
    return palette


def _hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectorised HSV (each in [0, 1]) -> RGB in [0, 1], shape (..., 3)."""
    i = np.floor(h * 6.0).astype(np.int64) % 6
    f = h * 6.0 - np.floor(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    table = np.stack([np.stack(c, -1) for c in ((v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q))], 0)
    return np.take_along_axis(table, i[None, ..., None].repeat(3, -1), 0)[0]


def random_colors(rng: np.random.Generator, n: int, palette: str = "uniform") -> np.ndarray:
    """``n`` colours, float64 (n, 3) RGB in [0, 255], drawn from ``palette``."""
    if palette == "uniform":
        return rng.uniform(0, 255, (n, 3))
    check_palette(palette)
    h = rng.random(n)
    s = rng.beta(1.2, 3.0, n)
    v = 0.05 + 0.9 * rng.beta(2.0, 2.0, n)
    return 255.0 * _hsv_to_rgb(h, s, v)


def random_color(rng: np.random.Generator, palette: str = "uniform") -> np.ndarray:
    """One colour, float64 (3,) RGB in [0, 255]."""
    return random_colors(rng, 1, palette)[0]
