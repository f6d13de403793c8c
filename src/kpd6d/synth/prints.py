"""Printed matter for procedural scenes: sheets of paper with marker grids, text, tables or a picture,
pasted onto backgrounds and table tops (``printed_matter``), and printed cards and boxes among the
occluders.

Offices and labs are full of printouts, posters, packaging and calibration markers: sharp,
high-contrast, high-frequency patterns that smooth procedural textures never show, and what a detector
trained without them takes for objects. Everything here is made in code from random numbers (a prior
about indoor scenes, nothing measured on photographs).
"""

from __future__ import annotations

import numpy as np

from kpd6d.synth.palette import random_color

__all__ = ["SHEET_KINDS", "paste_sheets", "printed_sheet"]

SHEET_KINDS = ("markers", "text", "table", "picture")
_LETTERS = np.array(list("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789  "))


def _paper(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """A blank sheet (RGB uint8): white to light grey, slightly tinted."""
    base = rng.uniform(200.0, 250.0)
    tint = rng.uniform(-8.0, 8.0, 3)
    return np.broadcast_to(np.clip(np.rint(base + tint), 0, 255).astype(np.uint8), (h, w, 3)).copy()


def _ink(rng: np.random.Generator, palette: str) -> tuple[int, int, int]:
    """Mostly black ink, sometimes a colour."""
    if rng.random() < 0.7:
        return tuple(int(v) for v in rng.integers(0, 50, 3))
    return tuple(int(v) for v in np.rint(random_color(rng, palette)))


def _markers(rng, w, h, palette):
    """A grid of square fiducial markers: a black border around a random binary n x n code."""
    img = _paper(rng, w, h)
    n = int(rng.integers(3, 7))  # code cells per side
    cell = max(1, int(rng.uniform(0.02, 0.08) * min(w, h)))
    side = (n + 2) * cell
    gap = int(rng.uniform(0.3, 1.5) * side)
    ink = _ink(rng, palette) if rng.random() < 0.2 else (0, 0, 0)
    for y0 in range(gap // 2, h - side + 1, side + gap):
        for x0 in range(gap // 2, w - side + 1, side + gap):
            code = rng.random((n + 2, n + 2)) < 0.5
            code[0, :] = code[-1, :] = code[:, 0] = code[:, -1] = True  # the black border
            block = np.kron(code, np.ones((cell, cell), bool))
            img[y0:y0 + side, x0:x0 + side][block] = ink
    return img


def _text(rng, w, h, palette):
    """Lines of random words (Hershey fonts), now and then a heading in colour."""
    import cv2

    img = _paper(rng, w, h)
    size = rng.uniform(0.015, 0.06) * h  # cap height, px
    font = int(rng.choice([cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
                           cv2.FONT_HERSHEY_PLAIN, cv2.FONT_HERSHEY_TRIPLEX]))
    scale = size / 22.0
    thick = max(1, round(size / 12))
    ink = _ink(rng, palette)
    margin = int(0.08 * w)
    y = margin + size
    while y < h - margin:
        heading = rng.random() < 0.1
        k = int(rng.integers(8, 60))
        line = "".join(rng.choice(_LETTERS, k))
        colour = _ink(rng, palette) if heading else ink
        cv2.putText(img, line, (margin, int(y)), font, scale * (1.6 if heading else 1.0), colour,
                    thick + (1 if heading else 0), cv2.LINE_AA)
        y += size * rng.uniform(1.6, 2.4) * (1.6 if heading else 1.0)
    return img


def _table(rng, w, h, palette):
    """A ruled table or form: grid lines, some cells filled."""
    import cv2

    img = _paper(rng, w, h)
    ink = _ink(rng, palette)
    rows, cols = int(rng.integers(3, 15)), int(rng.integers(2, 8))
    xs = np.sort(rng.uniform(0.05, 0.95, cols + 1)) * w
    ys = np.linspace(0.05, 0.95, rows + 1) * h
    fill = np.rint(random_color(rng, palette)).astype(np.uint8)
    for i in range(rows):
        for j in range(cols):
            if rng.random() < 0.15:
                img[int(ys[i]):int(ys[i + 1]), int(xs[j]):int(xs[j + 1])] = fill
    thick = max(1, int(rng.integers(1, 4)))
    for x in xs:
        cv2.line(img, (int(x), int(ys[0])), (int(x), int(ys[-1])), ink, thick)
    for y in ys:
        cv2.line(img, (int(xs[0]), int(y)), (int(xs[-1]), int(y)), ink, thick)
    return img


def _picture(rng, w, h, palette):
    """A printed picture: a saturated procedural image, with or without a white margin."""
    from kpd6d.synth.backgrounds import procedural_background

    pic = procedural_background(rng, w, h, "uniform" if rng.random() < 0.5 else palette)
    if rng.random() < 0.5:
        img = _paper(rng, w, h)
        m = int(rng.uniform(0.04, 0.15) * min(w, h))
        img[m:h - m, m:w - m] = pic[m:h - m, m:w - m]
        return img
    return pic


def printed_sheet(rng: np.random.Generator, width: int, height: int, palette: str = "uniform",
                  kind: str | None = None) -> np.ndarray:
    """One printed sheet, RGB uint8 (height, width, 3): ``kind`` one of :data:`SHEET_KINDS` (None: at
    random): a grid of fiducial markers, lines of text, a ruled table, or a picture."""
    if kind is None:
        kind = SHEET_KINDS[int(rng.integers(len(SHEET_KINDS)))]
    make = {"markers": _markers, "text": _text, "table": _table, "picture": _picture}.get(kind)
    if make is None:
        raise ValueError(f"printed_sheet: unknown kind {kind!r}; known: {list(SHEET_KINDS)}")
    return make(rng, max(int(width), 4), max(int(height), 4), palette)


def paste_sheets(rng: np.random.Generator, img: np.ndarray, count: int, palette: str = "uniform",
                 size_range: tuple[float, float] = (0.12, 0.45)) -> np.ndarray:
    """Paste ``count`` printed sheets onto ``img`` (RGB uint8, in place and returned), each of a
    random kind, a side of ``size_range`` times the image's longer side, turned by a random angle, a
    little darker or lighter than printed (lying in shade or light), anywhere (partly off the image)."""
    import cv2

    H, W = img.shape[:2]
    long = max(H, W)
    for _ in range(int(count)):
        s = rng.uniform(*size_range) * long
        aspect = rng.uniform(0.6, 1.6)
        sw, sh = max(8, int(s * np.sqrt(aspect))), max(8, int(s / np.sqrt(aspect)))
        sheet = printed_sheet(rng, sw, sh, palette).astype(np.float32) * np.float32(rng.uniform(0.7, 1.05))
        angle = rng.uniform(0.0, 360.0)
        cx, cy = rng.uniform(0, W), rng.uniform(0, H)
        M = cv2.getRotationMatrix2D((sw / 2, sh / 2), angle, 1.0)
        M[:, 2] += (cx - sw / 2, cy - sh / 2)
        # only the window the turned sheet covers (a pixel of margin for the interpolation) is touched
        corners = np.array([[0, 0, 1], [sw, 0, 1], [0, sh, 1], [sw, sh, 1]], np.float64) @ M.T
        x0, y0 = np.maximum(np.floor(corners.min(0)).astype(int) - 1, 0)
        x1, y1 = np.minimum(np.ceil(corners.max(0)).astype(int) + 2, (W, H))
        if x1 <= x0 or y1 <= y0:
            continue
        Mw = M - [[0, 0, x0], [0, 0, y0]]
        size = (int(x1 - x0), int(y1 - y0))
        warped = cv2.warpAffine(sheet, Mw, size, flags=cv2.INTER_LINEAR)
        alpha = cv2.warpAffine(np.ones((sh, sw), np.float32), Mw, size, flags=cv2.INTER_LINEAR)[..., None]
        win = img[y0:y1, x0:x1]
        win[...] = np.clip(win.astype(np.float32) * (1 - alpha) + warped * alpha + 0.5, 0, 255).astype(np.uint8)
    return img
