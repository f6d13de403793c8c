"""OpenCV PnP solvers: ``epnp``, ``iterative``, ``sqpnp``, ``epnp_ransac`` and ``sqpnp_ransac``.

Each uses only the points with confidence > 0 (confidences are not weights here). Minimum point
counts are what gives reliable answers, not only what OpenCV accepts: OpenCV's EPnP accepts 4
points but its 4-point solutions are wrong in most random trials (measured: 97 % of 200), so
``epnp`` needs 5; ``iterative`` starts from OpenCV's DLT for non-planar points (6); ``sqpnp``
needs 4 (3 points admit up to four poses). OpenCV's EPnP is also unreliable on exactly coplanar
3D points: on noise-free input it returned wrong poses (several px reprojection error) for 57 % of
200 random planes z = 0 and 16 % of 200 randomly rotated planes, and for none of them once the
points had a thickness of 1e-12 .. 0.1 of their extent. So ``epnp`` and ``epnp_ransac`` reject
coplanar points (thickness/extent <= 1e-6); use ``sqpnp`` or ``iterative`` for planar objects.
Batches are solved in a Python loop.
"""

from __future__ import annotations

import cv2
import numpy as np

from kpd6d.geometry import project_points
from kpd6d.pnp.base import PnPSolver, Problems
from kpd6d.pnp.checks import MAX_RELATIVE_RESIDUAL
from kpd6d.registry import PNP_SOLVERS

__all__ = ["EPnP", "EPnPRansac", "Iterative", "OpenCVSolver", "SQPnP", "SQPnPRansac"]


def _cv_error(exc: cv2.error) -> str:
    lines = [ln.strip() for ln in str(exc).strip().splitlines() if ln.strip()]
    return lines[-1] if lines else repr(exc)


class OpenCVSolver(PnPSolver):
    """``cv2.solvePnP`` with one of its ``SOLVEPNP_*`` flags, one problem at a time."""

    flag: int = cv2.SOLVEPNP_EPNP

    def _solve(self, probs: Problems, todo: np.ndarray, use: np.ndarray):
        T = len(todo)
        R = np.full((T, 3, 3), np.nan)
        t = np.full((T, 3), np.nan)
        inliers = use.copy()
        reasons = [""] * T
        for j, i in enumerate(todo):
            X = np.ascontiguousarray(probs.points_3d[i][use[j]])
            uv = np.ascontiguousarray(probs.points_2d[i][use[j]])
            try:
                R[j], t[j], inl, reasons[j] = self._solve_one(X, uv, probs.K[i])
            except cv2.error as exc:
                reasons[j] = f"OpenCV {self.name} failed: {_cv_error(exc)}"
                continue
            if inl is not None:
                inliers[j] = False
                inliers[j, np.flatnonzero(use[j])[inl]] = True
        return R, t, inliers, reasons

    def _solve_one(self, X: np.ndarray, uv: np.ndarray, K: np.ndarray):
        """(R, t, inlier indices into X or None for all, reason) for one problem."""
        ok, rvec, tvec = cv2.solvePnP(X, uv, K, None, flags=self.flag)
        if not ok:
            return np.nan, np.nan, None, f"OpenCV {self.name} reported failure"
        return cv2.Rodrigues(rvec)[0], tvec.reshape(3), None, ""


@PNP_SOLVERS.register("epnp")
class EPnP(OpenCVSolver):
    """OpenCV EPnP (``SOLVEPNP_EPNP``), the paper's solver. Needs >= 5 non-coplanar points."""

    name = "epnp"
    min_points = 5
    coplanar_rtol = 1e-6
    flag = cv2.SOLVEPNP_EPNP


@PNP_SOLVERS.register("iterative")
class Iterative(OpenCVSolver):
    """OpenCV ``SOLVEPNP_ITERATIVE``: DLT / homography start, then Levenberg–Marquardt. Needs >= 6 points."""

    name = "iterative"
    min_points = 6
    flag = cv2.SOLVEPNP_ITERATIVE


@PNP_SOLVERS.register("sqpnp")
class SQPnP(OpenCVSolver):
    """OpenCV SQPnP (``SOLVEPNP_SQPNP``), a globally optimal solver. Needs >= 4 points."""

    name = "sqpnp"
    min_points = 4
    flag = cv2.SOLVEPNP_SQPNP


