"""Checks shared by every PnP solver: which inputs are degenerate, which solutions are usable.

Both functions are vectorised over a batch of B problems (numpy, CPU) and return one reason
string per problem ("" when fine). The solvers call :func:`diagnose_inputs` before solving (so
OpenCV never sees input it would assert on) and :func:`diagnose_solutions` after (so nothing
non-finite, improper or behind the camera is marked ok).
"""

from __future__ import annotations

import numpy as np

from kpd6d.geometry import project_points, transform_points

__all__ = ["COLLINEAR_RTOL", "MAX_RELATIVE_RESIDUAL", "RESIDUAL_FLOOR_PX", "diagnose_inputs", "diagnose_solutions"]

#: A point set is collinear when its second principal spread is below this fraction of its first.
COLLINEAR_RTOL = 1e-6

#: Default validity gate of every solver: a solution is ok only when the median reprojection error
#: of the points it was fitted to is at most this fraction of the object's projected size (the
#: diagonal of the 2D box of those points: the smaller of the observed box and the box of their
#: projections with the solution). Measured on synthetic 20-point problems (200 mm objects at
#: 0.4-1.5 m, LineMod K): correct poses under 2 px noise and 10 % outliers give ratios <= 0.10,
#: poses fitted to uniformly random 2D points >= 0.32 (see docs/pnp.md).
MAX_RELATIVE_RESIDUAL = 0.2

#: The gate never asks for a median error below this many px (tiny, far objects under pixel noise).
RESIDUAL_FLOOR_PX = 4.0


