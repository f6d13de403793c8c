"""Compose one synthetic image: sample poses, render all objects and occluders in one scene (so that
mutual occlusion is right), paste them over a background, and compute the BOP ground truth.

Passes (``antialias: false``, the default): a colour pass of everything, whose depth (single-sampled)
is the pixel-centre depth of the whole scene, and a segmentation pass of the objects alone; an
object's visible mask is its objects-alone mask minus the pixels where the full scene is nearer
(an occluder in front), and its objects-alone mask is its silhouette as far as occluders go. An
object-alone pass is only added when other objects may cover it or it leaves the image, and objects
whose boxes are disjoint share one such pass (:func:`silhouette_counts_many`). With
``antialias: true`` the colour pass is multisampled (its depth is not pixel-centre exact), so a
segmentation pass of the whole scene gives the masks instead.

Ground truth follows bop_toolkit's ``calc_gt_info``: ``bbox_obj`` is the box of the whole silhouette
(including any part outside the image; here from the projected model vertices, as pixel indices:
``x = ceil(u_min)``, ``w = floor(u_max) - x``; ``[-1, -1, -1, -1]`` when nothing is visible, as
bop_toolkit does), ``px_count_all`` the whole silhouette's pixel count
(also outside the image), ``px_count_valid`` the silhouette's pixels inside the image (all of which
have rendered depth), ``px_count_visib`` the visible-mask pixels, ``visib_fract = visib / all``.

``layout: tabletop`` (:mod:`kpd6d.synth.tabletop`) adds a textured table plane to the colour pass only,
so it shows in rgb and depth but is never an occluder: the segmentation passes do not draw it, and
the two-pass rule ignores the pixels whose colour-pass depth is the table plane's (the objects stand
on it; at the contact line its depth ties with theirs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from kpd6d.data.bop_io import bbox_from_mask
from kpd6d.geometry import bbox_from_points, project_points
from kpd6d.synth.config import SynthConfig
from kpd6d.synth.photometric import PhotometricConfig, apply_photometric, surface_detail
from kpd6d.synth.poses import ModelGeometry, _inside, projected_box, sample_object_pose
from kpd6d.synth.room import make_room
from kpd6d.synth.tabletop import (
    RestingPoses,
    TableScene,
    depth_tolerance,
    footprint,
    make_table_mesh,
    plane_depth,
    shadow_pose,
    table_camera,
)

__all__ = ["SceneComposer", "SceneInstance", "SceneSample", "silhouette_counts", "silhouette_counts_many"]

_GAP = 1.0  # mm: least clearance between footprints on the table (and of floating occluders above it)


@dataclass
class SceneInstance:
    obj_id: int
    R: np.ndarray
    t: np.ndarray
    mask_visib: np.ndarray  # (H, W) bool
    bbox_obj: list[int]
    bbox_visib: list[int]
    px_count_all: int
    px_count_valid: int
    px_count_visib: int
    visib_fract: float

    def gt(self) -> dict:
        return {"obj_id": self.obj_id, "R": self.R, "t": self.t}

    def info(self) -> dict:
        return {
            "bbox_obj": self.bbox_obj, "bbox_visib": self.bbox_visib, "px_count_all": self.px_count_all,
            "px_count_valid": self.px_count_valid, "px_count_visib": self.px_count_visib,
            "visib_fract": self.visib_fract,
        }


@dataclass
class SceneSample:
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 mm (objects and occluders; 0 on the background)
    K: np.ndarray
    instances: list[SceneInstance]
    attempts: int = 1
    table: TableScene | None = None  # layout tabletop: the table and the camera pose in the table frame
    distractor_items: list | None = None  # layout tabletop: the rendered occluders, (mesh, R, t)


def bbox_obj_from_uv(uv: np.ndarray) -> list[int]:
    """BOP box (x, y, w, h) of the silhouette of projected vertices ``uv`` (N, 2), as pixel indices
    (bop_toolkit's ``calc_2d_bbox`` of the rendered silhouette): with pixel centres at integer
    coordinates the covered pixels run from ``ceil(min)`` to ``floor(max)``."""
    x, y, w, h = bbox_from_points(uv)
    lo = np.ceil([x, y]).astype(np.int64)
    hi = np.floor([x + w, y + h]).astype(np.int64)
    w, h = (int(v) for v in np.maximum(hi - lo, 0))
    return [int(lo[0]), int(lo[1]), w, h]


def _hull_mask(uv: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """Mask of the window [y0:y1, x0:x1] covering the convex hull of pixels ``uv``, dilated by 1 px."""
    import cv2

    pts = np.round((uv - [x0, y0]) * 16).astype(np.int32)
    hull = cv2.convexHull(pts)
    m = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillConvexPoly(m, hull, 1, lineType=cv2.LINE_8, shift=4)
    return cv2.dilate(m, np.ones((3, 3), np.uint8)).astype(bool)


def silhouette_counts(renderer, model, R, t, K, width, height, bbox_obj) -> tuple[int, int]:
    """(pixels of the whole silhouette, pixels inside the image) of ``model`` at (R, t) rendered alone.

    Parts outside the image are counted by rendering tiles of the image plane (the principal point
    shifted by multiples of the image size) that cover ``bbox_obj``; tiles do not overlap, so the
    count is exact.
    """
    return silhouette_counts_many(renderer, [(model, R, t)], K, width, height, [bbox_obj])[0]


def _inside_image(bbox_obj, width: int, height: int) -> bool:
    """Whether the box (x, y, w, h), with 1 px of slack against rasterization ties, lies in the image."""
    x, y, w, h = bbox_obj
    return x >= 1 and y >= 1 and x + w <= width - 2 and y + h <= height - 2


def _grown_box(bbox_obj) -> tuple[int, int, int, int]:
    """``bbox_obj`` (x, y, w, h) grown by 1 px (rasterization ties) as inclusive (x0, y0, x1, y1)."""
    x, y, w, h = bbox_obj
    return x - 1, y - 1, x + w + 1, y + h + 1


def _disjoint(a, b) -> bool:
    return a[2] < b[0] or b[2] < a[0] or a[3] < b[1] or b[3] < a[1]


def silhouette_counts_many(renderer, items, K, width, height, boxes) -> list[tuple[int, int]]:
    """:func:`silhouette_counts` of several instances ``items`` (``(model, R, t)``) with boxes ``boxes``.

    A silhouette lies inside its instance's box (grown by 1 px), so instances whose grown boxes are
    pairwise disjoint cannot cover one another: they share one segmentation pass of the image
    (greedy grouping), and each instance's pixels in it are exactly those of a pass drawing it alone.
    Parts outside the image (other tiles) are counted per instance, as in :func:`silhouette_counts`.
    """
    grown = [_grown_box(b) for b in boxes]
    groups: list[list[int]] = []
    for i, g in enumerate(grown):
        for group in groups:
            if all(_disjoint(g, grown[j]) for j in group):
                group.append(i)
                break
        else:
            groups.append([i])
    inside = [0] * len(items)
    for group in groups:
        res = renderer.render([items[i] for i in group], K=K, depth_only=True)
        for m, i in zip(res.masks_visib, group):
            inside[i] = int(np.count_nonzero(m))
    out = []
    for i, (model, R, t) in enumerate(items):
        if _inside_image(boxes[i], width, height):  # wholly inside: one tile
            out.append((inside[i], inside[i]))
            continue
        x, y, w, h = boxes[i]
        kx = range(math.floor((x - 1) / width), math.floor((x + w + 1) / width) + 1)
        ky = range(math.floor((y - 1) / height), math.floor((y + h + 1) / height) + 1)
        total = inside[i]
        for a in kx:
            for b in ky:
                if a == 0 and b == 0:
                    continue
                Kt = np.array(K, dtype=np.float64)
                Kt[0, 2] -= a * width
                Kt[1, 2] -= b * height
                total += int(np.count_nonzero(renderer.render([(model, R, t)], K=Kt, depth_only=True).depth > 0))
        out.append((total, inside[i]))
    return out


class SceneComposer:
    """Makes :class:`SceneSample` s for one renderer, model set, background source and config."""

    def __init__(self, renderer, models, cfg: SynthConfig, backgrounds, distractors: list, symmetry_handlers=None):
        self.renderer = renderer
        self.models = list(models)
        if not self.models:
            raise ValueError("SceneComposer: no object models given")
        self.cfg = cfg
        self.K = cfg.camera_K()
        self.W, self.H = cfg.width, cfg.height
        self.backgrounds = backgrounds
        self.geoms = [ModelGeometry(m) for m in self.models]
        self._resting: dict[tuple[str, int], RestingPoses] = {}  # (kind, index) -> resting poses, made once
        self.distractors: list = []
        self.set_distractors(distractors)
        self.ranges = cfg.view_ranges()
        self.photometric: PhotometricConfig = cfg.photometric_config()
        self.symmetry = symmetry_handlers or [None] * len(self.models)

    def set_distractors(self, distractors: list) -> None:
        """Use the occluder meshes ``distractors`` from now on (a refreshed pool): the previous ones'
        geometry, resting poses and cached GL meshes are dropped."""
        for mesh in self.distractors:
            self._forget_mesh(mesh)
        self._resting = {k: v for k, v in self._resting.items() if k[0] != "distractor"}
        self.distractors = list(distractors)
        self.d_geoms = [ModelGeometry(d) for d in self.distractors]

    # -- sampling ----------------------------------------------------------------------------------
    def _choose_objects(self, rng) -> list[int]:
        n_models = len(self.models)
        if self.cfg.objects_per_image == "all":
            return list(range(n_models))
        lo, hi = self.cfg.objects_per_image
        n = int(rng.integers(lo, hi + 1))
        if n <= n_models:
            return sorted(int(i) for i in rng.choice(n_models, size=n, replace=False))
        return sorted(int(i) for i in rng.integers(0, n_models, size=n))

    def _object_pose(self, rng, k):
        R, t = sample_object_pose(rng, self.geoms[k], self.K, self.W, self.H, self.ranges, self.cfg.view_margin)
        handler = self.symmetry[k]
        if handler is not None:
            R, t = handler.canonicalize(R, t)
            R, t = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
        return R, t

    def _distractor_pose(self, rng, d_idx, target_box, target_z, target_radius):
        """Pose of distractor ``d_idx``: in front of a target (to occlude part of it) or, one time in
        four, anywhere in view as background clutter."""
        g = self.d_geoms[d_idx]
        from kpd6d.geometry import random_rotation

        R = random_rotation(rng)
        fx = self.K[0, 0]
        if target_box is None or rng.random() < 0.25:
            z = rng.uniform(*self.ranges.distance)
            u, v = rng.uniform(0, self.W - 1), rng.uniform(0, self.H - 1)
        else:
            x, y, w, h = target_box
            size_px = max(w, h) * rng.uniform(*self.cfg.distractor_size)
            z = fx * 2 * g.radius / max(size_px, 1.0)
            z = min(z, target_z - target_radius - g.radius)  # entirely in front of the target
            z = max(z, 3 * self.renderer.znear + g.radius)
            cx, cy = x + w / 2, y + h / 2
            u = cx + rng.uniform(-1, 1) * (w / 2 + 0.3 * size_px)
            v = cy + rng.uniform(-1, 1) * (h / 2 + 0.3 * size_px)
        t = z * (np.linalg.inv(self.K) @ np.array([u, v, 1.0])) - R @ g.center
        return R, t

    # -- table-top layout --------------------------------------------------------------------------
    def _resting_poses(self, kind: str, i: int) -> RestingPoses:
        rp = self._resting.get((kind, i))
        if rp is None:
            geom, mesh = ((self.geoms[i], getattr(self.models[i], "mesh", None)) if kind == "model"
                          else (self.d_geoms[i], self.distractors[i]))
            rp = self._resting[(kind, i)] = RestingPoses.from_geometry(geom, mesh)
        return rp

    def _grid(self, chosen) -> tuple[int, float]:
        """(m, cell): the fallback layout puts the objects on an m x m grid of ``cell`` mm squares."""
        return math.ceil(math.sqrt(len(chosen))), 2.0 * max(self.geoms[k].radius for k in chosen) + _GAP

    def _sample_table(self, rng, chosen) -> TableScene:
        """The table of one image: side lengths in ``table_size_range`` (enlarged to hold the fallback
        grid of the objects), the look-at point (table-frame origin) at a random place on it at least
        half the grid away from the edges, and a texture from the background source."""
        m, cell = self._grid(chosen)
        half = m * cell / 2.0 + _GAP
        ext = []
        for _ in range(2):
            side = max(float(rng.uniform(*self.cfg.table_size_range)), 2.0 * half)
            a = float(rng.uniform(half, side - half))  # the origin's distance from the low edge
            ext += [-a, side - a]
        sx, sy = ext[1] - ext[0], ext[3] - ext[2]
        long = max(self.W, self.H)  # texture: the output's resolution at the table's aspect ratio
        tw, th = (long, max(8, round(long * sy / sx))) if sx >= sy else (max(8, round(long * sx / sy)), long)
        image = self.backgrounds.sample(rng, tw, th)
        room = ()
        if self.cfg.table_room_prob > 0 and rng.random() < self.cfg.table_room_prob:
            room = tuple(make_room(rng, self.backgrounds, ext, self._camera_reach()).meshes)
        return TableScene(mesh=make_table_mesh(image, *ext), extent=tuple(ext), room=room)

    def _camera_reach(self) -> float:
        """The largest horizontal distance (mm) of a sampled camera from the look-at point, plus the
        near plane and a margin: the room's walls stand beyond it."""
        el_min = math.radians(self.cfg.table_elevation_range[0])
        return self.ranges.distance[1] * math.cos(el_min) + 2.0 * self.renderer.znear + 100.0

    def _table_camera(self, rng, table: TableScene) -> TableScene:
        """The table with a camera looking down at its origin (elevation uniform on the sphere)."""
        cfg = self.cfg
        s_lo, s_hi = (math.sin(math.radians(a)) for a in cfg.table_elevation_range)
        el = math.asin(min(1.0, rng.uniform(s_lo, s_hi)))
        az = rng.uniform(0.0, 2.0 * math.pi)
        dist = float(rng.uniform(*self.ranges.distance))
        roll = math.radians(rng.uniform(*cfg.table_roll_range))
        R, t = table_camera(el, az, dist, roll)
        return replace(table, R_w2c=R, t_w2c=t, elevation_deg=math.degrees(el), distance=dist)

    def _place_on_table(self, rng, rp: RestingPoses, cam: TableScene, placed: list, view_geom=None,
                        tries: int = 30, upright_prob: float = 0.0):
        """A resting pose (R_mw, t_mw) of ``rp`` on the table within the cluster radius of the look-at
        point (widened by 10 % per failed try), its footprint clear of the ``placed`` ones (it is
        appended on success) and, with ``view_geom``, in view (``view_margin``); None if no try succeeds."""
        R_mw = rp.sample(rng, upright_prob)
        foot0, z_min = footprint(rp, R_mw)
        rho = self.cfg.table_cluster_radius * cam.distance
        for j in range(tries):
            a = rng.uniform(0.0, 2.0 * math.pi)
            p = rho * 1.1**j * math.sqrt(rng.random()) * np.array([math.cos(a), math.sin(a)])
            foot = foot0.moved(p - foot0.center)  # the footprint circle centred at p
            if not cam.holds(foot) or any(foot.overlaps(other, _GAP) for other in placed):
                continue
            t_mw = np.array([*(p - foot0.center), -z_min])
            if view_geom is not None:
                box, zmin = projected_box(view_geom, self.K, *cam.world_to_camera(R_mw, t_mw))
                if not (zmin > self.renderer.znear and _inside(box, self.W, self.H, self.cfg.view_margin)):
                    continue
            placed.append(foot)
            return R_mw, t_mw
        return None

    def _table_layout(self, rng, chosen, table: TableScene, layout_tries: int = 5):
        """Camera and resting object poses (camera frame, symmetric ones canonicalised) and their
        footprints; after ``layout_tries`` cameras without a layout in view, a grid (view ignored)."""
        for _ in range(layout_tries):
            cam = self._table_camera(rng, table)
            placed, world = [], []
            for k in chosen:
                pose = self._place_on_table(rng, self._resting_poses("model", k), cam, placed, self.geoms[k],
                                            upright_prob=self.cfg.table_upright_prob)
                if pose is None:
                    break
                world.append(pose)
            if len(world) == len(chosen):
                break
        else:  # each object in its own grid cell around the look-at point: on the table, disjoint
            m, cell = self._grid(chosen)
            placed, world = [], []
            for i, k in enumerate(chosen):
                rp = self._resting_poses("model", k)
                R_mw = rp.sample(rng, self.cfg.table_upright_prob)
                foot0, z_min = footprint(rp, R_mw)
                p = (np.array([i % m, i // m], dtype=np.float64) - (m - 1) / 2.0) * cell
                placed.append(foot0.moved(p - foot0.center))
                world.append((R_mw, np.array([*(p - foot0.center), -z_min])))
        poses = []
        for k, (R_mw, t_mw) in zip(chosen, world):
            R, t = cam.world_to_camera(R_mw, t_mw)
            handler = self.symmetry[k]
            if handler is not None:  # an equivalent pose: the rendered object, resting as sampled
                R, t = handler.canonicalize(R, t)
                R, t = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
            poses.append((R, t))
        return cam, poses, placed

    def _lift_above_table(self, cam: TableScene, geom, R, t):
        """Move a floating occluder up along the table normal until it is above the table plane."""
        z = (cam.R_w2c.T @ ((geom.hull @ R.T + t) - cam.t_w2c).T)[2]
        low = float(z.min())
        return t if low >= _GAP else t + cam.R_w2c[:, 2] * (_GAP - low)

    def _table_distractors(self, rng, chosen, poses, cam: TableScene, placed):
        """Occluders: with probability ``table_distractor_rest_prob`` resting on the table near the
        objects (footprints disjoint from everything resting there), otherwise (or when no place is
        free) floating in front of an object as in the free layout, lifted above the table plane."""
        cfg = self.cfg
        n_d = int(rng.integers(cfg.distractors[0], cfg.distractors[1] + 1)) if self.distractors else 0
        items = []
        for _ in range(n_d):
            d = int(rng.integers(len(self.distractors)))
            pose = None
            if rng.random() < cfg.table_distractor_rest_prob:
                pose = self._place_on_table(rng, self._resting_poses("distractor", d), cam, placed, tries=20)
                if pose is not None:
                    pose = cam.world_to_camera(*pose)
            if pose is None:
                j = int(rng.integers(len(chosen)))
                k = chosen[j]
                R, t = poses[j]
                box, _ = projected_box(self.geoms[k], self.K, R, t)
                tz = float((R @ self.geoms[k].center + t)[2])
                R_d, t_d = self._distractor_pose(rng, d, box, tz, self.geoms[k].radius)
                pose = (R_d, self._lift_above_table(cam, self.d_geoms[d], R_d, t_d))
            items.append((self.distractors[d], *pose))
        return items

    def _table_attempt(self, rng, chosen, lighting, table: TableScene):
        """One table-top attempt. The table is drawn in the colour pass only: it is never an occluder.

        Masks: a segmentation pass of the objects gives their silhouettes as far as occluders go (other
        objects do cover them there). With occluders and a single-sampled colour pass, an object pixel
        is hidden where the colour pass is nearer than the object (as in the free layout) unless the
        colour-pass depth is that of the table plane there (within :func:`depth_tolerance`): the
        objects stand on the table, which lies behind every object pixel and meets the object only at
        the contact, where the two depths tie. With ``antialias`` the segmentation pass draws the
        occluders too (no table) and gives the visible masks directly.
        """
        cfg = self.cfg
        cam, poses, placed = self._table_layout(rng, chosen, table)
        d_items = self._table_distractors(rng, chosen, poses, cam, placed)
        n = len(chosen)
        items = [(self.models[k], R, t) for k, (R, t) in zip(chosen, poses)] + d_items
        scenery = [(m, cam.R_w2c, cam.t_w2c) for m in (table.mesh, *table.room)]
        col = self.renderer.render([*items, *scenery], lighting=lighting, K=self.K, masks=False)
        if cfg.antialias:
            seg = self.renderer.render(items, K=self.K, depth_only=True)
            base = masks = seg.masks_visib[:n]
            coverers = [[seg.masks_visib[j] for j in range(len(items)) if j != i] for i in range(n)]
            depth = np.where(seg.depth > 0, seg.depth, col.depth)  # pixel-centre depth where it matters
        else:
            seg = self.renderer.render(items[:n], K=self.K, depth_only=True)
            base = seg.masks_visib
            masks = base
            if d_items or table.room:  # occluders, or room furniture that may stand in front
                in_front = col.depth < seg.depth * (1.0 - 1e-6) - 1e-3
                vs, us = np.nonzero(in_front)
                if len(us):  # the colour pass's depth there is the table plane's: a contact tie
                    table_tie = self._table_seen(cam, col.depth, us, vs)
                    in_front[vs[table_tie], us[table_tie]] = False
                masks = [m & ~in_front for m in base]
            coverers = [[base[j] for j in range(n) if j != i] for i in range(n)]
            depth = col.depth
        instances = self._instances(chosen, poses, masks, base, coverers)
        return (col.rgb, depth), instances, cam, d_items

    # -- one image ---------------------------------------------------------------------------------
    def _attempt(self, rng, chosen, lighting):
        cfg = self.cfg
        poses = [self._object_pose(rng, k) for k in chosen]
        n_d = int(rng.integers(cfg.distractors[0], cfg.distractors[1] + 1)) if self.distractors else 0
        d_items = []
        for _ in range(n_d):
            j = int(rng.integers(len(chosen)))
            k = chosen[j]
            R, t = poses[j]
            box, _ = projected_box(self.geoms[k], self.K, R, t)
            tz = float((R @ self.geoms[k].center + t)[2])
            d = int(rng.integers(len(self.distractors)))
            d_items.append((self.distractors[d], *self._distractor_pose(rng, d, box, tz, self.geoms[k].radius)))
        items = [(self.models[k], R, t) for k, (R, t) in zip(chosen, poses)] + d_items
        n = len(chosen)
        if d_items and not cfg.antialias:
            # two passes: colour of everything (with a single-sampled framebuffer its depth is the
            # pixel-centre depth) and a segmentation pass of the objects alone; an object pixel is
            # visible unless the full scene is nearer there (an occluder in front). The objects-alone
            # masks are the objects' silhouettes as far as occluders go, so px_count_all needs no
            # extra pass unless objects cover each other.
            col = self.renderer.render(items, lighting=lighting, K=self.K, masks=False)
            seg = self.renderer.render(items[:n], K=self.K, depth_only=True)
            in_front = col.depth < seg.depth * (1.0 - 1e-6) - 1e-3
            base = seg.masks_visib
            masks = [m & ~in_front for m in base]
            rgb, depth = col.rgb, col.depth
            coverers = [[base[j] for j in range(n) if j != i] for i in range(n)]
        else:
            res = self.renderer.render(items, lighting=lighting, K=self.K)
            base = masks = res.masks_visib[:n]
            rgb, depth = res.rgb, res.depth
            coverers = [[res.masks_visib[j] for j in range(len(items)) if j != i] for i in range(n)]
        instances = self._instances(chosen, poses, masks, base, coverers)
        return (rgb, depth), instances

    def _instances(self, chosen, poses, masks, base, coverers) -> list[SceneInstance]:
        """Ground truth of the objects ``chosen`` at ``poses``: ``masks`` are their visible masks,
        ``base`` their masks as far as occluders go, ``coverers[i]`` the masks that may cover object i."""
        boxes, counts, alone = [], [], []
        for i, k in enumerate(chosen):
            R, t = poses[i]
            uv = project_points(self.geoms[k].hull, self.K, R, t)  # same extremes as all vertices
            bbox_obj = bbox_obj_from_uv(uv)
            x, y, w, h = bbox_obj
            # could something cover part of base[i]? only if it shows inside the object's box
            x0, y0 = max(x - 1, 0), max(y - 1, 0)
            x1, y1 = min(x + w + 1, self.W - 1) + 1, min(y + h + 1, self.H - 1) + 1
            others = coverers[i]
            occluded = False
            if x1 > x0 and y1 > y0 and any(np.any(m[y0:y1, x0:x1]) for m in others):
                # tighter: the silhouette lies in the convex hull of the projected vertices
                # (grown by 1 px against rasterization ties); only pixels there can be covered
                hull = _hull_mask(uv, x0, y0, x1, y1)
                occluded = any(np.any(m[y0:y1, x0:x1] & hull) for m in others)
            boxes.append(bbox_obj)
            if not occluded and _inside_image(bbox_obj, self.W, self.H):
                n_px = int(np.count_nonzero(base[i]))
                counts.append((n_px, n_px))
            else:  # the whole silhouette needs a pass drawing the object alone
                counts.append(None)
                alone.append(i)
        if alone:
            many = silhouette_counts_many(self.renderer, [(self.models[chosen[i]], *poses[i]) for i in alone],
                                          self.K, self.W, self.H, [boxes[i] for i in alone])
            for i, c in zip(alone, many):
                counts[i] = c
        instances = []
        for i, k in enumerate(chosen):
            model = self.models[k]
            R, t = poses[i]
            mask = masks[i]
            visib = int(np.count_nonzero(mask))
            bbox_obj = boxes[i]
            px_all, px_valid = counts[i]
            instances.append(SceneInstance(
                obj_id=int(model.obj_id), R=R, t=t, mask_visib=mask,
                bbox_obj=bbox_obj if visib > 0 else [-1, -1, -1, -1],
                bbox_visib=bbox_from_mask(mask), px_count_all=px_all, px_count_valid=px_valid,
                px_count_visib=visib, visib_fract=float(visib / px_all) if px_all > 0 else 0.0,
            ))
        return instances

    def _violation(self, instances) -> float:
        lo, hi = self.cfg.visib_fract_range
        return sum(max(0.0, lo - inst.visib_fract) + max(0.0, inst.visib_fract - hi) for inst in instances)

    def compose(self, rng: np.random.Generator) -> SceneSample:
        """One image and its ground truth, deterministic for the state of ``rng``."""
        import cv2

        from kpd6d.render import Lighting

        cfg = self.cfg
        chosen = self._choose_objects(rng)
        style = cfg.lighting
        if style == "mixed":  # each image lit one way or the other, half and half
            style = "random" if rng.random() < 0.5 else "indoor"
        if style == "random":
            lighting = Lighting.random(rng, specular_prob=cfg.specular_prob)
        elif style == "indoor":
            lighting = Lighting.random_indoor(rng, specular_prob=cfg.specular_prob)
        else:
            lighting = Lighting()
        if cfg.contrast_lighting > 0 and rng.random() < cfg.contrast_lighting:  # (no draw when off: datasets resume)
            lighting = Lighting.random_contrast(rng)
        background = self.backgrounds.sample(rng, self.W, self.H)
        table = self._sample_table(rng, chosen) if cfg.layout == "tabletop" else None
        best = None
        attempts = 0
        try:
            for _ in range(cfg.max_retries + 1):
                attempts += 1
                if table is None:
                    res, instances = self._attempt(rng, chosen, lighting)
                    extra = (None, None)
                else:
                    res, instances, *extra = self._table_attempt(rng, chosen, lighting, table)
                v = self._violation(instances)
                if best is None or v < best[0]:
                    best = (v, res, instances, extra)
                if v == 0:
                    break
        finally:
            if table is not None:
                for mesh in (table.mesh, *table.room):
                    self._forget_mesh(mesh)
        _, (rendered, depth), instances, (table_cam, d_items) = best
        if table_cam is not None and cfg.table_shadow_prob > 0 and rng.random() < cfg.table_shadow_prob:
            rendered = self._cast_shadows(rng, rendered, depth, table_cam, instances, d_items, lighting)
        # paste: the union of all rendered silhouettes (objects and occluders); feathering only
        # softens its inner edge (blends background into the outermost object pixels, no dark halo)
        alpha = (depth > 0).astype(np.float32)
        if cfg.feather_sigma > 0:
            alpha = np.minimum(alpha, cv2.GaussianBlur(alpha, (0, 0), cfg.feather_sigma))
        rgb = cv2.blendLinear(np.ascontiguousarray(rendered), background, alpha, 1.0 - alpha)
        if cfg.object_detail > 0 and instances and rng.random() < cfg.object_detail:
            rgb = surface_detail(rgb, np.logical_or.reduce([inst.mask_visib for inst in instances]), rng)
        rgb = apply_photometric(rgb, rng, self.photometric)
        return SceneSample(rgb=rgb, depth=depth, K=self.K.copy(), instances=instances, attempts=attempts,
                           table=table_cam, distractor_items=d_items)

    def _table_seen(self, cam: TableScene, depth: np.ndarray, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
        """Whether the rendered ``depth`` at pixels (us, vs) is the table plane's (within
        :func:`depth_tolerance`): the table is what the camera sees there."""
        z = depth[vs, us].astype(np.float64)
        return z >= plane_depth(self.K, cam.R_w2c, cam.t_w2c, us, vs) - depth_tolerance(z, self.renderer.znear)

    def _cast_shadows(self, rng, rgb, depth, cam: TableScene, instances, d_items, lighting):
        """Darken the table where the objects and occluders cast a shadow of the strongest directional
        light: planar projection shadows (:func:`shadow_pose`) drawn in one segmentation pass, kept
        only on pixels whose colour-pass depth is the table plane's, softened by a random penumbra
        blur, by a random strength (the light's share of the table's brightness is not known, so it
        is randomised: 0.25-0.7). Objects do not shadow each other, only the table."""
        import cv2

        if not lighting.lights:
            return rgb
        light = max(lighting.lights, key=lambda li: li.intensity)
        by_id = {int(m.obj_id): m for m in self.models}
        casters = [(by_id[inst.obj_id], inst.R, inst.t) for inst in instances] + list(d_items or ())
        flat = [(mesh, *p) for mesh, R, t in casters
                if (p := shadow_pose(R, t, cam.R_w2c, cam.t_w2c, np.asarray(light.direction))) is not None]
        strength, blur = rng.uniform(0.25, 0.7), rng.uniform(0.5, 4.0)
        if not flat:
            return rgb
        shadow = self.renderer.render(flat, K=self.K, depth_only=True).depth > 0
        vs, us = np.nonzero(shadow & (depth > 0))
        if not len(us):
            return rgb
        on_table = self._table_seen(cam, depth, us, vs)
        table_px = np.zeros(depth.shape, np.float32)
        table_px[vs[on_table], us[on_table]] = 1.0
        # the blur spreads the shadow's edge inwards only (a penumbra inside the hard edge)
        gain = 1.0 - strength * cv2.GaussianBlur(table_px, (0, 0), blur) * table_px
        return np.clip(rgb.astype(np.float32) * gain[..., None] + 0.5, 0, 255).astype(np.uint8)

    def _forget_mesh(self, mesh) -> None:
        """Drop a one-image mesh (the table) from the renderer's cache; its GL buffers and texture are
        then released on the next render instead of accumulating."""
        forget = getattr(self.renderer, "forget", None)
        if forget is not None:
            forget(mesh)
