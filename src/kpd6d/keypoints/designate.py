"""The one designation path: keypoints for a set of objects, cached in a keypoint JSON file, and overview images.

:func:`designate_objects` runs a designator over models (with per-object parameter overrides, e.g.
17 keypoints on the eggbox), writing every result to a keypoint file (:mod:`kpd6d.keypoints.io`) as
soon as it is computed, so an interrupted run resumes where it stopped. An object is taken from the
file instead of recomputed when the file was made by the same designator with the same parameters
and (unless fingerprints are off) the object's mesh fingerprint matches. ``kpd6d-designate``
(:func:`designate_from_config`), ``kpd6d-run`` (:mod:`kpd6d.workflow`) and the data generator
(:mod:`kpd6d.synth.generate`) all designate through it.

:func:`render_overview` renders an object from several views and draws its keypoints: visible ones
as filled green dots, ones on the far side (occluded by the object itself) as hollow red rings;
:func:`write_overviews` writes one such PNG per object.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Sequence
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

__all__ = ["designate_from_config", "designate_objects", "designator_name_params", "render_overview",
           "write_overviews"]

log = logging.getLogger(__name__)


def _same_params(a: dict, b: dict) -> bool:
    import json

    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def designator_name_params(cfg, where: str = "designator") -> tuple[str, dict[str, Any]]:
    """``(name, params)`` of a designator config node (``{"name": ..., **params}``, conf/designator/).

    Parameters that should be numbers and are not raise :class:`kpd6d.config.ConfigError` naming
    ``<where>.<parameter>`` and the value (``designator.num_keypoints=abc``)."""
    from kpd6d.config import check_number_fields
    from kpd6d.registry import DESIGNATORS

    params = _jsonable(dict(cfg or {}))
    if "name" not in params:
        raise KeyError(f"the designator config has no 'name' (got keys {sorted(params)})")
    name = params.pop("name")
    if name in DESIGNATORS:
        check_number_fields(params, DESIGNATORS.get(name), where)
    return name, params


def designate_objects(models: Sequence, designator: str, params: dict[str, Any], cache_path: str | os.PathLike,
                      *, per_object: dict | None = None, fingerprints: bool = True, progress: bool = True,
                      on_designated: Callable[[int, np.ndarray, float], None] | None = None,
                      ) -> tuple[dict[int, np.ndarray], list[int]]:
    """Keypoints ``{obj_id: (k, 3)}`` for ``models`` by ``DESIGNATORS.build(designator, **params)``.

    Results are cached in ``cache_path`` (a keypoint JSON file), written after each object.
    ``per_object`` maps an object id to parameter overrides for that object; they are recorded in
    the file's parameters (``params["per_object"]``). ``fingerprints``: record each mesh's
    fingerprint and take an object from the cache only when it matches; False: take it by id (the
    file of a ``kpd6d-run`` folder, which records none). ``on_designated(obj_id, points, seconds)``
    is called after each object that was computed. Returns the keypoints and the ids taken from the cache.
    """
    from tqdm.auto import tqdm

    params = _jsonable(dict(params))
    overrides = {int(k): dict(v) for k, v in (_jsonable(per_object or {})).items()}
    recorded = dict(params)
    if overrides:
        recorded["per_object"] = {str(k): v for k, v in sorted(overrides.items())}
    build = DESIGNATORS.build(designator, **params)  # fails early on unknown names / parameters
    if designator in DESIGNATORS:
        from kpd6d.config import check_number_fields

        for oid, over in overrides.items():  # wrong types name designator_per_object.<id>.<parameter>
            check_number_fields(over, DESIGNATORS.get(designator), f"designator_per_object.{oid}")
    builds = {oid: DESIGNATORS.build(designator, **{**params, **over}) for oid, over in overrides.items()}
    cache_path = Path(cache_path)
    points: dict[int, np.ndarray] = {}
    fps: dict[int, str] = {}
    if cache_path.is_file():
        try:
            cached = read_keypoint_file(cache_path)
        except KeypointFileError as exc:
            log.warning("ignoring unreadable keypoint cache: %s", exc)
        else:
            if cached.designator == designator and _same_params(cached.params, recorded):
                points, fps = dict(cached.points), dict(cached.fingerprints)
            else:
                log.info("%s was made by %s %s; recomputing with %s %s", cache_path, cached.designator,
                         cached.params, designator, recorded)
    out: dict[int, np.ndarray] = {}
    reused: list[int] = []
    bar = tqdm(models, desc=f"designate ({designator})", unit="object", disable=not progress)
    for model in bar:
        oid = int(model.obj_id)
        fp = model_fingerprint(model) if fingerprints else None
        bar.set_postfix(obj=oid)
        if oid in points and (not fingerprints or fps.get(oid) == fp):
            out[oid] = points[oid]
            reused.append(oid)
            continue
        t0 = time.time()
        out[oid] = np.asarray(builds.get(oid, build)(model), dtype=np.float64)
        points[oid] = out[oid]
        if fingerprints:
            fps[oid] = fp
        save_keypoints(cache_path, points, designator=designator, params=recorded, fingerprints=fps)
        if on_designated is not None:
            on_designated(oid, out[oid], time.time() - t0)
    return out, reused


def write_overviews(models: Sequence, points: dict[int, np.ndarray], out_dir: str | os.PathLike, designator: str,
                    *, num_views: int = 6, image_size: int = 320, progress: bool = True) -> list[Path]:
    """``<out_dir>/obj_XXXXXX.png`` per model: :func:`render_overview` of its ``points``; returns the paths."""
    from tqdm.auto import tqdm

    from kpd6d.io import atomic_write_image
    from kpd6d.render import Renderer

    size = int(image_size)
    written = []
    renderer = Renderer(size, size)  # one OpenGL context for all objects (K is set per object)
    try:
        for m in tqdm(models, desc="overview PNGs", unit="object", disable=not progress):
            title = f"obj {m.obj_id} {m.name}: {len(points[m.obj_id])} {designator} keypoints"
            img = render_overview(m, points[m.obj_id], num_views=int(num_views), image_size=size, title=title,
                                  renderer=renderer)
            written.append(atomic_write_image(Path(out_dir) / f"obj_{m.obj_id:06d}.png", img))
    finally:
        renderer.close()
    return written


DESIGNATE_SETTINGS = ("designator", "out_dir", "cache_name", "models_dir", "obj_ids", "procedural_seed", "overview",
                      "progress")


def designate_from_config(cfg) -> tuple[Path, dict[int, np.ndarray], list[int]]:
    """Designate with a composed ``conf/designate.yaml``: the objects of a BOP models folder (or the
    procedural set) into ``<out_dir>/<cache_name>``, plus the overview PNGs. Returns the keypoint
    file, the keypoints and the ids taken from the cache."""
    from omegaconf import OmegaConf

    from kpd6d.config import cfg_int
    from kpd6d.objects import load_bop_models, procedural_objects

    c = OmegaConf.to_container(cfg, resolve=True) if OmegaConf.is_config(cfg) else dict(cfg)
    c.pop("hydra", None)
    unknown = sorted(set(c) - set(DESIGNATE_SETTINGS))
    if unknown:
        raise TypeError(f"kpd6d-designate: unknown setting(s) {unknown}; known: {sorted(DESIGNATE_SETTINGS)}")
    try:
        name, params = designator_name_params(c["designator"])
    except KeyError as exc:
        raise KeyError(f"kpd6d-designate: {exc.args[0]}") from None
    obj_ids = c.get("obj_ids")
    if c.get("models_dir"):
        models = load_bop_models(c["models_dir"], obj_ids=obj_ids)
    else:
        models = procedural_objects(seed=cfg_int(c, "procedural_seed", 0), obj_ids=obj_ids)
    out_dir = Path(c["out_dir"])
    out_dir.mkdir(parents=True, exist_ok=True)
    cache = out_dir / c.get("cache_name", "keypoints.json")
    progress = bool(c.get("progress", True))
    points, reused = designate_objects(models, name, params, cache, progress=progress)
    ov = c.get("overview") or {}
    if ov.get("enabled", True):
        write_overviews(models, points, out_dir, name, num_views=cfg_int(c, "overview.num_views", 6),
                        image_size=cfg_int(c, "overview.image_size", 320), progress=progress)
    return cache, points, reused


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
