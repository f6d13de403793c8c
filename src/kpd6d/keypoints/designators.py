"""Keypoint designators (``DESIGNATORS``): ``sift``, ``bbox_corners``, ``fps``.

``DESIGNATORS.build(name, num_keypoints=k, **params)(model) -> np.ndarray (k, 3)`` in the model
frame (mm). Every designator takes ``symmetry_aware`` (None: on when the model lists symmetries):
no two selected points then map onto each other (within ``min_distance`` × diameter) under a
symmetry of the object.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from kpd6d.keypoints.sampling import PointMetric, farthest_point_sampling, uses_symmetry
from kpd6d.keypoints.sift import SiftDesignator
from kpd6d.registry import DESIGNATORS

__all__ = ["BboxCornersDesignator", "FpsDesignator", "SiftDesignator"]

log = logging.getLogger(__name__)


@dataclass
class BboxCornersDesignator:
    """The 8 corners of the tight axis-aligned 3D box plus its centre (k = 9; BB8 / Tekin et al.).

    The set is fixed, so it cannot be made symmetry-aware: ``symmetry_aware=True`` raises, and for a
    symmetric model (``symmetry_aware=None``) a warning says that corners map onto each other.
    """

    num_keypoints: int = 9
    symmetry_aware: bool | None = None

    def __post_init__(self) -> None:
        if int(self.num_keypoints) != 9:
            raise ValueError(
                f"bbox_corners gives exactly 9 keypoints (8 box corners + centre); got num_keypoints="
                f"{self.num_keypoints!r}. Use 'fps' or 'sift' for another number."
            )
        if self.symmetry_aware:
            raise ValueError(
                "bbox_corners cannot be symmetry-aware (its 9 points are fixed and a symmetric object's "
                "corners map onto each other); use 'fps' or 'sift' with symmetry_aware=True"
            )

    def __call__(self, model) -> np.ndarray:
        if self.symmetry_aware is None and getattr(model, "is_symmetric", False):
            log.warning("bbox_corners: object %s is symmetric; its box corners map onto each other",
                        getattr(model, "obj_id", "?"))
        centre = model.bbox_min + model.bbox_size / 2.0
        return np.concatenate([model.bbox_corners, centre[None]], axis=0)


@dataclass
class FpsDesignator:
    """Farthest-point sampling on the surface (PVNet): ``num_surface_samples`` surface points,
    distances initialised from the box centre (which is not returned), then k farthest points."""

    num_keypoints: int = 8
    num_surface_samples: int = 5000
    symmetry_aware: bool | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        if int(self.num_keypoints) < 1:
            raise ValueError(f"fps: num_keypoints must be >= 1, got {self.num_keypoints!r}")
        if int(self.num_surface_samples) < int(self.num_keypoints):
            raise ValueError(f"fps: num_surface_samples ({self.num_surface_samples}) < num_keypoints ({self.num_keypoints})")

    def __call__(self, model) -> np.ndarray:
        samples = model.sample_points(int(self.num_surface_samples), seed=int(self.seed))
        metric = PointMetric(model, symmetric=uses_symmetry(model, self.symmetry_aware))
        centre = model.bbox_min + model.bbox_size / 2.0
        idx = farthest_point_sampling(samples, int(self.num_keypoints), start=centre, metric=metric)
        return samples[idx]


@DESIGNATORS.register("bbox_corners")
def _bbox_corners(num_keypoints: int = 9, symmetry_aware: bool | None = None) -> BboxCornersDesignator:
    return BboxCornersDesignator(num_keypoints=num_keypoints, symmetry_aware=symmetry_aware)


@DESIGNATORS.register("fps")
def _fps(num_keypoints: int = 8, num_surface_samples: int = 5000, symmetry_aware: bool | None = None,
         seed: int = 0) -> FpsDesignator:
    return FpsDesignator(num_keypoints, num_surface_samples, symmetry_aware, seed)


@DESIGNATORS.register("sift")
def _sift(num_keypoints: int = 50, num_views: int = 60, image_size: int = 256, fill: float = 0.8,
          cluster_radius: float = 0.025, min_distance: float = 0.05, max_candidates: int = 1500,
          contrast_threshold: float = 0.03, symmetry_aware: bool | None = None,
          num_surface_samples: int = 5000, seed: int = 0) -> SiftDesignator:
    return SiftDesignator(num_keypoints, num_views, image_size, fill, cluster_radius, min_distance,
                          max_candidates, contrast_threshold, symmetry_aware, num_surface_samples, seed)
