"""PnP solvers (registry ``PNP_SOLVERS``): ``epnp``, ``iterative``, ``sqpnp``, ``epnp_ransac``, ``sqpnp_ransac``, ``dlt``, ``weighted_lm``.

``PNP_SOLVERS.build(name, **params)(points_3d (N,3) mm, points_2d (N,2) px, K (3,3),
confidences=None) -> PoseEstimate``; ``solver.solve_batch(...)`` for (B, N, ...) inputs. See
:mod:`kpd6d.pnp.base` for the convention and docs/pnp.md for the solvers. :mod:`kpd6d.pnp.top_l`:
``top_l`` (the l most confident keypoints) and ``solve_top_l`` (one batched PnP on them).
"""

from kpd6d.pnp import dlt, opencv_solvers, weighted_lm  # noqa: F401 - importing registers the solvers
from kpd6d.pnp.base import BatchPoseEstimate, PnPSolver, PoseEstimate
from kpd6d.pnp.top_l import solve_top_l, top_l

__all__ = ["BatchPoseEstimate", "PnPSolver", "PoseEstimate", "solve_top_l", "top_l"]
