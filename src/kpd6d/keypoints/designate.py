"""Designate keypoints for a set of objects with a JSON cache, and draw keypoint overview images.

:func:`designate_objects` runs a designator over models, writing every result to a keypoint file
(:mod:`kpd6d.keypoints.io`) as soon as it is computed, so an interrupted run resumes where it
stopped. An object is taken from the file instead of recomputed when the file was made by the same
designator with the same parameters and the object's mesh fingerprint matches.

:func:`render_overview` renders an object from several views and draws its keypoints: visible ones
as filled green dots, ones on the far side (occluded by the object itself) as hollow red rings.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kpd6d.geometry import look_at_pose, project_points, transform_points
from kpd6d.keypoints.io import (
    KeypointFileError,
    _jsonable,
    model_fingerprint,
    read_keypoint_file,
    save_keypoints,
)
from kpd6d.registry import DESIGNATORS

__all__ = ["designate_objects", "render_overview"]

log = logging.getLogger(__name__)


def _same_params(a: dict, b: dict) -> bool:
    import json

    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def designate_objects(models: Sequence, designator: str, params: dict[str, Any], cache_path: str | os.PathLike,
                      *, progress: bool = True) -> tuple[dict[int, np.ndarray], list[int]]:
    """Keypoints ``{obj_id: (k, 3)}`` for ``models`` by ``DESIGNATORS.build(designator, **params)``.

    Results are cached in ``cache_path`` (a keypoint JSON file). Returns the keypoints and the ids
    taken from the cache.
    """
    from tqdm.auto import tqdm

    params = _jsonable(dict(params))
    build = DESIGNATORS.build(designator, **params)  # fails early on unknown names / parameters
    cache_path = Path(cache_path)
    points: dict[int, np.ndarray] = {}
    fingerprints: dict[int, str] = {}
    if cache_path.is_file():
        try:
            cached = read_keypoint_file(cache_path)
        except KeypointFileError as exc:
            log.warning("ignoring unreadable keypoint cache: %s", exc)
        else:
            if cached.designator == designator and _same_params(cached.params, params):
                points, fingerprints = dict(cached.points), dict(cached.fingerprints)
            else:
                log.info("%s was made by %s %s; recomputing with %s %s", cache_path, cached.designator,
                         cached.params, designator, params)
    out: dict[int, np.ndarray] = {}
    reused: list[int] = []
    bar = tqdm(models, desc=f"designate ({designator})", unit="object", disable=not progress)
    for model in bar:
        oid = int(model.obj_id)
        fp = model_fingerprint(model)
        bar.set_postfix(obj=oid)
        if oid in points and fingerprints.get(oid) == fp:
            out[oid] = points[oid]
            reused.append(oid)
            continue
        out[oid] = np.asarray(build(model), dtype=np.float64)
        points[oid], fingerprints[oid] = out[oid], fp
        save_keypoints(cache_path, points, designator=designator, params=params, fingerprints=fingerprints)
    return out, reused


def _overview_views(n: int) -> list[tuple[float, float]]:
    """(azimuth, elevation) in radians: a ring around the object at alternating elevations."""
    return [(2 * math.pi * i / n, math.radians(35.0 if i % 2 == 0 else -20.0)) for i in range(n)]


def render_overview(model, points: np.ndarray, *, num_views: int = 6, image_size: int = 320,
                    renderer=None, title: str | None = None) -> np.ndarray:
    """RGB image (uint8) tiling ``num_views`` renders of ``model`` with ``points`` drawn on them.

    A keypoint is drawn as visible (filled green dot) when the rendered depth at its pixel is within
    2% of the diameter of its own depth, else as occluded (hollow red ring).
    """
    import cv2

    from kpd6d.render import Renderer

    D = float(model.diameter)
    centre = model.bbox_min + model.bbox_size / 2.0
    S = int(image_size)
    dist = 2.5 * D
    f = 0.85 * S * (dist - D / 2.0) / D
    K = np.array([[f, 0.0, (S - 1) / 2.0], [0.0, f, (S - 1) / 2.0], [0.0, 0.0, 1.0]])
    own = renderer is None
    r = Renderer(S, S, K) if own else renderer
    tiles = []
    pts = np.asarray(points, dtype=np.float64)
    radius = max(2, S // 80)
    try:
        for az, el in _overview_views(int(num_views)):
            eye = centre + dist * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
            R, t = look_at_pose(eye, centre)
            res = r.render([(model, R, t)], K=K)
            img = np.ascontiguousarray(res.rgb.copy())
            uv = project_points(pts, K, R, t)
            z = transform_points(pts, R, t)[:, 2]
            for (u, v), zi in zip(uv, z):
                iu, iv = round(u), round(v)
                if not (0 <= iu < S and 0 <= iv < S):
                    continue
                d = res.depth[iv, iu]
                visible = d > 0 and abs(d - zi) < 0.02 * D
                if visible:
                    cv2.circle(img, (iu, iv), radius + 1, (0, 0, 0), -1, cv2.LINE_AA)
                    cv2.circle(img, (iu, iv), radius, (40, 255, 40), -1, cv2.LINE_AA)
                else:
                    cv2.circle(img, (iu, iv), radius, (255, 60, 60), 1, cv2.LINE_AA)
            tiles.append(img)
    finally:
        if own:
            r.close()
    cols = min(3, math.ceil(math.sqrt(len(tiles))))
    rows = math.ceil(len(tiles) / cols)
    while len(tiles) < rows * cols:
        tiles.append(np.zeros_like(tiles[0]))
    grid = np.concatenate([np.concatenate(tiles[i * cols:(i + 1) * cols], axis=1) for i in range(rows)], axis=0)
    if title:
        cv2.putText(grid, title, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        cv2.putText(grid, "filled: visible   ring: far side", (6, grid.shape[0] - 8),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return grid
