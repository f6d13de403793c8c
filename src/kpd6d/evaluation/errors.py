"""Pose error functions (BOP conventions: mm, OpenCV camera, ``x_c = R x_m + t``).

All take ``(R_est, t_est, R_gt, t_gt, points, ...)`` with R (3,3), t (3,) in mm and model points
(N, 3) in mm (BOP uses the model's vertices), and ``K`` (3,3) where a projection is involved.
Projection and transforms come from :mod:`kpd6d.geometry`.

* ``add_error``: mean distance between corresponding transformed points (Hinterstoisser et al.).
* ``adds_error``: mean distance from each GT-posed point to the closest estimate-posed point
  (ADD-S / ADI; KD-tree), as bop_toolkit's ``pose_error.adi``.
* ``proj2d_error``: mean distance (px) between the projections of the points; with ``symmetries``
  the minimum of that mean over the object's symmetry transforms (2D projection-S: an estimate that
  equals GT up to a symmetry of the object has error 0, as under MSPD).
* ``rotation_error`` (degrees, geodesic) and ``translation_error`` (mm).
* ``mssd_error`` / ``mspd_error``: BOP19 maximum symmetry-aware surface / projection distance,
  ``min over symmetries S of max over points`` of the distance between the estimate-posed point
  and the point posed by GT composed with S (``R_gt S_R``, ``R_gt S_t + t_gt``), exactly as
  bop_toolkit's ``pose_error.mssd`` / ``mspd``; vectorised over symmetries.

A non-finite estimate (a failed PnP returns NaN R, t) has error ``inf`` under every function.
* ``symmetry_transforms``: the symmetry transform set of a models_info entry as bop_toolkit's
  ``misc.get_symmetry_transformations`` builds it (identity first).
* ``keypoint_errors``: how the KPD's 2D keypoints of one instance sit against the projections of its 3D
  keypoints at the GT pose (not a pose error: a diagnostic of the keypoint detector) - their median
  distance (px), the offset of their centroid (px) and the scale of their pattern about its centroid
  (1: the size the GT projects to; < 1: drawn in towards the middle, which PnP turns into depth).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from kpd6d.geometry import (
    compose_poses,
    project_points,
    rotation_about_axis,
    rotation_error_deg,
    transform_points,
)
from kpd6d.geometry import translation_error as _translation_distance

__all__ = [
    "BOP_MAX_SYM_DISC_STEP",
    "add_error",
    "adds_error",
    "as_symmetry_array",
    "depth_ratio",
    "keypoint_errors",
    "mspd_error",
    "mssd_error",
    "proj2d_error",
    "rotation_error",
    "symmetry_transforms",
    "translation_error",
]

#: bop_toolkit's default ``max_sym_disc_step`` (fraction of the diameter): ceil(pi / 0.01) = 315 steps.
BOP_MAX_SYM_DISC_STEP = 0.01

#: Work in chunks of about this many 3-vectors when posing points under many symmetries.
_CHUNK = 2_000_000


def _pose(R, t) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"pose must be R (3, 3) and t (3,) (or (3, 1)), got R {R.shape} and t {t.shape}")
    return R, t


def _failed(R, t) -> bool:
    """A non-finite estimate (e.g. a failed PnP's NaN pose): its errors are ``inf``."""
    return not (np.isfinite(R).all() and np.isfinite(t).all())


def _points(points) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"points must be a non-empty (N, 3) array, got shape {p.shape}")
    return p


def _K(K) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    return K


def add_error(R_est, t_est, R_gt, t_gt, points) -> float:
    """ADD (mm): mean over points of ``||(R_est x + t_est) - (R_gt x + t_gt)||``."""
    (R_e, t_e), (R_g, t_g), p = _pose(R_est, t_est), _pose(R_gt, t_gt), _points(points)
    if _failed(R_e, t_e):
        return math.inf
    d = transform_points(p, R_e, t_e) - transform_points(p, R_g, t_g)
    return float(np.linalg.norm(d, axis=-1).mean())


def adds_error(R_est, t_est, R_gt, t_gt, points) -> float:
    """ADD-S (mm): mean over GT-posed points of the distance to the closest estimate-posed point."""
    from scipy.spatial import cKDTree

    (R_e, t_e), (R_g, t_g), p = _pose(R_est, t_est), _pose(R_gt, t_gt), _points(points)
    if _failed(R_e, t_e):
        return math.inf
    pe = transform_points(p, R_e, t_e)
    dist, _ = cKDTree(pe).query(transform_points(p, R_g, t_g), k=1)
    return float(dist.mean())


def proj2d_error(R_est, t_est, R_gt, t_gt, points, K, symmetries: Sequence | np.ndarray | None = None) -> float:
    """2D projection error (px): mean over points of the distance between their two projections.

    ``symmetries`` ((S, 4, 4) including the identity, :func:`symmetry_transforms`): the minimum over S
    of that mean with GT composed with S (``min_S mean_x ||pi(R_est x + t_est) - pi(R_gt (S_R x + S_t) + t_gt)||``),
    the symmetric form for objects evaluated with ADD-S; None: the identity only (the plain error).
    """
    return float(_sym_distances(R_est, t_est, R_gt, t_gt, points, symmetries, K=_K(K), reduce="mean").min())


