"""Backgrounds for render-and-paste: a user folder of images, else procedural ones made in code.

Procedural backgrounds mix a base (gradient, multi-octave noise, stripes / checkerboard texture)
with random shapes and small clutter, then a little grain. Nothing is downloaded.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from pathlib import Path

import numpy as np

from kpd6d.config import to_fraction
from kpd6d.synth.palette import check_palette, random_color

__all__ = ["BackgroundSource", "FolderBackgrounds", "ProceduralBackgrounds", "make_background_source",
           "procedural_background"]

#: file extensions OpenCV reads (cv2.imread)
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm", ".pbm",
                    ".pnm", ".jp2", ".sr", ".ras", ".exr", ".hdr", ".pic")


class BackgroundSource:
    def sample(self, rng: np.random.Generator, width: int, height: int) -> np.ndarray:
        """An RGB uint8 (height, width, 3) background."""
        raise NotImplementedError


def _random_color(rng: np.random.Generator, palette: str = "uniform") -> tuple[int, int, int]:
    if palette == "uniform":
        return tuple(int(c) for c in rng.integers(0, 256, 3))
    return tuple(int(c) for c in np.rint(random_color(rng, palette)))


def _colors(rng: np.random.Generator, palette: str) -> tuple[np.ndarray, np.ndarray]:
    """Two colours (float32 RGB in [0, 255]) for a gradient, noise or texture base."""
    return random_color(rng, palette).astype(np.float32), random_color(rng, palette).astype(np.float32)


def _gradient(rng, w, h, palette="uniform"):
    c0, c1 = _colors(rng, palette)
    xs = np.linspace(-1, 1, w, dtype=np.float32)[None, :]
    ys = np.linspace(-1, 1, h, dtype=np.float32)[:, None]
    if rng.random() < 0.5:  # linear
        a = rng.uniform(0, 2 * np.pi)
        s = np.float32(np.cos(a)) * xs + np.float32(np.sin(a)) * ys
    else:  # radial
        cx, cy = rng.uniform(-0.5, 0.5, 2).astype(np.float32)
        s = np.sqrt((xs - cx) ** 2 + (ys - cy) ** 2)
    s = (s - s.min()) / max(float(np.ptp(s)), 1e-6)
    return c0 + s[..., None] * (c1 - c0)


def _noise(rng, w, h, palette="uniform"):
    import cv2

    out = np.zeros((h, w, 3), np.float32)
    amp, total = 1.0, 0.0
    base = int(rng.integers(2, 8))
    for octave in range(4):
        n = base * 2**octave
        small = rng.random((max(2, n * h // w), n, 3), dtype=np.float32)
        out += np.float32(amp) * cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= rng.uniform(0.35, 0.65)
    out *= np.float32(1.0 / total)
    lo, hi = _colors(rng, palette)
    return lo + out * (hi - lo)


def _texture(rng, w, h, palette="uniform"):
    """Stripes (sine or square) or a checkerboard at a random angle; ``w, h`` is the working size
    (half the output), periods are given in it."""
    import cv2

    period = rng.uniform(2, 30)
    a = rng.uniform(0, np.pi)
    xs = np.arange(w, dtype=np.float32)[None, :]
    ys = np.arange(h, dtype=np.float32)[:, None]
    u = np.float32(np.cos(a)) * xs + np.float32(np.sin(a)) * ys
    if rng.random() < 0.5:  # stripes
        s = (0.5 + 0.5 * np.sin(np.float32(2 * np.pi / period) * u)) if rng.random() < 0.5 else (u // period) % 2
    else:  # checkerboard
        v = np.float32(-np.sin(a)) * xs + np.float32(np.cos(a)) * ys
        s = (u // period + v // period) % 2
    s = cv2.GaussianBlur(s.astype(np.float32), (0, 0), rng.uniform(0.3, 1.0))
    c0, c1 = _colors(rng, palette)
    return c0 + s[..., None] * (c1 - c0)


def _shapes(rng, img, count, max_size, palette="uniform"):
    import cv2

    h, w = img.shape[:2]
    for _ in range(count):
        color = _random_color(rng, palette)
        kind = rng.integers(0, 5)
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        s = int(rng.integers(2, max(3, max_size)))
        filled = -1 if rng.random() < 0.7 else int(rng.integers(1, 6))
        if kind == 0:
            cv2.rectangle(img, (cx - s, cy - s // 2), (cx + s, cy + s // 2), color, filled)
        elif kind == 1:
            cv2.circle(img, (cx, cy), s, color, filled)
        elif kind == 2:
            cv2.ellipse(img, (cx, cy), (s, max(1, s // 3)), float(rng.uniform(0, 180)), 0, 360, color, filled)
        elif kind == 3:
            pts = (np.array([cx, cy]) + rng.integers(-s, s + 1, (int(rng.integers(3, 7)), 2))).astype(np.int32)
            cv2.fillPoly(img, [pts], color)
        else:
            p2 = (cx + int(rng.integers(-2 * s, 2 * s + 1)), cy + int(rng.integers(-2 * s, 2 * s + 1)))
            cv2.line(img, (cx, cy), p2, color, int(rng.integers(1, 8)))


def procedural_background(rng: np.random.Generator, width: int, height: int, palette: str = "uniform",
                          printed: float = 0.0) -> np.ndarray:
    """One procedural RGB uint8 background (height, width, 3), its colours from ``palette``
    (:mod:`kpd6d.synth.palette`); with probability ``printed``, 1-5 printed sheets lie on it
    (:func:`kpd6d.synth.prints.paste_sheets`; 0 draws nothing more from ``rng``)."""
    import cv2

    # the base is made at half resolution and upsampled (smooth patterns; 4x fewer pixels to compute)
    hw, hh = max(2, (width + 1) // 2), max(2, (height + 1) // 2)
    kind = rng.integers(0, 3)
    base = (_gradient, _noise, _texture)[kind](rng, hw, hh, palette)
    if rng.random() < 0.5:  # blend two bases for more variety
        other = (_gradient, _noise, _texture)[rng.integers(0, 3)](rng, hw, hh, palette)
        a = np.float32(rng.uniform(0.2, 0.8))
        base = a * base + (1 - a) * other
    base = np.clip(base, 0, 255).astype(np.uint8)
    img = np.ascontiguousarray(cv2.resize(base, (width, height), interpolation=cv2.INTER_LINEAR))
    scale = max(width, height)
    _shapes(rng, img, int(rng.integers(0, 12)), scale // 4, palette)  # large shapes
    _shapes(rng, img, int(rng.integers(0, 60)), max(4, scale // 25), palette)  # clutter
    if printed > 0 and rng.random() < printed:
        from kpd6d.synth.prints import paste_sheets

        paste_sheets(rng, img, int(rng.integers(1, 6)), palette)
    if rng.random() < 0.5:
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.5, 2.0))
    sigma = rng.uniform(0, 8)
    if sigma > 1:  # grain, 2x2-pixel cells (the composite may get finer noise later)
        grain = rng.normal(0, sigma, (hh, hw)).astype(np.float32)
        grain = cv2.resize(grain, (width, height), interpolation=cv2.INTER_NEAREST)
        img = cv2.add(img, cv2.merge([grain, grain, grain]), dtype=cv2.CV_8U)
    return img


class ProceduralBackgrounds(BackgroundSource):
    def __init__(self, palette: str = "uniform", printed: float = 0.0) -> None:
        self.palette = check_palette(palette)
        self.printed = to_fraction(printed, "printed_matter")

    def sample(self, rng, width, height):
        return procedural_background(rng, width, height, self.palette, self.printed)

    def __repr__(self) -> str:
        return f"ProceduralBackgrounds(palette={self.palette!r}, printed={self.printed})"


class FolderBackgrounds(BackgroundSource):
    """Images under ``folder`` (recursively; any format OpenCV reads), randomly cropped to the output
    aspect ratio, flipped and resized. Decoded images are kept in a small per-process LRU cache."""

    def __init__(self, folder: str | os.PathLike, cache_mb: float = 256.0) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise FileNotFoundError(f"backgrounds_dir {self.folder}: folder does not exist")
        self.files = sorted(
            p for p in self.folder.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
        )
        if not self.files:
            raise FileNotFoundError(
                f"backgrounds_dir {self.folder}: no image files found (extensions: {', '.join(IMAGE_EXTENSIONS)})"
            )
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self._cache_bytes, self._cache_limit = 0, int(cache_mb * 2**20)

    def _load(self, i: int) -> np.ndarray:
        img = self._cache.get(i)
        if img is not None:
            self._cache.move_to_end(i)
            return img
        import cv2

        path = self.files[i]
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None or img.size == 0:
            raise OSError(f"background image {path}: cannot be read as an image (corrupt or unsupported format)")
        img = np.ascontiguousarray(img[..., ::-1])
        self._cache[i] = img
        self._cache_bytes += img.nbytes
        while self._cache_bytes > self._cache_limit and len(self._cache) > 1:
            _, old = self._cache.popitem(last=False)
            self._cache_bytes -= old.nbytes
        return img

    def sample(self, rng, width, height):
        import cv2

        img = self._load(int(rng.integers(len(self.files))))
        h, w = img.shape[:2]
        aspect = width / height
        cw = min(w, h * aspect)
        s = rng.uniform(0.5, 1.0)
        cw = max(1.0, cw * s)
        ch = max(1.0, cw / aspect)
        x0 = rng.uniform(0, w - cw) if w > cw else 0.0
        y0 = rng.uniform(0, h - ch) if h > ch else 0.0
        crop = img[int(y0):int(y0 + ch) or 1, int(x0):int(x0 + cw) or 1]
        if rng.random() < 0.5:
            crop = crop[:, ::-1]
        interp = cv2.INTER_AREA if crop.shape[1] > width else cv2.INTER_LINEAR
        return np.ascontiguousarray(cv2.resize(np.ascontiguousarray(crop), (width, height), interpolation=interp))

    def __repr__(self) -> str:
        return f"FolderBackgrounds({str(self.folder)!r}, files={len(self.files)})"


def make_background_source(backgrounds_dir: str | os.PathLike | None, palette: str = "uniform",
                           printed: float = 0.0) -> BackgroundSource:
    """A :class:`FolderBackgrounds` for a folder, else :class:`ProceduralBackgrounds` in ``palette``
    with printed sheets on a ``printed`` share of them (a folder's images are used as they are)."""
    return FolderBackgrounds(backgrounds_dir) if backgrounds_dir else ProceduralBackgrounds(palette, printed)
