"""``weighted_lm``: batched, confidence-weighted Levenberg–Marquardt refinement of the reprojection error.

Minimises, for every problem b independently and all at once in torch,

    E_b(R, t) = sum_i c_bi * || project(K_b, R X_bi + t) - u_bi ||^2

where c_bi is keypoint i's confidence (1 without confidences; 0 drops the point). The pose is
updated on SE(3) with an axis-angle increment about the current centroid of the used points in
the camera frame, ``x_c <- exp([w]x) (x_c - c) + c + v`` (better conditioned than rotating about
the camera centre), with Marquardt's damping ``(H + lambda diag(H)) delta = -g``; steps that do
not lower E are rejected and lambda grows tenfold, accepted ones shrink it tenfold. Runs in
float64 on the input's device (CUDA when the tensors are there).

The start comes from another solver: ``init`` (default ``epnp``) for single problems and for
batch problems ``batch_init`` cannot take; ``batch_init`` (default ``dlt``, which is batched on
the same device; ``None`` uses ``init``) for batches.
"""

from __future__ import annotations

import numpy as np

from kpd6d.geometry import project_points, transform_points
from kpd6d.pnp.base import PnPSolver, Problems
from kpd6d.pnp.checks import MAX_RELATIVE_RESIDUAL
from kpd6d.registry import PNP_SOLVERS

__all__ = ["WeightedLM", "lm_refine"]


def _numpy(a) -> np.ndarray:
    return a.detach().cpu().numpy() if hasattr(a, "detach") else np.asarray(a)


def _skew(v):
    import torch

    z = torch.zeros_like(v[..., 0])
    return torch.stack(
        [z, -v[..., 2], v[..., 1], v[..., 2], z, -v[..., 0], -v[..., 1], v[..., 0], z], dim=-1
    ).reshape((*v.shape[:-1], 3, 3))


def _cost(X, uv, K, w, R, t):
    import torch

    proj, z = project_points(X, K, R, t, return_depth=True)
    r = proj - uv
    c = (w * (r * r).sum(-1)).sum(-1)
    # a point of positive weight at or behind the camera makes the pose unusable for this model
    bad = ((z <= 0) & (w > 0)).any(-1) | ~torch.isfinite(c)
    return torch.where(bad, torch.full_like(c, float("inf")), c)


def lm_refine(X, uv, K, w, R, t, *, max_iters: int = 30, lam0: float = 1e-3, tol: float = 1e-12):
    """Refine poses (R (B,3,3), t (B,3)) of points X (B,N,3) seen at uv (B,N,2) with K (B,3,3), weights w (B,N).

    All tensors float64 on one device. Returns refined (R, t, cost (B,), iterations run).
    """
    import torch
    from kornia.geometry.conversions import axis_angle_to_rotation_matrix

    B = X.shape[0]
    eye3 = torch.eye(3, dtype=X.dtype, device=X.device)
    wsum = w.sum(-1).clamp_min(1e-300)
    Xbar = (w[..., None] * X).sum(-2) / wsum[:, None]  # weighted model centroid (B,3)
    lam = torch.full((B,), lam0, dtype=X.dtype, device=X.device)
    cost = _cost(X, uv, K, w, R, t)
    it = 0
    for it in range(1, max_iters + 1):  # noqa: B007 - `it` is returned
        xc = transform_points(X, R, t)  # (B,N,3)
        c = (R @ Xbar[..., None])[..., 0] + t  # centroid in the camera (B,3)
        proj = project_points(xc, K)  # (B,N,2)
        r = proj - uv
        z = xc[..., 2].clamp_min(1e-9)
        # d proj / d x_c = (K[:2] - proj e3^T) / z    (B,N,2,3)
        Jp = (K[:, None, :2, :] - proj[..., :, None] * eye3[2]) / z[..., None, None]
        J = torch.cat([-Jp @ _skew(xc - c[:, None]), Jp], dim=-1)  # (B,N,2,6): (omega, v)
        Jw = J * w[..., None, None]
        H = torch.einsum("bnki,bnkj->bij", Jw, J)
        g = torch.einsum("bnki,bnk->bi", Jw, r)
        damp = lam[:, None] * torch.diagonal(H, dim1=-2, dim2=-1) + 1e-12
        A = H + torch.diag_embed(damp)
        delta = -torch.linalg.solve(A, g[..., None])[..., 0]
        delta = torch.nan_to_num(delta, nan=0.0, posinf=0.0, neginf=0.0)
        dR = axis_angle_to_rotation_matrix(delta[:, :3])
        R_new = dR @ R
        t_new = (dR @ (t - c)[..., None])[..., 0] + c + delta[:, 3:]
        new_cost = _cost(X, uv, K, w, R_new, t_new)
        accept = new_cost < cost
        R = torch.where(accept[:, None, None], R_new, R)
        t = torch.where(accept[:, None], t_new, t)
        improvement = torch.where(accept, cost - new_cost, torch.zeros_like(cost))
        cost = torch.where(accept, new_cost, cost)
        lam = torch.where(accept, lam * 0.1, lam * 10.0).clamp(1e-12, 1e12)
        # converged: accepted steps no longer lower the cost noticeably and the step is tiny
        small = (improvement <= tol * (1.0 + cost)) & (delta.abs().amax(-1) < 1e-10 * (1.0 + t.abs().amax(-1)))
        stuck = lam >= 1e12
        if bool((small | stuck | ~torch.isfinite(cost)).all()):
            break
    return R, t, cost, it