def rotation_error(R_est, R_gt) -> float:
    """Geodesic rotation error (degrees), ``arccos((tr(R_est^T R_gt) - 1) / 2)``; inf for a non-finite estimate."""
    if _failed(np.asarray(R_est, dtype=np.float64), 0.0):
        return math.inf
    return float(rotation_error_deg(_pose(R_est, np.zeros(3))[0], _pose(R_gt, np.zeros(3))[0]))


def translation_error(t_est, t_gt) -> float:
    """Translation error (mm), ``||t_est - t_gt||``; inf for a non-finite estimate."""
    if _failed(0.0, np.asarray(t_est, dtype=np.float64)):
        return math.inf
    return float(_translation_distance(_pose(np.eye(3), t_est)[1], _pose(np.eye(3), t_gt)[1]))


def depth_ratio(R_est, t_est, R_gt, t_gt, points) -> float:
    """Estimated over true camera depth (z) of the centroid of ``points`` (model frame); > 1: too far. The
    centroid of a symmetric object's points is fixed by its symmetries, so an estimate equal to the truth up to
    a symmetry has ratio 1. NaN for a non-finite estimate."""
    if _failed(np.asarray(R_est, dtype=np.float64), np.asarray(t_est, dtype=np.float64)):
        return math.nan
    c = _points(points).mean(axis=0)
    R, t = _pose(R_est, t_est)
    Rg, tg = _pose(R_gt, t_gt)
    return float((R[2] @ c + t[2]) / (Rg[2] @ c + tg[2]))


# ---------------------------------------------------------------------------------------------
# symmetries and the BOP19 errors
# ---------------------------------------------------------------------------------------------
def as_symmetry_array(symmetries) -> np.ndarray:
    """(S, 4, 4) float64 from a list of 4x4 matrices, 16-value rows, or ``{"R", "t"}`` dicts (bop_toolkit's form)."""
    if symmetries is None:
        return np.eye(4)[None]
    if isinstance(symmetries, np.ndarray) and symmetries.ndim == 3:
        arr = symmetries
    else:
        mats = []
        for j, s in enumerate(symmetries):
            if isinstance(s, Mapping):
                T = np.eye(4)
                T[:3, :3] = np.asarray(s["R"], dtype=np.float64).reshape(3, 3)
                T[:3, 3] = np.asarray(s["t"], dtype=np.float64).reshape(3)
            else:
                T = np.asarray(s, dtype=np.float64)
                if T.size != 16:
                    raise ValueError(f"symmetries[{j}] must be a 4x4 transform (16 values), got shape {T.shape}")
                T = T.reshape(4, 4)
            mats.append(T)
        if not mats:
            raise ValueError("symmetries is empty; pass at least the identity (symmetry_transforms() includes it)")
        arr = np.stack(mats)
    arr = np.asarray(arr, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"symmetries must be (S, 4, 4), got {arr.shape}")
    return arr


def symmetry_transforms(info: Mapping[str, Any] | Any, continuous_step_deg: float | None = None, *,
                        max_sym_disc_step: float = BOP_MAX_SYM_DISC_STEP) -> np.ndarray:
    """Symmetry transforms (S, 4, 4) (mm) of a BOP models_info entry, identity first.

    As bop_toolkit's ``misc.get_symmetry_transformations(info, max_sym_disc_step)``: the discrete
    set is the identity followed by ``symmetries_discrete``; each continuous symmetry (``axis``,
    ``offset``) is discretised into ``n`` rotations by ``i * 360/n`` degrees (i = 0..n-1) about the
    axis through ``offset`` (``t = offset - R offset``); with continuous symmetries every discrete
    transform D is combined with every continuous one C as ``C @ D`` (discrete outer loop).
    ``n = ceil(pi / max_sym_disc_step)`` (the toolkit's rule; 315 for its default 0.01) unless
    ``continuous_step_deg`` is given, then ``n = ceil(360 / continuous_step_deg)``.
    ``info`` may also be an object with an ``info()`` method (e.g. :class:`kpd6d.objects.ObjectModel`).
    """
    if not isinstance(info, Mapping) and hasattr(info, "info"):
        info = info.info()
    if not isinstance(info, Mapping):
        raise TypeError(f"symmetry_transforms: info must be a models_info entry (a mapping), got {type(info).__name__}")
    discrete = [np.eye(4)]
    for j, s in enumerate(info.get("symmetries_discrete", []) or []):
        T = np.asarray(s, dtype=np.float64)
        if T.size != 16:
            raise ValueError(f"models_info symmetries_discrete[{j}] has {T.size} values, expected 16")
        discrete.append(T.reshape(4, 4))
    continuous = []
    cont = info.get("symmetries_continuous", []) or []
    if cont:
        if continuous_step_deg is not None:
            if not continuous_step_deg > 0:
                raise ValueError(f"continuous_step_deg must be > 0, got {continuous_step_deg!r}")
            n = math.ceil(360.0 / continuous_step_deg - 1e-9)
        else:
            if not max_sym_disc_step > 0:
                raise ValueError(f"max_sym_disc_step must be > 0, got {max_sym_disc_step!r}")
            n = math.ceil(math.pi / max_sym_disc_step)
        for j, s in enumerate(cont):
            if "axis" not in s:
                raise ValueError(f"models_info symmetries_continuous[{j}] has no 'axis'")
            offset = np.asarray(s.get("offset", [0.0, 0.0, 0.0]), dtype=np.float64).reshape(3)
            for i in range(n):
                R = rotation_about_axis(s["axis"], i * 2.0 * math.pi / n)
                T = np.eye(4)
                T[:3, :3] = R
                T[:3, 3] = offset - R @ offset
                continuous.append(T)
    if not continuous:
        return np.stack(discrete)
    return np.stack([C @ D for D in discrete for C in continuous])


