"""Box-error statistics: how a detector's boxes deviate from ground truth, and their file format.

The detector stage measures them on its validation set (:mod:`kpd6d.detection.box_stats` matches
boxes and calls :func:`fit_box_error_stats`; the run writes ``box_stats.json`` with
:func:`save_box_error_stats`); the KPD's ``pgpg`` box augmentation (:mod:`kpd6d.kpd.box_augment`)
reads them with :func:`load_box_error_stats` and samples offsets from them. This module is the
contract between the two stages, below both, so neither stage package imports the other.

Format (JSON, see docs/kpd.md): a normalised offset of a predicted box ``p`` from its ground-truth
box ``g`` (xywh, centres ``c = (x + w/2, y + h/2)``) is
``(dx, dy, dw, dh) = ((c_p.x − c_g.x)/w_g, (c_p.y − c_g.y)/h_g, log(w_p/w_g), log(h_p/h_g))``;
the file holds ``format``, ``version``, ``fields``, ``num_samples``, ``mean``, ``std``, ``offsets``
(N, 4) and optionally ``per_object`` offsets, ``iou_threshold`` and ``recall``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kpd6d.io import atomic_write_text, read_json

__all__ = [
    "STATS_FORMAT",
    "STATS_VERSION",
    "BoxErrorStatsError",
    "apply_offsets",
    "box_offsets",
    "fit_box_error_stats",
    "load_box_error_stats",
    "save_box_error_stats",
    "validate_box_error_stats",
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


def validate_box_error_stats(stats: Any, where: str) -> dict:
    """Check a stats dict (as read from JSON); ``offsets`` / ``per_object`` come back as numpy arrays."""
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
    validate_box_error_stats({**stats}, str(path))
    p = Path(path)
    plain = {k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v) for k, v in stats.items()}
    if "per_object" in plain:
        plain["per_object"] = {str(k): np.asarray(v).tolist() for k, v in plain["per_object"].items()}
    atomic_write_text(p, json.dumps(plain))
    return p


def load_box_error_stats(path: str | os.PathLike) -> dict:
    """Read and validate a stats file; ``offsets`` come back as a numpy array (N, 4)."""
    p = Path(path)
    data = read_json(p, what="box-error stats file (written by the detector stage)", error=BoxErrorStatsError)
    return validate_box_error_stats(data, str(p))
