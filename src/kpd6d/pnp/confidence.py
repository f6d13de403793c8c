"""Per-pose confidence in [0, 1] from the keypoint confidences and the PnP reprojection residual.

For one instance with keypoint confidences ``c_i`` (the heatmap maxima the KPD decodes), the top-l
set ``U`` given to PnP and the PnP inliers ``I ⊆ U`` (all of ``U`` for the non-RANSAC solvers)::

    residual_px = mean over i in I of || project(K, R, t, X_i) - x_i ||          (px)
    confidence  = ( sum over i in I of clip(c_i, 0, 1) ) / |U|  *  exp(-residual_px / residual_scale_px)

i.e. the mean clipped heatmap maximum over the used keypoints, counting the ones RANSAC rejected as 0,
times a residual factor that is 1 for a perfect fit and 1/e at ``residual_scale_px`` (default
:data:`RESIDUAL_SCALE_PX` = 10 px). A pose PnP could not solve (``ok`` False), or one without any used
point, has confidence 0 and residual NaN. numpy only (the torch-free runtime uses it too).
"""

from __future__ import annotations

import numpy as np

__all__ = ["RESIDUAL_SCALE_PX", "pose_confidence", "reprojection_residuals"]

RESIDUAL_SCALE_PX = 10.0


def reprojection_residuals(points_3d, points_2d, K, R, t, mask) -> np.ndarray:
    """Mean reprojection error (N,) px over ``mask`` (N, k) of N poses ``R`` (N, 3, 3), ``t`` (N, 3)
    for ``points_3d`` (N, k, 3) mm, ``points_2d`` (N, k, 2) px, ``K`` (N, 3, 3) or (3, 3); NaN where the
    pose is not finite, no point is masked or a masked point is at z <= 0."""
    p3 = np.asarray(points_3d, dtype=np.float64)
    p2 = np.asarray(points_2d, dtype=np.float64)
    R, t, m = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64), np.asarray(mask, dtype=bool)
    N = p3.shape[0]
    Ks = np.broadcast_to(np.asarray(K, dtype=np.float64), (N, 3, 3))
    out = np.full(N, np.nan)
    for n in range(N):
        if not m[n].any() or not (np.isfinite(R[n]).all() and np.isfinite(t[n]).all()):
            continue
        cam = p3[n][m[n]] @ R[n].T + t[n]
        if (cam[:, 2] <= 0).any():
            continue
        uvw = cam @ Ks[n].T
        uv = uvw[:, :2] / uvw[:, 2:3]
        out[n] = float(np.linalg.norm(uv - p2[n][m[n]], axis=-1).mean())
    return out


def pose_confidence(confidences, used, inliers, residual_px, ok=None,
                    residual_scale_px: float = RESIDUAL_SCALE_PX) -> np.ndarray:
    """The confidence (N,) in [0, 1] of N poses (formula in the module docstring).

    ``confidences`` (N, k) keypoint confidences, ``used`` (N, k) bool the top-l keypoints, ``inliers``
    (N, k) bool the PnP inliers (only those also in ``used`` count), ``residual_px`` (N,) their mean
    reprojection error, ``ok`` (N,) bool PnP's verdict (None: all ok). 0 where not ok, where no
    keypoint is used or where the residual is not finite."""
    if not residual_scale_px > 0:
        raise ValueError(f"residual_scale_px must be > 0, got {residual_scale_px!r}")
    c = np.clip(np.nan_to_num(np.asarray(confidences, dtype=np.float64), nan=0.0), 0.0, 1.0)
    used = np.asarray(used, dtype=bool)
    inl = np.asarray(inliers, dtype=bool) & used
    res = np.asarray(residual_px, dtype=np.float64).reshape(-1)
    n_used = used.sum(-1)
    kp = np.where(n_used > 0, (c * inl).sum(-1) / np.maximum(n_used, 1), 0.0)
    with np.errstate(invalid="ignore", over="ignore"):
        factor = np.where(np.isfinite(res), np.exp(-np.maximum(np.nan_to_num(res, nan=0.0), 0.0) / residual_scale_px),
                          0.0)
    conf = kp * factor
    if ok is not None:
        conf = np.where(np.asarray(ok, dtype=bool), conf, 0.0)
    return np.clip(conf, 0.0, 1.0)
