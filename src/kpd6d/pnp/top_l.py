"""Top-l keypoint selection and PnP on the selected correspondences.

``top_l(confidences (..., k), l)`` returns the indices (..., l) of the ``l`` most confident
keypoints, most confident first (``l=None`` or ``l >= k``: all k, sorted). :func:`solve_top_l`
solves one PnP problem per instance with a ``PNP_SOLVERS`` entry on those correspondences, passing
the confidences to the solver (weighted solvers use them). torch is imported only for torch
input, so ``import kpd6d.pnp`` stays torch-free.
"""

from __future__ import annotations

import numpy as np

__all__ = ["solve_top_l", "top_l", "top_l_mask"]


def _is_torch(x) -> bool:
    return type(x).__module__.startswith("torch")


def top_l(confidences, l: int | None = None):  # noqa: E741 - the paper's name
    """Indices (..., l) of the l largest confidences along the last axis (numpy or torch, like the input)."""
    k = confidences.shape[-1]
    if l is not None and int(l) < 1:
        raise ValueError(f"top_l: l must be >= 1 or None (all), got {l}")
    n = k if l is None else min(int(l), k)
    if _is_torch(confidences):
        import torch

        return torch.topk(confidences, n, dim=-1, sorted=True).indices
    c = np.asarray(confidences)
    order = np.argsort(-c, axis=-1, kind="stable")
    return order[..., :n]


def top_l_mask(confidences, l: int | None = None):  # noqa: E741
    """Boolean mask (..., k) of the l most confident keypoints (numpy or torch, like the input)."""
    idx = top_l(confidences, l)
    if _is_torch(confidences):
        import torch

        return torch.zeros_like(confidences, dtype=torch.bool).scatter_(-1, idx, True)
    mask = np.zeros(np.shape(confidences), dtype=bool)
    np.put_along_axis(mask, idx, True, axis=-1)
    return mask


def solve_top_l(solver, keypoints_3d, keypoints_2d, K, confidences, l: int | None = None,  # noqa: E741
                weighted: bool = True):
    """One batched PnP over N instances, each on its top-l keypoints.

    ``keypoints_3d`` (N, k, 3) or (k, 3) mm, ``keypoints_2d`` (N, k, 2) image px, ``K`` (N, 3, 3) or
    (3, 3), ``confidences`` (N, k); ``solver`` a PNP_SOLVERS instance (or a config dict
    ``{"name": ..., ...}``). The unselected keypoints get confidence 0, which every solver reads as
    "not used"; the selected ones pass their confidence (``weighted``) or 1 to the solver. Returns the
    solver's ``BatchPoseEstimate`` (indexable: ``result[i]`` is instance i's ``PoseEstimate``).
    """
    from kpd6d.registry import PNP_SOLVERS, build_from_cfg

    if isinstance(solver, dict) or hasattr(solver, "keys"):
        solver = build_from_cfg(PNP_SOLVERS, solver)

    def np64(x):
        return (x.detach().cpu().numpy() if _is_torch(x) else np.asarray(x)).astype(np.float64)

    p2, c = np64(keypoints_2d), np64(confidences)
    p3, Ks = np64(keypoints_3d), np64(K)
    N = c.shape[0]
    if p3.ndim == 2:
        p3 = np.broadcast_to(p3, (N, *p3.shape))
    if Ks.ndim == 2:
        Ks = np.broadcast_to(Ks, (N, 3, 3))
    used = top_l_mask(c, l)
    weights = np.where(used, np.maximum(c, 1e-6) if weighted else 1.0, 0.0)
    return solver.solve_batch(np.ascontiguousarray(p3), p2, np.ascontiguousarray(Ks), weights)


def pose_records(est, boxes, image_hw, img_idx, obj_ids, scores, keypoints_2d, confidences, used, out, *,
                 points_3d, K, min_confidence: float = 0.0, residual_scale_px: float | None = None,
                 depth_calibration: np.ndarray | None = None) -> None:
    """Append one pose dict per instance to ``out[image]`` (the pipelines' output records): ``obj_id``,
    ``R``, ``t``, ``score``, ``keypoints_2d``, ``confidences``, ``used``, ``box``, ``ok``, ``reason``,
    ``confidence`` and ``residual_px`` from the batched PnP result ``est``.

    ``points_3d`` (N, k, 3) and ``K`` (N, 3, 3) are the instances' 3D keypoints and cameras:
    ``residual_px`` is the mean reprojection error of the PnP inliers among the used keypoints and
    ``confidence`` the pose confidence of :mod:`kpd6d.pnp.confidence` (``residual_scale_px``, None:
    its default). ``ok`` = PnP ok and ``confidence >= min_confidence``; a pose failing only the
    confidence gate gets NaN R, t too, with the reason. A degenerate detector box
    (:func:`kpd6d.geometry.box_problem` in an image of ``image_hw`` = (H, W)) never gives an ok pose:
    its R, t become NaN with the reason. ``depth_calibration`` (N,) multiplies each reported translation
    (a depth calibration); the residual and the confidence are those of the PnP pose itself."""
    from kpd6d.geometry import box_problem
    from kpd6d.pnp.confidence import RESIDUAL_SCALE_PX, pose_confidence, reprojection_residuals

    R, t, ok = np.array(est.R, dtype=np.float64), np.array(est.t, dtype=np.float64), np.array(est.ok, dtype=bool)
    reasons = list(est.reasons)
    H, W = int(image_hw[0]), int(image_hw[1])
    for n, box in enumerate(boxes):
        why = box_problem(box, W, H)
        if why:
            R[n], t[n], ok[n], reasons[n] = np.nan, np.nan, False, why
    used = np.asarray(used, dtype=bool)
    inliers = np.asarray(est.inliers, dtype=bool) & used
    residual = reprojection_residuals(points_3d, keypoints_2d, K, R, t, inliers)
    conf = pose_confidence(confidences, used, inliers, residual, ok,
                           RESIDUAL_SCALE_PX if residual_scale_px is None else float(residual_scale_px))
    for n in range(len(boxes)):
        if ok[n] and not conf[n] >= min_confidence:
            R[n], t[n], ok[n] = np.nan, np.nan, False
            reasons[n] = f"pose confidence {conf[n]:.3g} is below min_confidence={min_confidence:g}"
    if depth_calibration is not None:
        t = t * np.asarray(depth_calibration, dtype=np.float64).reshape(-1, 1)
    for n, b in enumerate(img_idx):
        out[b].append({
            "obj_id": obj_ids[n], "R": R[n], "t": t[n], "score": scores[n],
            "keypoints_2d": keypoints_2d[n], "confidences": confidences[n], "used": used[n],
            "box": np.asarray(boxes[n]), "ok": bool(ok[n]), "reason": reasons[n],
            "confidence": float(conf[n]), "residual_px": float(residual[n]),
        })
