"""The KPD stage's validation metrics (logged by :class:`kpd6d.kpd.module.KPDModule` as ``val/...``).

* :func:`keypoint_error_px` — mean distance (image px) between decoded crop keypoints mapped back to
  the image and the GT projections.
* :func:`pose_metrics` — from one PnP result per instance (the top-l PnP the KPD's
  ``pose_metrics`` runs on its decoded keypoints): the 2-D projection accuracy at 5 px, the ADD(-S)
  accuracy at 0.1 × diameter and the PnP failure rate (a failed PnP counts as a miss for both).

Only geometry and the error functions of :mod:`kpd6d.evaluation.errors`: no model, no solver.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from kpd6d.evaluation.errors import add_error, adds_error, proj2d_error

__all__ = ["keypoint_error_px", "pose_metrics"]


def keypoint_error_px(kp_crop, affine, keypoints_image):
    """Mean image-px error of keypoints (B, k, 2) in crop px, mapped to the image with the inverse of
    the image → crop ``affine`` (B, 2, 3), against ``keypoints_image`` (B, k, 2); float64 tensors in,
    a float64 scalar tensor out (also returns the mapped keypoints: ``(error, kp_image)``)."""
    from kpd6d.geometry import affine_apply, invert_affine

    kp_img = affine_apply(invert_affine(affine.double()), kp_crop.double())
    return (kp_img - keypoints_image.double()).norm(dim=-1).mean(), kp_img


def pose_metrics(poses, R_gt, t_gt, K, surface_points: Sequence, symmetric: Sequence[bool],
                 diameters: Sequence[float], symmetries: Sequence | None = None) -> dict[str, float]:
    """``proj2d_acc_5px``, ``add_acc_0.1d`` and ``pnp_fail_rate`` over N instances.

    ``poses`` is indexable per instance (``.ok``, ``.R``, ``.t``: a ``BatchPoseEstimate``);
    ``R_gt`` (N, 3, 3), ``t_gt`` (N, 3) mm, ``K`` (N, 3, 3) numpy; ``surface_points`` (N of (P, 3) mm),
    ``symmetric`` and ``diameters`` (mm) per instance (ADD-S for symmetric objects, else ADD);
    ``symmetries``: per instance (S, 4, 4) symmetry transforms or None — the 2D projection error is then
    the minimum over them (as the evaluation's, :func:`kpd6d.evaluation.errors.proj2d_error`).
    """
    hit2d, hitadd, fail = [], [], []
    for j in range(len(poses)):
        est = poses[j]
        if not est.ok:
            hit2d.append(0.0)
            hitadd.append(0.0)
            fail.append(1.0)
            continue
        pts = np.asarray(surface_points[j], dtype=np.float64)
        Re, te = np.asarray(est.R, dtype=np.float64), np.asarray(est.t, dtype=np.float64)
        e2d = proj2d_error(Re, te, R_gt[j], t_gt[j], pts, K[j], symmetries[j] if symmetries is not None else None)
        ead = (adds_error if symmetric[j] else add_error)(Re, te, R_gt[j], t_gt[j], pts)
        hit2d.append(float(e2d < 5.0))
        hitadd.append(float(ead < 0.1 * diameters[j]))
        fail.append(0.0)
    return {"proj2d_acc_5px": float(np.mean(hit2d)), "add_acc_0.1d": float(np.mean(hitadd)),
            "pnp_fail_rate": float(np.mean(fail))}
