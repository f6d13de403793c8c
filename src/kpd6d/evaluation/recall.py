"""Recall at thresholds, area under the accuracy–threshold curve, and the usual pose accuracies.

An estimate counts as correct at threshold θ when its error is strictly below θ (``e < θ``, as in
BOP and the ADD "< 0.1 d" criterion). Non-finite errors (failed or missing estimates: NaN, inf)
are never correct.
"""

from __future__ import annotations

import numpy as np

__all__ = ["add_s_accuracy", "auc", "proj2d_accuracy", "recall_at"]


def _errors(errors) -> np.ndarray:
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    if (e[np.isfinite(e)] < 0).any():
        raise ValueError(f"errors must be >= 0 (NaN/inf mark failures), got min {float(np.nanmin(e))}")
    return e


def recall_at(errors, thresholds) -> np.ndarray | float:
    """Fraction of ``errors`` strictly below each threshold.

    ``thresholds`` scalar -> float; sequence -> array of the same length. An empty ``errors``
    gives 0. NaN/inf errors count as incorrect (they stay in the denominator).
    """
    e = _errors(errors)
    th = np.asarray(thresholds, dtype=np.float64)
    if len(e) == 0:
        out = np.zeros(th.shape)
    else:
        ok = np.where(np.isfinite(e), e, np.inf)
        out = (ok[None, :] < th.reshape(-1)[:, None]).mean(axis=1).reshape(th.shape)
    return float(out) if out.ndim == 0 else out


def auc(errors, max_threshold: float, *, normalized: bool = True) -> float:
    """Area under the accuracy–threshold curve ``acc(θ) = recall_at(errors, θ)`` for θ in [0, max_threshold].

    Integration rule: exact. ``acc`` is a step function, so the area is
    ``mean_i max(0, max_threshold - e_i)`` (each estimate contributes the length of the threshold
    interval (e_i, max_threshold] where it is correct); failed (non-finite) estimates contribute 0.
    With ``normalized`` (default) the area is divided by ``max_threshold``, giving a value in
    [0, 1] (the YCB-Video "AUC of ADD(-S)" with max_threshold = 100 mm, as the exact limit of its
    VOC-style integration).
    """
    if not max_threshold > 0:
        raise ValueError(f"auc: max_threshold must be > 0, got {max_threshold!r}")
    e = _errors(errors)
    if len(e) == 0:
        return 0.0
    contrib = np.where(np.isfinite(e), np.clip(max_threshold - e, 0.0, None), 0.0)
    area = float(contrib.mean())
    return area / max_threshold if normalized else area


def add_s_accuracy(errors, diameters, fraction: float = 0.1) -> float:
    """ADD(-S) accuracy: fraction of estimates whose (ADD or ADD-S) error is below ``fraction`` × diameter.

    ``diameters``: one per error, or a scalar for all (mm).
    """
    e = _errors(errors)
    d = np.broadcast_to(np.asarray(diameters, dtype=np.float64), e.shape)
    if not (np.isfinite(d) & (d > 0)).all():
        raise ValueError("add_s_accuracy: diameters must be finite and > 0")
    if len(e) == 0:
        return 0.0
    return float((np.where(np.isfinite(e), e, np.inf) < fraction * d).mean())


def proj2d_accuracy(errors, threshold_px: float = 5.0) -> float:
    """2D projection accuracy: fraction of ``proj2d_error`` values below ``threshold_px`` (5 px)."""
    return float(recall_at(errors, threshold_px))
