"""SIFT surface keypoints (the paper's designation): render, detect, lift, cluster, rank, select.

1. Render the textured model from ``num_views`` viewpoints spread evenly over the sphere (Fibonacci
   lattice) at ``image_size``² pixels, the object filling about ``fill`` of the image.
2. Detect SIFT keypoints (``cv2.SIFT_create``) on each grey image, inside the object's mask eroded
   by 2 px (no background corners).
3. Lift each keypoint to 3D with the rendered depth (:func:`kpd6d.geometry.backproject`) and map it
   to the model frame.
4. Cluster the lifted points across views (greedy, strongest response first, radius
   ``cluster_radius`` × diameter).
5. Rank clusters by repeatability (number of distinct views that found them), then by summed response.
6. Snap cluster centres to the surface (trimesh closest point) and select ``num_keypoints`` with
   spatial non-maximum suppression (``min_distance`` × diameter), symmetry-aware when asked (or
   when the model lists symmetries). If fewer clusters survive, the rest are filled by
   farthest-point sampling of the surface and a warning is logged.

An untextured mesh still gets keypoints: the renders are shaded by a directional light, and SIFT
responds to shading changes at creases and corners (fewer and less repeatable than on texture).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from kpd6d.geometry import backproject, invert_pose, look_at_pose, transform_points
from kpd6d.keypoints.sampling import PointMetric, farthest_point_sampling, nms_select, uses_symmetry

__all__ = ["SiftDesignator", "fibonacci_sphere", "snap_to_surface"]

log = logging.getLogger(__name__)


def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` unit vectors (n, 3) spread evenly over the sphere."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, 1.0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def snap_to_surface(mesh, points: np.ndarray) -> np.ndarray:
    """Closest points on the mesh surface (trimesh) to ``points`` (N, 3)."""
    import trimesh

    if len(points) == 0:
        return np.zeros((0, 3))
    closest, _, _ = trimesh.proximity.closest_point(mesh, np.asarray(points, dtype=np.float64))
    return np.asarray(closest, dtype=np.float64)


@dataclass
class SiftDesignator:
    """SIFT surface keypoints; parameters as in ``conf/designator/sift.yaml``."""

    num_keypoints: int = 50
    num_views: int = 60
    image_size: int = 256
    fill: float = 0.8
    cluster_radius: float = 0.025
    min_distance: float = 0.05
    max_candidates: int = 1500
    contrast_threshold: float = 0.03
    symmetry_aware: bool | None = None
    num_surface_samples: int = 5000
    seed: int = 0

    def __post_init__(self) -> None:
        if int(self.num_keypoints) < 1:
            raise ValueError(f"sift: num_keypoints must be >= 1, got {self.num_keypoints!r}")
        if int(self.num_views) < 1:
            raise ValueError(f"sift: num_views must be >= 1, got {self.num_views!r}")
        if int(self.image_size) < 32:
            raise ValueError(f"sift: image_size must be >= 32 px, got {self.image_size!r}")
        if not 0.1 <= float(self.fill) <= 1.0:
            raise ValueError(f"sift: fill must be in [0.1, 1], got {self.fill!r}")
        self.last_stats: dict = {}

    # -- stages -------------------------------------------------------------------------------
    def views(self, model) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
        """Intrinsics K and the (R, t) of every view."""
        D = float(model.diameter)
        centre = model.bbox_min + model.bbox_size / 2.0
        dist = 2.5 * D
        S = int(self.image_size)
        f = self.fill * S * (dist - D / 2.0) / D
        K = np.array([[f, 0.0, (S - 1) / 2.0], [0.0, f, (S - 1) / 2.0], [0.0, 0.0, 1.0]])
        poses = [look_at_pose(centre + dist * d, centre) for d in fibonacci_sphere(int(self.num_views))]
        return K, poses

    def detect(self, model, renderer=None):
        """Lifted SIFT detections: (points (N, 3) model frame, responses (N,), view index (N,))."""
        import cv2

        from kpd6d.render import Renderer

        K, poses = self.views(model)
        S = int(self.image_size)
        own = renderer is None
        r = Renderer(S, S, K) if own else renderer
        sift = cv2.SIFT_create(contrastThreshold=float(self.contrast_threshold))
        kernel = np.ones((5, 5), np.uint8)
        pts, resp, view = [], [], []
        try:
            for vi, (R, t) in enumerate(poses):
                out = r.render([(model, R, t)], K=K)
                mask = cv2.erode((out.depth > 0).astype(np.uint8), kernel)
                if not mask.any():
                    continue
                gray = cv2.cvtColor(out.rgb, cv2.COLOR_RGB2GRAY)
                kps = sift.detect(gray, mask)
                if not kps:
                    continue
                uv = np.array([kp.pt for kp in kps], dtype=np.float64)
                ij = np.clip(np.rint(uv).astype(int), 0, S - 1)
                z = out.depth[ij[:, 1], ij[:, 0]].astype(np.float64)
                ok = z > 0
                if not ok.any():
                    continue
                pc = backproject(uv[ok], z[ok], K)
                Ri, ti = invert_pose(R, t)
                pts.append(transform_points(pc, Ri, ti))
                resp.append(np.array([kp.response for kp in kps], dtype=np.float64)[ok])
                view.append(np.full(int(ok.sum()), vi))
        finally:
            if own:
                r.close()
        if not pts:
            return np.zeros((0, 3)), np.zeros(0), np.zeros(0, int)
        return np.concatenate(pts), np.concatenate(resp), np.concatenate(view)

    def cluster(self, points, responses, views, radius: float):
        """Greedy clustering; returns (centres (M, 3), n_views (M,), summed responses (M,)) ranked best first."""
        from scipy.spatial import cKDTree

        if len(points) == 0:
            return np.zeros((0, 3)), np.zeros(0, int), np.zeros(0)
        order = np.argsort(-responses, kind="stable")
        tree = cKDTree(points)
        label = np.full(len(points), -1)
        centres, nviews, score = [], [], []
        for i in order:
            if label[i] >= 0:
                continue
            members = np.array([j for j in tree.query_ball_point(points[i], radius) if label[j] < 0])
            label[members] = len(centres)
            centres.append(points[members].mean(axis=0))
            nviews.append(len(np.unique(views[members])))
            score.append(float(responses[members].sum()))
        centres, nviews, score = np.asarray(centres), np.asarray(nviews), np.asarray(score)
        rank = np.lexsort((-score, -nviews))  # by views, then response
        return centres[rank], nviews[rank], score[rank]

    # -- the designator -----------------------------------------------------------------------
    def __call__(self, model, renderer=None) -> np.ndarray:
        k = int(self.num_keypoints)
        D = float(model.diameter)
        metric = PointMetric(model, symmetric=uses_symmetry(model, self.symmetry_aware))
        pts, resp, view = self.detect(model, renderer)
        centres, nviews, _ = self.cluster(pts, resp, view, self.cluster_radius * D)
        cand = snap_to_surface(model.mesh, centres[: int(self.max_candidates)])
        min_d = self.min_distance * D
        sel = nms_select(cand, k, min_d, metric) if len(cand) else []
        chosen = cand[sel] if sel else np.zeros((0, 3))
        n_sift = len(chosen)
        if n_sift < k:
            samples = model.sample_points(int(self.num_surface_samples), seed=int(self.seed))
            extra = farthest_point_sampling(samples, k - n_sift, metric=metric,
                                            initial=chosen if n_sift else None,
                                            start=None if n_sift else model.bbox_min + model.bbox_size / 2)
            chosen = np.concatenate([chosen, samples[extra]]) if n_sift else samples[extra]
            log.warning(
                "sift: object %s has only %d SIFT clusters %.1f mm apart (of %d requested); filled %d by "
                "farthest-point sampling (min distance now %.1f mm)",
                getattr(model, "obj_id", "?"), n_sift, min_d, k, k - n_sift, metric.min_pairwise(chosen),
            )
        self.last_stats = {
            "detections": len(pts), "clusters": len(centres), "sift_keypoints": n_sift,
            "filled": k - n_sift, "views_of_selected": nviews[sel].tolist(),
        }
        return chosen