def _sym_distances(R_est, t_est, R_gt, t_gt, points, symmetries, K=None, reduce: str = "max") -> np.ndarray:
    """Max (``reduce="mean"``: mean) over points of the est-vs-(GT o S) distance, for every symmetry S: (S,)."""
    (R_e, t_e), (R_g, t_g), p = _pose(R_est, t_est), _pose(R_gt, t_gt), _points(points)
    S = as_symmetry_array(symmetries)
    if _failed(R_e, t_e):
        return np.full(len(S), math.inf)
    est = transform_points(p, R_e, t_e) if K is None else project_points(p, K, R_e, t_e)
    out = np.empty(len(S))
    step = max(1, _CHUNK // len(p))
    for a in range(0, len(S), step):
        Rs, ts = compose_poses(R_g, t_g, S[a : a + step, :3, :3], S[a : a + step, :3, 3])  # (s,3,3), (s,3)
        gt = transform_points(p, Rs, ts) if K is None else project_points(p, K, Rs, ts)  # (s, N, d)
        dist = np.linalg.norm(gt - est, axis=-1)
        out[a : a + step] = dist.max(axis=-1) if reduce == "max" else dist.mean(axis=-1)
    return out


def mssd_error(R_est, t_est, R_gt, t_gt, points, symmetries: Sequence | np.ndarray | None = None) -> float:
    """BOP19 MSSD (mm): ``min_S max_x ||(R_est x + t_est) - (R_gt (S_R x + S_t) + t_gt)||``.

    ``symmetries``: (S, 4, 4) transforms including the identity (see :func:`symmetry_transforms`);
    None means no symmetry (identity only).
    """
    return float(_sym_distances(R_est, t_est, R_gt, t_gt, points, symmetries).min())


def mspd_error(R_est, t_est, R_gt, t_gt, points, K, symmetries: Sequence | np.ndarray | None = None) -> float:
    """BOP19 MSPD (px): as :func:`mssd_error` with the distance between projections by ``K``."""
    return float(_sym_distances(R_est, t_est, R_gt, t_gt, points, symmetries, K=_K(K)).min())


def keypoint_errors(keypoints_2d, keypoints_3d, R_gt, t_gt, K, symmetries: Sequence | np.ndarray | None = None) -> dict:
    """``{"err_px", "centroid_px", "scale"}`` of predicted keypoints ``keypoints_2d`` (k, 2) image px against
    the projections of ``keypoints_3d`` (k, 3) mm at the GT pose: the median of the k distances, the distance
    between the two patterns' centroids, and the least-squares scale ``s`` of the predicted pattern about its
    centroid against the GT's (``argmin_s sum ||(p - p_mean) - s (g - g_mean)||^2``).

    ``symmetries`` ((S, 4, 4), :func:`symmetry_transforms`): GT composed with the symmetry whose projections
    lie nearest the prediction (smallest mean distance), as a KPD trained on canonical poses predicts them.
    Non-finite keypoints or a degenerate GT pattern (all projections in one place) give NaN values."""
    kp = np.asarray(keypoints_2d, dtype=np.float64).reshape(-1, 2)
    X = _points(keypoints_3d)
    nan = {"err_px": math.nan, "centroid_px": math.nan, "scale": math.nan}
    if len(kp) != len(X):
        raise ValueError(f"keypoint_errors: {len(kp)} 2D keypoints for {len(X)} 3D keypoints")
    if not np.isfinite(kp).all():
        return nan
    S = as_symmetry_array(symmetries)
    R_g, t_g = _pose(R_gt, t_gt)
    Rs, ts = compose_poses(R_g, t_g, S[:, :3, :3], S[:, :3, 3])
    gts = project_points(X, _K(K), Rs, ts).reshape(len(S), len(X), 2)
    d = np.linalg.norm(gts - kp[None], axis=-1)  # (S, k)
    best = int(np.argmin(d.mean(axis=1)))
    g = gts[best]
    a, b = g - g.mean(axis=0), kp - kp.mean(axis=0)
    aa = float((a * a).sum())
    if not aa > 1e-12:
        return nan
    return {"err_px": float(np.median(d[best])), "centroid_px": float(np.linalg.norm(kp.mean(0) - g.mean(0))),
            "scale": float((a * b).sum() / aa)}
