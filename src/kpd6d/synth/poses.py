"""Pose sampling for synthetic scenes: viewpoints on a sphere around the object, placed in the image.

A viewpoint is (azimuth about the model's z axis, elevation from its x-y plane, distance, in-plane
rotation); :func:`kpd6d.geometry.pose_from_view` turns it into a rotation. The object is then moved
so that its bounding-box centre projects to a random pixel at depth = the sampled distance, and the
pose is re-sampled while its projected box leaves the image by more than ``view_margin`` (a fraction
of the box size).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from kpd6d.geometry import bbox_from_points, pose_from_view, project_points

__all__ = ["ModelGeometry", "ViewRanges", "place_in_image", "projected_box", "sample_object_pose", "sample_view_rotation"]


@dataclass(frozen=True)
class ViewRanges:
    """Sampling ranges: distance in mm, angles in degrees."""

    distance: tuple[float, float] = (346.0, 1500.0)
    elevation: tuple[float, float] = (-15.0, 90.0)
    azimuth: tuple[float, float] = (0.0, 360.0)
    inplane: tuple[float, float] = (-45.0, 45.0)

    def __post_init__(self) -> None:
        for name in ("distance", "elevation", "azimuth", "inplane"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
                raise ValueError(f"{name}_range must be [low, high] with low <= high, got {[lo, hi]}")
        if self.distance[0] <= 0:
            raise ValueError(f"distance_range must be positive (mm), got {list(self.distance)}")
        if self.elevation[0] < -90 or self.elevation[1] > 90:
            raise ValueError(f"elevation_range must lie in [-90, 90] degrees, got {list(self.elevation)}")


class ModelGeometry:
    """Per-model values the sampler needs, computed once: convex-hull vertices (their projected box
    equals that of all vertices: perspective projection maps convex hulls to convex hulls) and the
    bounding-box centre."""

    def __init__(self, model) -> None:
        v = np.asarray(model.vertices, dtype=np.float64)
        self.center = (v.min(axis=0) + v.max(axis=0)) / 2.0
        self.radius = float(np.linalg.norm(v - self.center, axis=1).max())
        pts = v
        if len(v) > 64:
            try:
                from scipy.spatial import ConvexHull

                pts = v[ConvexHull(v).vertices]
            except Exception:  # flat / degenerate meshes: keep every vertex
                pts = v
        self.hull = pts


def sample_view_rotation(rng: np.random.Generator, ranges: ViewRanges) -> np.ndarray:
    """Rotation of a camera looking at the model origin from a random viewpoint within ``ranges``.

    Elevation is sampled uniformly on the sphere (uniform in sin(elevation)), azimuth and in-plane
    angle uniformly.
    """
    s_lo, s_hi = (math.sin(math.radians(a)) for a in ranges.elevation)
    el = math.asin(rng.uniform(s_lo, s_hi))
    az = math.radians(rng.uniform(*ranges.azimuth))
    ip = math.radians(rng.uniform(*ranges.inplane))
    R, _ = pose_from_view(az, el, 1000.0, ip)
    return R


def projected_box(geom: ModelGeometry, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, float]:
    """(x, y, w, h) box of the projected hull (float px) and the smallest vertex depth (mm)."""
    uv, z = project_points(geom.hull, K, R, t, return_depth=True)
    return bbox_from_points(uv), float(z.min())


def _inside(box: np.ndarray, width: int, height: int, margin: float) -> bool:
    x, y, w, h = box
    mx, my = margin * w, margin * h
    return x >= -mx and y >= -my and x + w <= width - 1 + mx and y + h <= height - 1 + my


def place_in_image(rng: np.random.Generator, geom: ModelGeometry, R: np.ndarray, z: float, K: np.ndarray,
                   width: int, height: int, view_margin: float, tries: int = 8,
                   znear: float = 10.0) -> np.ndarray | None:
    """Translation putting the box centre at a random pixel at depth ``z`` with the projected box
    inside the image (up to ``view_margin`` of its size outside); ``None`` if no try succeeds."""
    Kinv = np.linalg.inv(K)
    for _ in range(tries):
        u, v = rng.uniform(0, width - 1), rng.uniform(0, height - 1)
        t = z * (Kinv @ np.array([u, v, 1.0])) - R @ geom.center
        box, zmin = projected_box(geom, K, R, t)
        if zmin > znear and _inside(box, width, height, view_margin):
            return t
    return None


def sample_object_pose(rng: np.random.Generator, geom: ModelGeometry, K: np.ndarray, width: int, height: int,
                       ranges: ViewRanges, view_margin: float = 0.1, max_tries: int = 50,
                       znear: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Random (R, t) within ``ranges`` with the object in view.

    If no sample lands in view after ``max_tries`` viewpoints (e.g. an object too large for the
    distance range), the last one is centred on the principal point at the far end of the range.
    """
    R = np.eye(3)
    for _ in range(max_tries):
        R = sample_view_rotation(rng, ranges)
        z = rng.uniform(*ranges.distance)
        t = place_in_image(rng, geom, R, z, K, width, height, view_margin, znear=znear)
        if t is not None:
            return R, t
    z = max(ranges.distance[1], geom.radius + 2 * znear)
    t = z * (np.linalg.inv(K) @ np.array([K[0, 2], K[1, 2], 1.0])) - R @ geom.center
    return R, t