@PNP_SOLVERS.register("weighted_lm")
class WeightedLM(PnPSolver):
    """Confidence-weighted LM (see module docstring).

    ``init``: PnP solver name for the starting pose of single problems (default ``epnp``);
    ``batch_init``: solver for batches (default ``dlt``; problems it cannot take fall back to
    ``init``; None: always ``init``); ``max_iters``: LM iterations; ``device``: torch device
    (default: the input's).
    """

    name = "weighted_lm"

    def __init__(self, init: str = "epnp", batch_init: str | None = "dlt", max_iters: int = 30,
                 device: str | None = None, max_reprojection_error: float | None = None,
                 max_relative_residual: float | None = MAX_RELATIVE_RESIDUAL) -> None:
        super().__init__(max_reprojection_error, max_relative_residual)
        if init == "weighted_lm" or batch_init == "weighted_lm":
            raise ValueError("weighted_lm cannot initialise itself; pick another PnP solver for init/batch_init")
        if int(max_iters) < 1:
            raise ValueError(f"weighted_lm: max_iters must be >= 1, got {max_iters!r}")
        self.init = init
        self.batch_init = batch_init
        self.max_iters = int(max_iters)
        self.device = device
        # starting poses are not gated: LM may turn a poor start into a good pose; the gate judges the result
        self._init = PNP_SOLVERS.build(init, max_relative_residual=None)
        self._batch_init = None if batch_init is None else PNP_SOLVERS.build(batch_init, max_relative_residual=None)
        self.min_points = self._init.min_points
        if self._batch_init is not None:
            self.min_points = min(self.min_points, self._batch_init.min_points)

    def _start(self, probs: Problems, todo: np.ndarray):
        """Starting poses for problems ``todo``: ``init`` for one problem; for more, ``batch_init``
        with ``init`` as the fallback for the problems it cannot take."""
        T = len(todo)
        R0 = np.full((T, 3, 3), np.nan)
        t0 = np.full((T, 3), np.nan)
        reasons = ["not initialised"] * T
        order = [self._init] if (len(probs) == 1 or self._batch_init is None) else [self._batch_init, self._init]
        device = self.device or probs.device  # batched initialisers solve where the input lives
        remaining = np.arange(T)
        for solver in order:
            if not len(remaining):
                break
            res = solver._run(probs.subset(todo[remaining], device=device))
            ok, Rr, tr = (_numpy(a) for a in (res.ok, res.R, res.t))
            for j, k in enumerate(remaining):
                if ok[j]:
                    R0[k], t0[k], reasons[k] = Rr[j], tr[j], ""
                else:
                    reasons[k] = f"initialisation by {solver.name} failed: {res.reasons[j]}"
            remaining = remaining[~ok.astype(bool)]
        return R0, t0, reasons

    def _solve(self, probs: Problems, todo: np.ndarray, use: np.ndarray):
        import torch

        R0, t0, reasons = self._start(probs, todo)
        started = np.array([not r for r in reasons], dtype=bool)
        R = np.full_like(R0, np.nan)
        t = np.full_like(t0, np.nan)
        if started.any():
            dev = torch.device(self.device or probs.device or "cpu")
            idx = todo[started]
            u = use[started]

            def tt(a):
                return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64, device=dev)

            conf = np.ones(u.shape) if probs.confidences is None else probs.confidences[idx]
            X = tt(np.where(u[..., None], probs.points_3d[idx], 0.0))
            uv = tt(np.where(u[..., None], probs.points_2d[idx], 0.0))
            w = tt(np.where(u, conf, 0.0))
            Rr, tr, _, _ = lm_refine(X, uv, tt(probs.K[idx]), w, tt(R0[started]), tt(t0[started]),
                                     max_iters=self.max_iters)
            R[started], t[started] = Rr.cpu().numpy(), tr.cpu().numpy()
        return R, t, use.copy(), reasons
