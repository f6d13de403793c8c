"""``dlt``: batched Direct Linear Transform PnP (``kornia.geometry.calibration.solve_pnp_dlt``).

Runs in torch on the input's device (numpy input: CPU; ``device=`` overrides), float64, all
problems in one call. Needs >= 6 non-coplanar points. Confidences weight each point's equations
by sqrt(confidence), so the algebraic cost is confidence-weighted like ``weighted_lm``'s; a zero
confidence removes the point.
"""

from __future__ import annotations

import numpy as np

from kpd6d.pnp.base import PnPSolver, Problems
from kpd6d.pnp.checks import MAX_RELATIVE_RESIDUAL
from kpd6d.registry import PNP_SOLVERS

__all__ = ["DLT", "dlt_poses"]


def dlt_poses(points_3d, points_2d, K, weights=None):
    """Run kornia's DLT on torch tensors (B,N,3), (B,N,2), (B,3,3), weights (B,N) or None.

    Returns (R (B,3,3), t (B,3), reasons); a batch that kornia rejects as a whole (its own
    rank check) is re-run problem by problem so only the offending problems fail.
    """
    import torch
    from kornia.geometry.calibration import solve_pnp_dlt

    B = points_3d.shape[0]
    try:
        P = solve_pnp_dlt(points_3d, points_2d, K, weights=weights)
        return P[:, :, :3], P[:, :, 3], [""] * B
    except (AssertionError, RuntimeError, ValueError) as exc:
        if B == 1:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            nan = torch.full((1, 3, 4), float("nan"), dtype=points_3d.dtype, device=points_3d.device)
            return nan[:, :, :3], nan[:, :, 3], [f"kornia DLT failed: {first}"]
    Rs, ts, reasons = [], [], []
    for i in range(B):
        R, t, why = dlt_poses(points_3d[i : i + 1], points_2d[i : i + 1], K[i : i + 1],
                              None if weights is None else weights[i : i + 1])
        Rs.append(R)
        ts.append(t)
        reasons += why
    return torch.cat(Rs), torch.cat(ts), reasons


@PNP_SOLVERS.register("dlt")
class DLT(PnPSolver):
    """Batched DLT (kornia). ``device``: torch device to solve on (default: the input's)."""

    name = "dlt"
    min_points = 6
    coplanar_rtol = 1e-3  # stricter than kornia's own rank check, so a batch is not rejected whole

    def __init__(self, device: str | None = None, max_reprojection_error: float | None = None,
                 max_relative_residual: float | None = MAX_RELATIVE_RESIDUAL) -> None:
        super().__init__(max_reprojection_error, max_relative_residual)
        self.device = device

    def _torch_inputs(self, probs: Problems, todo: np.ndarray, use: np.ndarray):
        """The ``todo`` problems as float64 tensors on the solving device, unused points zeroed."""
        import torch

        dev = torch.device(self.device) if self.device is not None else (probs.device or torch.device("cpu"))

        def tt(a):
            return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64, device=dev)

        X = np.where(use[..., None], probs.points_3d[todo], 0.0)
        uv = np.where(use[..., None], probs.points_2d[todo], 0.0)
        conf = np.ones(use.shape) if probs.confidences is None else probs.confidences[todo]
        w = np.where(use, conf, 0.0)
        return tt(X), tt(uv), tt(probs.K[todo]), tt(w)

    def _solve(self, probs: Problems, todo: np.ndarray, use: np.ndarray):
        X, uv, K, w = self._torch_inputs(probs, todo, use)
        weights = None if probs.confidences is None and bool(use.all()) else w.sqrt()
        R, t, reasons = dlt_poses(X, uv, K, weights)
        return R.cpu().numpy(), t.cpu().numpy(), use.copy(), reasons
