"""numpy image operations of the torch-free runtime, each written to give what its torch / kornia
counterpart gives (within float32 rounding; the parity tests in tests/test_deploy.py compare them):

* :func:`warp_affine_bilinear` — kornia ``warp_affine(..., align_corners=True)`` (bilinear, zeros
  outside): the KPD's inference crops (:func:`kpd6d.kpd.crops.inference_crops`);
* :func:`resize_bilinear_antialias` — ``F.interpolate(mode="bilinear", align_corners=False,
  antialias=True)``: the detectors' resize to their input size (``Detector.network_images``);
* :func:`decode_centernet` — :func:`kpd6d.detection.centernet.decode_centernet` (3x3 peaks, top-k);
* :func:`postprocess_detections` — ``Detector.postprocess`` (score threshold, one per object,
  ``max_detections``) and :func:`oracle_detections` — the ``oracle`` detector without jitter.

Imports numpy only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["NumpyDetections", "decode_centernet", "oracle_detections", "postprocess_detections",
           "resize_bilinear_antialias", "warp_affine_bilinear"]


@dataclass
class NumpyDetections:
    """One image's detections, as :class:`kpd6d.detection.Detections` but numpy: ``boxes`` (N, 4)
    xywh px float32, ``obj_ids`` (N,) int64, ``scores`` (N,) float32, by descending score."""

    boxes: np.ndarray
    obj_ids: np.ndarray
    scores: np.ndarray

    def __len__(self) -> int:
        return int(self.scores.shape[0])


def warp_affine_bilinear(image: np.ndarray, A: np.ndarray, size: int | tuple[int, int]) -> np.ndarray:
    """Crops of one image (H, W, C) float32 with image → crop affines ``A`` (N, 2, 3) → (N, C, h, w).

    Crop pixel (u, v) samples the image at ``A⁻¹ (u, v, 1)`` (pixel centres at integers), bilinearly;
    neighbours outside the image count as 0 (kornia ``warp_affine`` with ``align_corners=True``).
    """
    w, h = (size, size) if isinstance(size, int) else size
    H, W = image.shape[:2]
    A = np.asarray(A, dtype=np.float64).reshape(-1, 2, 3)
    M = np.concatenate([A, np.broadcast_to([0.0, 0.0, 1.0], (len(A), 1, 3))], axis=1)
    Minv = np.linalg.inv(M)[:, :2]  # (N, 2, 3) crop -> image
    if not np.any(Minv[:, 0, 1]) and not np.any(Minv[:, 1, 0]):  # scale + shift (the codec's crops): separable
        out = np.empty((len(A), image.shape[2], h, w), dtype=np.float32)
        for n in range(len(A)):
            out[n] = _warp_separable(image, Minv[n], w, h)
        return out
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    sx = Minv[:, 0, 0, None, None] * u + Minv[:, 0, 1, None, None] * v + Minv[:, 0, 2, None, None]
    sy = Minv[:, 1, 0, None, None] * u + Minv[:, 1, 1, None, None] * v + Minv[:, 1, 2, None, None]
    x0, y0 = np.floor(sx), np.floor(sy)
    fx, fy = (sx - x0).astype(np.float32), (sy - y0).astype(np.float32)
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    out = np.zeros((len(A), h, w, image.shape[2]), dtype=np.float32)
    for dy, wy in ((0, 1.0 - fy), (1, fy)):
        for dx, wx in ((0, 1.0 - fx), (1, fx)):
            xi, yi = x0 + dx, y0 + dy
            inside = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
            vals = image[np.clip(yi, 0, H - 1), np.clip(xi, 0, W - 1)]  # (N, h, w, C)
            out += (wy * wx * inside)[..., None] * vals
    return np.ascontiguousarray(out.transpose(0, 3, 1, 2))


def _linear_taps(a: float, b: float, n_out: int, n_in: int):
    """Bilinear taps along one axis for output pixels ``i`` sampling input ``a * i + b``: the two
    input indices (clipped) and their weights (0 for a neighbour outside ``[0, n_in)``)."""
    src = a * np.arange(n_out, dtype=np.float64) + b
    i0 = np.floor(src)
    f = (src - i0).astype(np.float32)
    i0 = i0.astype(np.int64)
    i1 = i0 + 1
    w0 = (np.float32(1.0) - f) * ((i0 >= 0) & (i0 < n_in))
    w1 = f * ((i1 >= 0) & (i1 < n_in))
    return np.clip(i0, 0, n_in - 1), np.clip(i1, 0, n_in - 1), w0.astype(np.float32), w1.astype(np.float32)


def _warp_separable(image: np.ndarray, minv: np.ndarray, w: int, h: int) -> np.ndarray:
    """One crop (C, h, w) for an axis-aligned crop → image map ``minv`` (2, 3): rows, then columns.
    The same taps and weights as the general path (the product of the two axes' weights)."""
    x0, x1, wx0, wx1 = _linear_taps(minv[0, 0], minv[0, 2], w, image.shape[1])
    y0, y1, wy0, wy1 = _linear_taps(minv[1, 1], minv[1, 2], h, image.shape[0])
    c_lo, c_hi = int(min(x0.min(), x1.min())), int(max(x0.max(), x1.max())) + 1
    band = image[:, c_lo:c_hi]  # only the columns the crop reads
    rows = band[y0] * wy0[:, None, None] + band[y1] * wy1[:, None, None]  # (h, cols, C)
    out = rows[:, x0 - c_lo] * wx0[None, :, None] + rows[:, x1 - c_lo] * wx1[None, :, None]  # (h, w, C)
    return out.transpose(2, 0, 1)


def _aa_taps(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray]:
    """PyTorch's antialiased bilinear taps (``_compute_indices_min_size_weights_aa``): indices
    (n_out, T) and normalised triangle weights (n_out, T) (weight 0 on unused taps)."""
    scale = n_in / n_out
    support = scale if scale >= 1.0 else 1.0
    invscale = 1.0 / scale if scale >= 1.0 else 1.0
    centers = scale * (np.arange(n_out) + 0.5)
    xmin = np.maximum((centers - support + 0.5).astype(np.int64), 0)  # C++ truncation toward zero
    xmax = np.minimum((centers + support + 0.5).astype(np.int64), n_in)
    T = int((xmax - xmin).max())
    j = np.arange(T)
    idx = xmin[:, None] + j
    wts = np.clip(1.0 - np.abs((idx - centers[:, None] + 0.5) * invscale), 0.0, None)
    wts = np.where(idx < xmax[:, None], wts, 0.0)
    total = wts.sum(1, keepdims=True)
    wts = np.where(total > 0, wts / np.where(total > 0, total, 1.0), 0.0)
    return np.minimum(idx, n_in - 1), wts.astype(np.float32)


def resize_bilinear_antialias(images: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(B, C, H, W) float32 → (B, C, h, w) for ``size`` = (w, h): PyTorch's bilinear
    ``align_corners=False, antialias=True`` interpolation (separable; width first)."""
    w, h = int(size[0]), int(size[1])
    H, W = images.shape[-2:]
    if (W, H) == (w, h):
        return images
    ix, wx = _aa_taps(W, w)
    iy, wy = _aa_taps(H, h)
    tmp = np.einsum("bchwt,wt->bchw", images[..., ix], wx, optimize=True)  # (B, C, H, w)
    return np.ascontiguousarray(np.einsum("bchtw,ht->bchw", tmp[:, :, iy, :], wy, optimize=True), dtype=np.float32)


def decode_centernet(heat: np.ndarray, wh: np.ndarray, offset: np.ndarray, stride: int, k: int = 100):
    """numpy :func:`kpd6d.detection.centernet.decode_centernet`: peaks of ``heat`` (B, C, h, w)
    (probabilities; a peak equals the max of its 3x3 neighbourhood) → top-``k`` ``boxes`` (B, k, 4)
    xywh network px, ``labels`` (B, k), ``scores`` (B, k), by descending score."""
    B, C, h, w = heat.shape
    padded = np.pad(heat, ((0, 0), (0, 0), (1, 1), (1, 1)), constant_values=-np.inf)
    hmax = heat.copy()
    for dy in range(3):
        for dx in range(3):
            np.maximum(hmax, padded[:, :, dy:dy + h, dx:dx + w], out=hmax)
    peaks = (heat * (hmax == heat)).reshape(B, -1)
    k = min(int(k), C * h * w)
    idx = np.argsort(-peaks, axis=1, kind="stable")[:, :k]
    scores = np.take_along_axis(peaks, idx, 1)
    labels = idx // (h * w)
    cell = idx % (h * w)
    cy, cx = cell // w, cell % w
    off = np.take_along_axis(offset.reshape(B, 2, h * w), cell[:, None, :].repeat(2, 1), 2)
    size = np.take_along_axis(wh.reshape(B, 2, h * w), cell[:, None, :].repeat(2, 1), 2)
    ctr_x = (cx.astype(np.float32) + off[:, 0]) * stride
    ctr_y = (cy.astype(np.float32) + off[:, 1]) * stride
    bw, bh = size[:, 0] * stride, size[:, 1] * stride
    boxes = np.stack([ctr_x - bw / 2, ctr_y - bh / 2, bw, bh], axis=-1).astype(np.float32)
    return boxes, labels, scores.astype(np.float32)


def postprocess_detections(boxes: np.ndarray, labels: np.ndarray, scores: np.ndarray, obj_ids: Sequence[int],
                           score_threshold: float, max_detections: int, one_per_object: bool) -> list[NumpyDetections]:
    """``Detector.postprocess`` in numpy: padded score-sorted (B, K, ...) outputs → one
    :class:`NumpyDetections` per image (class index i is object id ``obj_ids[i]``)."""
    valid = (scores >= score_threshold) & (scores > 0)
    if one_per_object and labels.shape[1]:
        K = labels.shape[1]
        for b in range(labels.shape[0]):  # first valid entry of each class (rows are score-sorted)
            lab = np.where(valid[b], labels[b], -1)
            _, first = np.unique(lab, return_index=True)
            keep = np.zeros(K, dtype=bool)
            keep[first] = True
            valid[b] &= keep
    valid &= np.cumsum(valid, axis=1) <= int(max_detections)
    table = np.asarray(list(obj_ids), dtype=np.int64)
    ids = table[np.clip(labels, 0, None)] if len(table) else labels.astype(np.int64)
    return [NumpyDetections(boxes[b][valid[b]].astype(np.float32), ids[b][valid[b]].astype(np.int64),
                            scores[b][valid[b]].astype(np.float32)) for b in range(boxes.shape[0])]


def oracle_detections(targets: Sequence[dict], obj_ids: Sequence[int] | None = None,
                      max_detections: int = 100) -> list[NumpyDetections]:
    """The ``oracle`` detector (GT boxes from ``targets``; no jitter) in numpy: ``targets[b]`` holds
    ``boxes`` (n, 4) xywh, ``obj_ids`` (n,) and optional ``scores`` (n,) (default 1)."""
    if targets is None:
        raise ValueError("oracle detector needs targets: a list (one per image) of dicts with 'boxes' (n, 4) "
                         "xywh and 'obj_ids' (n,)")
    out = []
    for i, t in enumerate(targets):
        if not isinstance(t, dict) or "boxes" not in t or "obj_ids" not in t:
            raise ValueError(f"oracle: targets[{i}] must be a dict with 'boxes' and 'obj_ids'")
        boxes = np.asarray(t["boxes"], dtype=np.float32).reshape(-1, 4)
        ids = np.asarray(t["obj_ids"], dtype=np.int64).reshape(-1)
        scores = (np.asarray(t["scores"], dtype=np.float32).reshape(-1) if "scores" in t
                  else np.ones(len(ids), dtype=np.float32))
        if obj_ids is not None:
            keep = np.isin(ids, np.asarray(list(obj_ids), dtype=np.int64))
            boxes, ids, scores = boxes[keep], ids[keep], scores[keep]
        order = np.argsort(-scores, kind="stable")[: int(max_detections)]
        out.append(NumpyDetections(boxes[order], ids[order], scores[order]))
    return out
