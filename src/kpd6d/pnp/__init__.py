"""PnP solvers (registry ``PNP_SOLVERS``): ``epnp``, ``iterative``, ``sqpnp``, ``epnp_ransac``, ``dlt``, ``weighted_lm``.

``PNP_SOLVERS.build(name, **params)(points_3d (N,3) mm, points_2d (N,2) px, K (3,3),
confidences=None) -> PoseEstimate``; ``solver.solve_batch(...)`` for (B, N, ...) inputs. See
:mod:`kpd6d.pnp.base` for the convention and docs/pnp.md for the solvers.
"""

from kpd6d.pnp import dlt, opencv_solvers, weighted_lm  # noqa: F401 - importing registers the solvers
from kpd6d.pnp.base import BatchPoseEstimate, PnPSolver, PoseEstimate

__all__ = ["BatchPoseEstimate", "PnPSolver", "PoseEstimate"]