@PNP_SOLVERS.register("epnp_ransac")
class EPnPRansac(OpenCVSolver):
    """``cv2.solvePnPRansac`` with EPnP hypotheses, then (``refine``) LM on the inliers.

    ``reprojection_error`` (px) is the inlier threshold, ``iterations`` the RANSAC iteration cap,
    ``confidence`` its success probability. ``refine=True`` polishes the consensus pose with
    ``cv2.solvePnPRefineLM`` over the inliers. ``seed`` (int, or None to leave OpenCV's global RNG
    alone) reseeds OpenCV's RNG before each problem so results are reproducible. ``min_inliers``
    (default 5, at least 5) is the smallest consensus set accepted; ``inliers`` marks it.
    ``relative_error`` (None = off) scales the inlier threshold with the object's image size: the
    threshold is ``max(reprojection_error, relative_error x d)`` where d is the diagonal of the 2D
    box of the points (the size the validity gate uses), so one setting suits a 40 px and a 300 px
    object.
    """

    name = "epnp_ransac"
    min_points = 5
    coplanar_rtol = 1e-6
    flag = cv2.SOLVEPNP_EPNP

    def __init__(self, reprojection_error: float = 8.0, iterations: int = 100, confidence: float = 0.99,
                 refine: bool = True, seed: int | None = 0, min_inliers: int = 5,
                 max_reprojection_error: float | None = None,
                 max_relative_residual: float | None = MAX_RELATIVE_RESIDUAL,
                 relative_error: float | None = None) -> None:
        super().__init__(max_reprojection_error, max_relative_residual)
        if not reprojection_error > 0:
            raise ValueError(f"epnp_ransac: reprojection_error must be > 0 px, got {reprojection_error!r}")
        if int(iterations) < 1:
            raise ValueError(f"epnp_ransac: iterations must be >= 1, got {iterations!r}")
        if not 0 < confidence < 1:
            raise ValueError(f"epnp_ransac: confidence must be in (0, 1), got {confidence!r}")
        if int(min_inliers) < 5:
            raise ValueError(f"epnp_ransac: min_inliers must be >= 5 (EPnP's minimum), got {min_inliers!r}")
        if relative_error is not None and not (isinstance(relative_error, (int, float)) and 0 < relative_error < 1):
            raise ValueError(f"{self.name}: relative_error must be in (0, 1) or None, got {relative_error!r}")
        self.relative_error = None if relative_error is None else float(relative_error)
        self.reprojection_error = float(reprojection_error)
        self.iterations = int(iterations)
        self.confidence = float(confidence)
        self.refine = bool(refine)
        self.seed = seed
        self.min_inliers = int(min_inliers)
        self.min_points = self.min_inliers

    def threshold(self, uv: np.ndarray) -> float:
        """The inlier threshold (px) for image points ``uv`` (N, 2)."""
        if self.relative_error is None:
            return self.reprojection_error
        return max(self.reprojection_error, self.relative_error * float(np.linalg.norm(uv.max(0) - uv.min(0))))

    def _solve_one(self, X, uv, K):
        if self.seed is not None:
            cv2.setRNGSeed(int(self.seed))
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            X, uv, K, None, iterationsCount=self.iterations, reprojectionError=self.threshold(uv),
            confidence=self.confidence, flags=self.flag,
        )
        if not ok or inl is None:
            return np.nan, np.nan, None, "RANSAC found no consensus set"
        inl = np.sort(inl.reshape(-1))
        if len(inl) < self.min_inliers:
            return np.nan, np.nan, None, f"RANSAC found only {len(inl)} inliers; min_inliers={self.min_inliers}"
        return self._refit(X, uv, K, rvec, tvec, inl)

    def _refit(self, X, uv, K, rvec, tvec, inl):
        """(R, t, inliers, reason) from the consensus pose (rvec, tvec) and its inlier indices ``inl``."""
        if self.refine:
            rvec, tvec = cv2.solvePnPRefineLM(X[inl], uv[inl], K, None, rvec, tvec)
        return cv2.Rodrigues(rvec)[0], tvec.reshape(3), inl, ""


@PNP_SOLVERS.register("sqpnp_ransac")
class SQPnPRansac(EPnPRansac):
    """RANSAC consensus as ``epnp_ransac`` (EPnP hypotheses on 5-point samples), then SQPnP (globally
    optimal) on all the inliers, the inliers re-chosen with that pose and refitted until they no longer
    change (at most :attr:`max_refits` times), then (``refine``) LM on them.

    The robust form of ``sqpnp`` on many keypoints: where most keypoints are good, SQPnP on all of
    them averages their noise out; a few gross outliers (a keypoint on the wrong part, an occluder)
    pull that fit, and RANSAC removes them first. Because the inliers are refitted together, the
    threshold can be generous: by default it grows with the object's image size
    (``relative_error`` 0.1 of the 2D box diagonal, at least ``reprojection_error`` px).
    """

    name = "sqpnp_ransac"

    def __init__(self, reprojection_error: float = 8.0, iterations: int = 100, confidence: float = 0.99,
                 refine: bool = False, seed: int | None = 0, min_inliers: int = 5,
                 max_reprojection_error: float | None = None,
                 max_relative_residual: float | None = MAX_RELATIVE_RESIDUAL,
                 relative_error: float | None = 0.1) -> None:
        super().__init__(reprojection_error, iterations, confidence, refine, seed, min_inliers,
                         max_reprojection_error, max_relative_residual, relative_error)

    #: refits (SQPnP on the inliers, then the inliers re-chosen with that pose) at most this many times
    max_refits = 3

    def _refit(self, X, uv, K, rvec, tvec, inl):
        # The consensus set was chosen with a 5-point hypothesis, whose own errors push some good points
        # over the threshold: refit on the inliers, re-choose them with the refitted pose, until stable
        # (the local optimisation of LO-RANSAC).
        thr = self.threshold(uv)
        for it in range(self.max_refits):
            ok, rvec_s, tvec_s = cv2.solvePnP(X[inl], uv[inl], K, None, flags=cv2.SOLVEPNP_SQPNP)
            if not ok or it == self.max_refits - 1:  # the reported inliers are the ones last fitted
                rvec, tvec = (rvec_s, tvec_s) if ok else (rvec, tvec)
                break
            rvec, tvec = rvec_s, tvec_s
            err = np.linalg.norm(project_points(X, K, cv2.Rodrigues(rvec)[0], tvec.reshape(3)) - uv, axis=1)
            new = np.flatnonzero(err <= thr)
            if len(new) < self.min_inliers or np.array_equal(new, inl):
                break
            inl = new
        return super()._refit(X, uv, K, rvec, tvec, inl)
