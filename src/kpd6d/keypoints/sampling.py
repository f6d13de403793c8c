"""Point sampling shared by the designators: spatial NMS and farthest-point sampling, both
optionally symmetry-aware.

Symmetry-aware selection measures distances between *orbits*: ``d(p, q) = min_S |S p - q|`` over the
object's symmetry transforms S (identity included). Two keypoints closer than the tolerance under
that distance would map onto each other under a symmetry, so the keypoint detector could not tell
them apart (the paper's 17 non-symmetric eggbox keypoints). For a body of revolution the orbit
distance is exact: the distance between the (radius, height) coordinates about the axis.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["PointMetric", "farthest_point_sampling", "nms_select", "uses_symmetry"]


def uses_symmetry(model, symmetry_aware: bool | None) -> bool:
    """``symmetry_aware`` if given, else whether the model lists any symmetry."""
    if symmetry_aware is None:
        return bool(getattr(model, "is_symmetric", False))
    return bool(symmetry_aware)


class PointMetric:
    """Euclidean distance, or the orbit distance under a model's symmetries (``symmetric=True``)."""

    def __init__(self, model=None, symmetric: bool = False) -> None:
        self.symmetric = bool(symmetric and model is not None and getattr(model, "is_symmetric", False))
        self._transforms: list[np.ndarray] = [np.eye(4)]
        self._axis = None
        if not self.symmetric:
            return
        from kpd6d.symmetry import ContinuousSymmetry, handler_for_model

        handler = handler_for_model(model)
        if isinstance(handler, ContinuousSymmetry):
            self._axis = (handler.axis, handler.offset)
            self._transforms = [np.eye(4), *handler.flips]
        else:  # the model's own (BOP) matrices: tolerances hold for exactly these
            listed = [np.asarray(S, dtype=np.float64).reshape(4, 4) for S in model.symmetries_discrete]
            self._transforms = [np.eye(4), *listed, *(np.linalg.inv(S) for S in listed)]

    @property
    def transforms(self) -> list[np.ndarray]:
        """The transforms used (identity first; for a body of revolution: identity and its flips)."""
        return [T.copy() for T in self._transforms]

    def _rh(self, P: np.ndarray) -> np.ndarray:
        a, o = self._axis
        d = P - o
        h = d @ a
        r = np.linalg.norm(d - h[..., None] * a, axis=-1)
        return np.stack([r, h], axis=-1)

    def distance(self, P: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Distances (N,) from points P (N, 3) to point q (3,)."""
        P = np.asarray(P, dtype=np.float64)
        q = np.asarray(q, dtype=np.float64)
        best = None
        for T in self._transforms:
            q_img = T[:3, :3] @ q + T[:3, 3]
            if self._axis is not None:
                d = np.linalg.norm(self._rh(P) - self._rh(q_img[None])[0], axis=-1)
            else:
                d = np.linalg.norm(P - q_img, axis=-1)
            best = d if best is None else np.minimum(best, d)
        return best

    def min_pairwise(self, P: np.ndarray) -> float:
        """Smallest distance between two different points of P (inf for fewer than two)."""
        P = np.asarray(P, dtype=np.float64)
        best = math.inf
        for i in range(len(P) - 1):
            best = min(best, float(self.distance(P[i + 1 :], P[i]).min()))
        return best


def nms_select(candidates: np.ndarray, k: int, min_dist: float, metric: PointMetric | None = None) -> list[int]:
    """Greedy spatial NMS: walk ``candidates`` (N, 3) in order (best first) and keep a point when it
    is at least ``min_dist`` from every kept one under ``metric``; stops at ``k``. Returns indices."""
    metric = metric or PointMetric()
    C = np.asarray(candidates, dtype=np.float64)
    kept: list[int] = []
    min_d = np.full(len(C), np.inf)
    for i in range(len(C)):
        if len(kept) >= k:
            break
        if min_d[i] < min_dist:
            continue
        kept.append(i)
        min_d = np.minimum(min_d, metric.distance(C, C[i]))
    return kept


def farthest_point_sampling(points: np.ndarray, k: int, start=None, metric: PointMetric | None = None,
                            initial: np.ndarray | None = None) -> list[int]:
    """Farthest-point sampling of ``k`` indices of ``points`` (N, 3).

    Distances start from ``start`` (a 3-vector, e.g. the object centre, not itself returned, as in
    PVNet) and from already chosen ``initial`` points (M, 3); without either, the first point is
    ``points[0]``. ``metric`` makes the sampling symmetry-aware.
    """
    metric = metric or PointMetric()
    P = np.asarray(points, dtype=np.float64)
    if k > len(P):
        raise ValueError(f"farthest_point_sampling: asked for {k} points from only {len(P)} samples")
    min_d = np.full(len(P), np.inf)
    seeds = []
    if start is not None:
        seeds.append(np.asarray(start, dtype=np.float64))
    if initial is not None:
        seeds.extend(np.asarray(initial, dtype=np.float64).reshape(-1, 3))
    for s in seeds:
        min_d = np.minimum(min_d, metric.distance(P, s))
    chosen: list[int] = []
    for _ in range(k):
        i = int(np.argmax(min_d)) if seeds or chosen else 0
        chosen.append(i)
        min_d = np.minimum(min_d, metric.distance(P, P[i]))
        min_d[i] = -np.inf
    return chosen
