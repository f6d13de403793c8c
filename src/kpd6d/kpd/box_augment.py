"""Box augmentation for KPD training crops: ``jitter`` (default) and ``pgpg``.

Both take a box (x, y, w, h) in pixels and a ``numpy.random.Generator`` and return a perturbed box.

* ``jitter`` — centre shift ``U(−shift, shift)`` × (w, h) and size factors ``exp(U(−log(1+scale), log(1+scale)))``.
* ``pgpg`` — RMPE's pose-guided proposal generator: offsets drawn from the empirical distribution of
  a detector's box errors relative to ground truth, fitted on a validation set with
  :func:`fit_box_error_stats` and saved by the detector stage with :func:`save_box_error_stats`.

Box-error stats format (JSON, see docs/kpd.md): a normalised offset of a predicted box ``p`` from
its ground-truth box ``g`` (centres ``c = (x + w/2, y + h/2)``) is
``(dx, dy, dw, dh) = ((c_p.x − c_g.x)/w_g, (c_p.y − c_g.y)/h_g, log(w_p/w_g), log(h_p/h_g))``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "BOX_AUGMENTS",
    "STATS_FORMAT",
    "BoxErrorStatsError",
    "BoxJitter",
    "BoxPGPG",
    "apply_offsets",
    "box_offsets",
    "build_box_augment",
    "fit_box_error_stats",
    "jitter",
    "load_box_error_stats",
    "pgpg",
    "save_box_error_stats",
]

STATS_FORMAT = "kpd6d-box-error-stats"
STATS_VERSION = 1


class BoxErrorStatsError(ValueError):
    """A box-error stats file or dict that cannot be used; the message names the file / field."""


def box_offsets(gt_boxes, pred_boxes) -> np.ndarray:
    """Normalised offsets (N, 4) ``(dx/w, dy/h, log(w'/w), log(h'/h))`` of predicted from GT boxes (xywh)."""
    g = np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 4)
    p = np.asarray(pred_boxes, dtype=np.float64).reshape(-1, 4)
    if g.shape != p.shape:
        raise ValueError(f"box_offsets: gt_boxes {g.shape} and pred_boxes {p.shape} differ in shape")
    if (g[:, 2:] <= 0).any() or (p[:, 2:] <= 0).any():
        raise ValueError("box_offsets: every box needs a positive width and height")
    gc = g[:, :2] + g[:, 2:] / 2
    pc = p[:, :2] + p[:, 2:] / 2
    return np.concatenate([(pc - gc) / g[:, 2:], np.log(p[:, 2:] / g[:, 2:])], axis=1)


def apply_offsets(box, offset) -> np.ndarray:
    """Inverse of :func:`box_offsets`: the box (4,) whose offset from ``box`` is ``offset`` (4,)."""
    b = np.asarray(box, dtype=np.float64)
    o = np.asarray(offset, dtype=np.float64)
    c = b[:2] + b[2:] / 2 + o[:2] * b[2:]
    wh = b[2:] * np.exp(o[2:])
    return np.concatenate([c - wh / 2, wh])


def fit_box_error_stats(gt_boxes, pred_boxes, obj_ids: Sequence[int] | None = None,
                        max_samples: int = 100_000) -> dict:
    """The empirical box-error distribution of a detector: matched GT / predicted boxes (N, 4) xywh.

    Returns the stats dict of the documented format (``offsets`` (N, 4), ``mean``, ``std``,
    ``num_samples`` and, with ``obj_ids``, ``per_object`` offsets). Save it with
    :func:`save_box_error_stats`.
    """
    off = box_offsets(gt_boxes, pred_boxes)
    if len(off) == 0:
        raise ValueError("fit_box_error_stats: no matched boxes")
    keep = np.arange(len(off))
    if len(off) > max_samples:
        keep = np.random.default_rng(0).choice(len(off), max_samples, replace=False)
    stats: dict[str, Any] = {
        "format": STATS_FORMAT,
        "version": STATS_VERSION,
        "fields": ["dx_over_w", "dy_over_h", "log_w_ratio", "log_h_ratio"],
        "num_samples": len(off),
        "mean": off.mean(0).tolist(),
        "std": off.std(0).tolist(),
        "offsets": off[keep].tolist(),
    }
    if obj_ids is not None:
        ids = np.asarray(obj_ids).reshape(-1)
        if len(ids) != len(off):
            raise ValueError(f"fit_box_error_stats: {len(ids)} obj_ids for {len(off)} boxes")
        stats["per_object"] = {str(int(o)): off[keep][ids[keep] == o].tolist() for o in np.unique(ids)}
    return stats


def _validate(stats: Any, where: str) -> dict:
    if not isinstance(stats, Mapping):
        raise BoxErrorStatsError(f"{where}: box-error stats must be a JSON object, got {type(stats).__name__}")
    if stats.get("format") != STATS_FORMAT:
        raise BoxErrorStatsError(f"{where}: field 'format' must be {STATS_FORMAT!r}, got {stats.get('format')!r}")
    off = np.asarray(stats.get("offsets", []), dtype=np.float64)
    if off.ndim != 2 or off.shape[1] != 4 or len(off) == 0:
        raise BoxErrorStatsError(f"{where}: field 'offsets' must be a non-empty (N, 4) list, got shape {off.shape}")
    if not np.isfinite(off).all():
        raise BoxErrorStatsError(f"{where}: field 'offsets' holds non-finite values")
    out = dict(stats)
    out["offsets"] = off
    per = stats.get("per_object") or {}
    out["per_object"] = {int(k): np.asarray(v, dtype=np.float64).reshape(-1, 4) for k, v in per.items()}
    return out


def save_box_error_stats(path: str | os.PathLike, stats: Mapping) -> Path:
    """Write ``stats`` as JSON atomically (temp file + os.replace)."""
    _validate({**stats}, str(path))
    p = Path(path)
    plain = {k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v) for k, v in stats.items()}
    if "per_object" in plain:
        plain["per_object"] = {str(k): np.asarray(v).tolist() for k, v in plain["per_object"].items()}
    from kpd6d.data import atomic_write_text

    atomic_write_text(p, json.dumps(plain))
    return p


def load_box_error_stats(path: str | os.PathLike) -> dict:
    """Read and validate a stats file; ``offsets`` come back as a numpy array (N, 4)."""
    from kpd6d.data import read_json

    p = Path(path)
    data = read_json(p, what="box-error stats file (written by the detector stage)", error=BoxErrorStatsError)
    return _validate(data, str(p))


class BoxJitter:
    """Scale and shift noise (the default box augmentation)."""

    def __init__(self, shift: float = 0.1, scale: float = 0.1) -> None:
        if shift < 0 or scale < 0:
            raise ValueError(f"jitter: shift and scale must be >= 0, got shift={shift}, scale={scale}")
        self.shift, self.scale = float(shift), float(scale)

    def __call__(self, box, rng: np.random.Generator, obj_id: int | None = None) -> np.ndarray:
        ls = np.log1p(self.scale)
        off = np.concatenate([rng.uniform(-self.shift, self.shift, 2), rng.uniform(-ls, ls, 2)])
        return apply_offsets(box, off)


class BoxPGPG:
    """Offsets resampled from a detector's empirical box errors (per object when the stats have it)."""

    def __init__(self, stats: str | os.PathLike | Mapping, per_object: bool = True, min_per_object: int = 20) -> None:
        self.stats = load_box_error_stats(stats) if isinstance(stats, (str, os.PathLike)) else _validate(stats, "pgpg stats")
        self.per_object = per_object
        self.min_per_object = int(min_per_object)

    def __call__(self, box, rng: np.random.Generator, obj_id: int | None = None) -> np.ndarray:
        pool = self.stats["offsets"]
        if self.per_object and obj_id is not None:
            own = self.stats["per_object"].get(int(obj_id))
            if own is not None and len(own) >= self.min_per_object:
                pool = own
        return apply_offsets(box, pool[rng.integers(len(pool))])


def jitter(shift: float = 0.1, scale: float = 0.1) -> BoxJitter:
    return BoxJitter(shift=shift, scale=scale)


def pgpg(stats: str | os.PathLike | Mapping, per_object: bool = True, min_per_object: int = 20) -> BoxPGPG:
    return BoxPGPG(stats, per_object=per_object, min_per_object=min_per_object)


def _none():
    return None


BOX_AUGMENTS = {"jitter": jitter, "pgpg": pgpg, "none": _none}


def build_box_augment(cfg: Mapping | None):
    """``{"name": "jitter"|"pgpg"|"none", ...params}`` → a box augmenter (or None)."""
    if cfg is None:
        return None
    params = dict(cfg)
    name = params.pop("name", None)
    if name not in BOX_AUGMENTS:
        raise ValueError(f"unknown box augmentation {name!r}; known: {', '.join(sorted(BOX_AUGMENTS))}")
    return BOX_AUGMENTS[name](**params)