def _spreads(points: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Principal standard deviations (B, D), largest first, of the used points, and their scale (B,)."""
    w = use.astype(np.float64)
    n = np.maximum(w.sum(-1), 1.0)
    p = np.where(use[..., None], points, 0.0)
    mean = (p * w[..., None]).sum(-2) / n[:, None]
    d = (p - mean[:, None, :]) * w[..., None]
    cov = d.swapaxes(-1, -2) @ d / n[:, None, None]
    ev = np.linalg.eigvalsh(cov)[:, ::-1]
    scale = np.abs(p).max(axis=(-1, -2))
    return np.sqrt(np.clip(ev, 0.0, None)), scale


def diagnose_inputs(
    points_3d: np.ndarray,
    points_2d: np.ndarray,
    K: np.ndarray,
    confidences: np.ndarray | None,
    *,
    method: str,
    min_points: int,
    coplanar_rtol: float | None = None,
) -> tuple[np.ndarray, list[str]]:
    """Points each problem may use (confidence > 0) and why a problem cannot be solved.

    Shapes: points_3d (B, N, 3), points_2d (B, N, 2), K (B, 3, 3), confidences (B, N) or None,
    all float64 and already shape-checked. Returns ``use`` (B, N) bool and B reasons, the first
    that applies of: invalid K, non-finite or negative confidences, all confidences zero, NaN/inf
    among the used points, fewer than ``min_points`` used points, coincident / collinear 3D points,
    coplanar 3D points (only with ``coplanar_rtol``: third principal spread <= coplanar_rtol x
    first), coincident / collinear 2D points.
    """
    B, N = points_3d.shape[:2]
    reasons = [""] * B

    def fail(mask: np.ndarray, make) -> None:
        if not mask.any():
            return
        for i in np.flatnonzero(mask):
            if not reasons[i]:
                reasons[i] = make(i)

    k_ok = (
        np.isfinite(K).all(axis=(-1, -2))
        & (K[:, 0, 0] > 0)
        & (K[:, 1, 1] > 0)
        & (K[:, 2, 0] == 0)
        & (K[:, 2, 1] == 0)
        & (K[:, 2, 2] == 1)
    )
    fail(~k_ok, lambda i: f"K is not a valid camera matrix (need finite fx, fy > 0 and last row [0, 0, 1]), got {K[i].tolist()}")

    if confidences is None:
        use = np.ones((B, N), dtype=bool)
    else:
        finite_c = np.isfinite(confidences)
        fail(~finite_c.all(-1), lambda i: f"confidences contain NaN/inf at index {int(np.flatnonzero(~finite_c[i])[0])}")
        neg = np.where(finite_c, confidences, 0.0) < 0
        fail(neg.any(-1), lambda i: f"confidences must be >= 0, got {float(confidences[i][neg[i]].min())}")
        use = np.where(finite_c, confidences, 0.0) > 0
        fail(~use.any(-1), lambda i: "all confidences are zero")

    finite_p = np.isfinite(points_3d).all(-1) & np.isfinite(points_2d).all(-1)
    bad = use & ~finite_p
    fail(bad.any(-1), lambda i: f"points contain NaN/inf (point {int(np.flatnonzero(bad[i])[0])})")
    use = use & finite_p

    count = use.sum(-1)
    fail(count < min_points,
         lambda i: f"too few points: {int(count[i])} usable (confidence > 0, finite); {method} needs >= {min_points}")

    s3, scale3 = _spreads(points_3d, use)
    s2, scale2 = _spreads(points_2d, use)
    fail(s3[:, 0] <= 1e-9 * (1.0 + scale3), lambda i: "all 3D points coincide")
    fail(s3[:, 1] <= COLLINEAR_RTOL * s3[:, 0], lambda i: "3D points are collinear")
    if coplanar_rtol is not None:
        fail(s3[:, 2] <= coplanar_rtol * s3[:, 0],
             lambda i: f"3D points are coplanar (thickness/extent {s3[i, 2] / s3[i, 0]:.2g} <= {coplanar_rtol:g}); "
                       f"{method} needs non-planar points")
    fail(s2[:, 0] <= 1e-9 * (1.0 + scale2), lambda i: "all 2D points coincide")
    fail(s2[:, 1] <= COLLINEAR_RTOL * s2[:, 0], lambda i: "2D points are collinear")
    return use, reasons


def diagnose_solutions(
    R: np.ndarray,
    t: np.ndarray,
    points_3d: np.ndarray,
    points_2d: np.ndarray,
    K: np.ndarray,
    use: np.ndarray,
    *,
    max_reprojection_error: float | None = None,
    max_relative_residual: float | None = None,
) -> list[str]:
    """Why each solution (R (B,3,3), t (B,3)) is not usable ("" when it is).

    A solution is usable when R and t are finite, R is a proper rotation (orthonormal, det +1 to
    1e-6), at most half of the used points (``use`` (B, N)) lie at z <= 0 in the camera, when
    ``max_reprojection_error`` (px) is given, the median reprojection error of the used points
    does not exceed it, and, when ``max_relative_residual`` is given, that median does not exceed
    ``max(RESIDUAL_FLOOR_PX, max_relative_residual x size)`` where size is the diagonal of the 2D
    box of the used points (the smaller of the observed box and the box of their projections).
    """
    B = R.shape[0]
    reasons = [""] * B
    finite = np.isfinite(R).all(axis=(-1, -2)) & np.isfinite(t).all(-1)
    Rf = np.where(finite[:, None, None], R, np.eye(3))
    tf = np.where(finite[:, None], t, 0.0)
    orth = np.abs(Rf.swapaxes(-1, -2) @ Rf - np.eye(3)).max(axis=(-1, -2)) < 1e-6
    proper = orth & (np.linalg.det(Rf) > 0)
    z = transform_points(np.where(use[..., None], points_3d, 0.0), Rf, tf)[..., 2]
    n_used = use.sum(-1)
    behind = ((z <= 0) & use).sum(-1)
    for i in range(B):
        if not finite[i]:
            reasons[i] = "solver returned a non-finite pose"
        elif not proper[i]:
            reasons[i] = "solver returned an improper rotation (not orthonormal with det +1)"
        elif 2 * behind[i] > n_used[i]:
            reasons[i] = f"solution puts the object behind the camera ({int(behind[i])} of {int(n_used[i])} points at z <= 0)"
    if max_reprojection_error is None and max_relative_residual is None:
        return reasons
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = project_points(np.where(use[..., None], points_3d, 0.0), K, Rf, tf)
    err = np.linalg.norm(uv - points_2d, axis=-1)
    for i in range(B):
        if reasons[i]:
            continue
        med = float(np.median(err[i][use[i]]))
        if max_reprojection_error is not None and not med <= max_reprojection_error:
            reasons[i] = f"median reprojection error {med:.3g} px exceeds max_reprojection_error={max_reprojection_error}"
        elif max_relative_residual is not None:
            seen, proj = points_2d[i][use[i]], uv[i][use[i]]
            size = min(float(np.linalg.norm(seen.max(0) - seen.min(0))), float(np.linalg.norm(proj.max(0) - proj.min(0))))
            limit = max(RESIDUAL_FLOOR_PX, max_relative_residual * size)
            if not med <= limit:
                reasons[i] = (f"median reprojection error {med:.3g} px exceeds max_relative_residual={max_relative_residual:g} "
                              f"x the object's projected size {size:.3g} px (limit {limit:.3g} px): the points do not "
                              f"fit one pose")
    return reasons
