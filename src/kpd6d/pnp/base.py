"""The PnP calling convention: result types and the base class every solver derives from.

``solver(points_3d (N,3) mm, points_2d (N,2) px, K (3,3), confidences=None) -> PoseEstimate`` and
``solver.solve_batch(points_3d (B,N,3), points_2d (B,N,2), K (B,3,3) or (3,3), confidences (B,N)
or None) -> BatchPoseEstimate``. numpy in gives numpy out; torch in gives torch out on the input's
device. Outputs are float64. ``inliers`` is always a boolean mask over the N input points.
Mismatched shapes raise ``ValueError`` naming the shapes; every other problem with the input or
the solution gives ``ok=False`` with a ``reason`` and NaN ``R``/``t`` (see :mod:`kpd6d.pnp.checks`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from kpd6d.pnp.checks import MAX_RELATIVE_RESIDUAL, diagnose_inputs, diagnose_solutions

__all__ = ["BatchPoseEstimate", "PnPSolver", "PoseEstimate", "Problems"]


@dataclass
class PoseEstimate:
    """One PnP result. ``R`` (3,3) and ``t`` (3,) mm are NaN when ``ok`` is False.

    ``inliers`` is a bool mask (N,) over the input points: the points the pose was fitted to
    (confidence > 0, and for RANSAC the consensus set); all False when not ok.
    """

    R: Any
    t: Any
    inliers: Any
    ok: bool
    reason: str = ""


@dataclass
class BatchPoseEstimate:
    """B PnP results: ``R`` (B,3,3), ``t`` (B,3), ``ok`` (B,) bool, ``inliers`` (B,N) bool, ``reasons`` (B strings, "" when ok)."""

    R: Any
    t: Any
    ok: Any
    inliers: Any
    reasons: list[str]

    def __len__(self) -> int:
        return len(self.reasons)

    def __getitem__(self, i: int) -> PoseEstimate:
        return PoseEstimate(self.R[i], self.t[i], self.inliers[i], bool(self.ok[i]), self.reasons[i])


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


def _to_numpy(x: Any) -> np.ndarray:
    if _is_torch(x):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


@dataclass
class Problems:
    """A validated batch of PnP problems as float64 numpy arrays (plus where the input came from)."""

    points_3d: np.ndarray  # (B, N, 3)
    points_2d: np.ndarray  # (B, N, 2)
    K: np.ndarray  # (B, 3, 3)
    confidences: np.ndarray | None  # (B, N)
    device: Any  # torch device of the input, or None for numpy input

    @classmethod
    def from_inputs(cls, points_3d, points_2d, K, confidences, *, batched: bool) -> Problems:
        """Validate shapes (``ValueError`` naming them) and convert to float64 numpy."""
        device = points_3d.device if _is_torch(points_3d) else None
        p3, p2, k = _to_numpy(points_3d), _to_numpy(points_2d), _to_numpy(K)
        c = None if confidences is None else _to_numpy(confidences)
        lead = "(B, N, " if batched else "(N, "
        form = (f"points_3d {lead}3), points_2d {lead}2), K (3, 3)" + (" or (B, 3, 3)" if batched else "")
                + f", confidences {lead[:-2]}) or None")

        def bad(what: str) -> ValueError:
            return ValueError(
                f"PnP input shapes do not match ({what}): got points_3d {p3.shape}, points_2d {p2.shape}, "
                f"K {k.shape}, confidences {None if c is None else c.shape}; expected {form}"
            )

        nd = 3 if batched else 2
        if p3.ndim != nd or p3.shape[-1] != 3:
            raise bad("points_3d")
        if p2.ndim != nd or p2.shape[-1] != 2 or p2.shape[:-1] != p3.shape[:-1]:
            raise bad("points_2d")
        if c is not None and c.shape != p3.shape[:-1]:
            raise bad("confidences")
        if not batched:
            if k.shape != (3, 3):
                raise bad("K")
            p3, p2, k = p3[None], p2[None], k[None]
            c = None if c is None else c[None]
        else:
            if k.shape == (3, 3):
                k = np.broadcast_to(k, (p3.shape[0], 3, 3))
            elif k.shape != (p3.shape[0], 3, 3):
                raise bad("K")
        return cls(p3, p2, np.ascontiguousarray(k), c, device)

    def __len__(self) -> int:
        return self.points_3d.shape[0]

    def subset(self, idx: np.ndarray, device: Any = None) -> Problems:
        """Problems ``idx`` (results of solvers given it come back on ``device``: None = numpy)."""
        c = None if self.confidences is None else self.confidences[idx]
        return Problems(self.points_3d[idx], self.points_2d[idx], self.K[idx], c, device)


class PnPSolver:
    """Base class. Subclasses set ``min_points`` (and ``coplanar_rtol`` when coplanar 3D points
    are degenerate for them) and implement
    :meth:`_solve`, which gets only the problems that passed :func:`diagnose_inputs`.

    ``max_reprojection_error`` (px, default None = off): when set, a solution whose median
    reprojection error over its used points exceeds it is returned with ``ok=False``.
    ``max_relative_residual`` (default :data:`kpd6d.pnp.checks.MAX_RELATIVE_RESIDUAL` = 0.2; None =
    off) is the default validity gate: a solution whose median reprojection error exceeds this
    fraction of the object's projected size (floor 4 px) is returned with ``ok=False`` (so points
    that fit no pose, e.g. random ones, are never ok).
    """

    name: str = "pnp"
    min_points: int = 4
    coplanar_rtol: float | None = None

    def __init__(self, max_reprojection_error: float | None = None,
                 max_relative_residual: float | None = MAX_RELATIVE_RESIDUAL) -> None:
        if max_reprojection_error is not None and not max_reprojection_error > 0:
            raise ValueError(f"{self.name}: max_reprojection_error must be > 0 or None, got {max_reprojection_error!r}")
        if max_relative_residual is not None and not (isinstance(max_relative_residual, (int, float))
                                                      and max_relative_residual > 0):
            raise ValueError(f"{self.name}: max_relative_residual must be > 0 or None, got {max_relative_residual!r}")
        self.max_reprojection_error = max_reprojection_error
        self.max_relative_residual = None if max_relative_residual is None else float(max_relative_residual)

    def __repr__(self) -> str:
        params = ", ".join(f"{k}={v!r}" for k, v in vars(self).items() if not k.startswith("_") and k != "min_points")
        return f"{type(self).__name__}({params})"

    # -- public API -----------------------------------------------------------------------------
    def __call__(self, points_3d, points_2d, K, confidences=None) -> PoseEstimate:
        probs = Problems.from_inputs(points_3d, points_2d, K, confidences, batched=False)
        return self._run(probs)[0]

    def solve_batch(self, points_3d, points_2d, K, confidences=None) -> BatchPoseEstimate:
        probs = Problems.from_inputs(points_3d, points_2d, K, confidences, batched=True)
        return self._run(probs)

    # -- implementation -------------------------------------------------------------------------
    def _run(self, probs: Problems) -> BatchPoseEstimate:
        B, N = probs.points_3d.shape[:2]
        use, reasons = diagnose_inputs(
            probs.points_3d, probs.points_2d, probs.K, probs.confidences,
            method=self.name, min_points=self.min_points, coplanar_rtol=self.coplanar_rtol,
        )
        R = np.full((B, 3, 3), np.nan)
        t = np.full((B, 3), np.nan)
        inliers = np.zeros((B, N), dtype=bool)
        todo = np.array([i for i in range(B) if not reasons[i]], dtype=np.int64)
        if len(todo):
            R_s, t_s, inl_s, why = self._solve(probs, todo, use[todo])
            post = diagnose_solutions(
                R_s, t_s, probs.points_3d[todo], probs.points_2d[todo], probs.K[todo], inl_s,
                max_reprojection_error=self.max_reprojection_error,
                max_relative_residual=getattr(self, "max_relative_residual", MAX_RELATIVE_RESIDUAL),
            )
            for j, i in enumerate(todo):
                reasons[i] = why[j] or post[j]
                if not reasons[i]:
                    R[i], t[i], inliers[i] = R_s[j], t_s[j], inl_s[j]
        ok = np.array([not r for r in reasons], dtype=bool)
        return self._wrap(BatchPoseEstimate(R, t, ok, inliers, reasons), probs.device)

    def _solve(self, probs: Problems, todo: np.ndarray, use: np.ndarray):
        """Solve problems ``todo`` (indices into ``probs``) using points ``use`` (len(todo), N).

        Returns R (T,3,3), t (T,3), inliers (T,N) bool and T reasons ("" when solved).
        """
        raise NotImplementedError

    @staticmethod
    def _wrap(res: BatchPoseEstimate, device) -> BatchPoseEstimate:
        if device is None:
            return res
        import torch

        def tt(a):
            return torch.as_tensor(a, device=device)

        return BatchPoseEstimate(tt(res.R), tt(res.t), tt(res.ok), tt(res.inliers), res.reasons)
