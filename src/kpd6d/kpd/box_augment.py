"""Box augmentation for KPD training crops: ``jitter`` (default) and ``pgpg``.

Both take a box (x, y, w, h) in pixels and a ``numpy.random.Generator`` and return a perturbed box.

* ``jitter`` — centre shift ``U(−shift, shift)`` × (w, h) and size factors ``exp(U(−log(1+scale), log(1+scale)))``.
* ``pgpg`` — RMPE's pose-guided proposal generator: offsets drawn from the empirical distribution of
  a detector's box errors relative to ground truth, measured by the detector stage on a validation
  set. The statistics, their offset parametrisation and their file format are :mod:`kpd6d.box_errors`
  (re-exported here so old imports keep working).
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import numpy as np

from kpd6d.box_errors import (
    STATS_FORMAT,
    BoxErrorStatsError,
    apply_offsets,
    box_offsets,
    fit_box_error_stats,
    load_box_error_stats,
    save_box_error_stats,
    validate_box_error_stats,
)
from kpd6d.registry import BOX_AUGMENTS

__all__ = [
    "BOX_AUGMENTS",
    "STATS_FORMAT",
    "BoxErrorStatsError",
    "BoxJitter",
    "BoxPGPG",
    "apply_offsets",
    "box_offsets",
    "build_box_augment",
    "fit_box_error_stats",
    "jitter",
    "load_box_error_stats",
    "pgpg",
    "save_box_error_stats",
]


class BoxJitter:
    """Scale and shift noise (the default box augmentation)."""

    def __init__(self, shift: float = 0.1, scale: float = 0.1) -> None:
        if shift < 0 or scale < 0:
            raise ValueError(f"jitter: shift and scale must be >= 0, got shift={shift}, scale={scale}")
        self.shift, self.scale = float(shift), float(scale)

    def __call__(self, box, rng: np.random.Generator, obj_id: int | None = None) -> np.ndarray:
        ls = np.log1p(self.scale)
        off = np.concatenate([rng.uniform(-self.shift, self.shift, 2), rng.uniform(-ls, ls, 2)])
        return apply_offsets(box, off)


class BoxPGPG:
    """Offsets resampled from a detector's empirical box errors (per object when the stats have it)."""

    def __init__(self, stats: str | os.PathLike | Mapping, per_object: bool = True, min_per_object: int = 20) -> None:
        self.stats = load_box_error_stats(stats) if isinstance(stats, (str, os.PathLike)) else validate_box_error_stats(stats, "pgpg stats")
        self.per_object = per_object
        self.min_per_object = int(min_per_object)

    def __call__(self, box, rng: np.random.Generator, obj_id: int | None = None) -> np.ndarray:
        pool = self.stats["offsets"]
        if self.per_object and obj_id is not None:
            own = self.stats["per_object"].get(int(obj_id))
            if own is not None and len(own) >= self.min_per_object:
                pool = own
        return apply_offsets(box, pool[rng.integers(len(pool))])


@BOX_AUGMENTS.register("jitter")
def jitter(shift: float = 0.1, scale: float = 0.1) -> BoxJitter:
    return BoxJitter(shift=shift, scale=scale)


@BOX_AUGMENTS.register("pgpg")
def pgpg(stats: str | os.PathLike | Mapping, per_object: bool = True, min_per_object: int = 20) -> BoxPGPG:
    return BoxPGPG(stats, per_object=per_object, min_per_object=min_per_object)


@BOX_AUGMENTS.register("none")
def _none():
    return None


def build_box_augment(cfg: Mapping | None):
    """``{"name": "jitter"|"pgpg"|"none", ...params}`` → a box augmenter (or None)."""
    if cfg is None:
        return None
    params = dict(cfg)
    name = params.pop("name", None)
    if name not in BOX_AUGMENTS:
        raise ValueError(f"unknown box augmentation {name!r}; known: {', '.join(BOX_AUGMENTS.names())}")
    return BOX_AUGMENTS.build(name, **params)
