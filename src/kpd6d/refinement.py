"""Region-based pose refinement: a pose (from the KPD + PnP) pulled onto the object's silhouette in
the image itself, with nothing learnt (sparse correspondence lines in the manner of SRT3D, Stoiber et
al., "A Sparse Gaussian Approach to Region-Based 6DoF Object Tracking", ACCV 2020).

Each iteration:

1. the object's silhouette at the current pose is rendered (depth only) into a small viewport that
   frames its projected box (same camera centre and orientation, scaled intrinsics, so the silhouette
   and its 3D contour points are exact); ``num_lines`` points are sampled along its outer contour and
   lifted to 3D from the rendered depth;
2. colour histograms of the foreground (the silhouette, eroded) and the background (a ring around it)
   are collected from the image, giving each pixel a foreground posterior ``p_f``;
3. along each contour point's normal a correspondence line samples ``p_f`` at ``2 L + 1`` positions
   ``step`` pixels apart; a smoothed step model (foreground inside, background outside) gives a
   distribution of where the image's contour lies on the line, summarised by its mean ``mu`` and
   variance ``var``;
4. one regularised Gauss-Newton step moves the pose (rotation about the object's centre, translation)
   so that the projected contour points move ``mu`` along their normals, each line weighted by
   ``1 / var``.

The line spacing shrinks from coarse to fine over the iterations, in proportion to the object's
projected size. The only colours used are the image's own: there is no domain gap to cross. Where too
few lines carry evidence the input pose is returned unchanged (``RefineResult.ok`` False).
"""
from __future__ import annotations

import inspect
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from kpd6d.geometry import backproject, project_points, rotation_about_axis
from kpd6d.registry import REFINERS, build_from_cfg

__all__ = ["COVER_BOX", "RefineResult", "RegionRefineConfig", "RegionRefiner", "build_refiner", "cover_box"]

#: ``RegionRefineConfig.cover_box``: when the pose is brought up to its box (see :func:`cover_box`)
COVER_BOX = ("none", "before", "after")


@dataclass(frozen=True)
class RegionRefineConfig:
    """Settings of :class:`RegionRefiner` (lengths in pixels of the image unless said otherwise).

    ``scales``: one Gauss-Newton step per entry; each is the line's half-length as a fraction of the
    object's projected diameter (coarse to fine). ``line_steps``: samples on each side of the contour
    (``L``); the spacing is ``scale * diameter_px / L``, at least ``min_step``. ``num_lines``: contour
    points per iteration. ``hist_bins``: bins per colour channel. ``fg_margin`` / ``bg_margin``: image px
    next to the silhouette's edge left out of the foreground (inside) / background (outside) histogram,
    where a blurred image mixes the two colours. ``amplitude`` / ``slope``: the
    smoothed step ``h_f(x) = 1/2 - amplitude * tanh(x / (2 slope))`` (x in line steps, outward
    positive). ``prior_rotation`` (rad) / ``prior_translation`` (mm): standard deviations of a zero-mean
    prior on each step (keeps weakly observed directions still). ``min_lines``: fewer informative
    lines than this and the input pose is kept. ``viewport``: side of the silhouette render. ``occlusion``: in :meth:`RegionRefiner.refine_poses`,
    the other objects estimated in the same image (at their current poses) are rendered too, and line
    samples where one of them lies in front of the object's contour (by more than 5 % of the object's
    diameter) carry no evidence, nor do the pixels they cover in the foreground histogram. ``cover_box``:
    in :meth:`RegionRefiner.refine_poses`, each pose whose object, projected, is narrower or shorter than the
    box it was estimated from (the pose dict's ``box``: the detection) moves along its ray toward the camera
    until it covers the box (:func:`cover_box`), ``before`` or ``after`` the region steps (``none``: never).
    A detection box holds the object's visible part, so the whole object projected at the true pose covers
    it; an estimate that does not is too far. ``depth_hypotheses``: in :meth:`RegionRefiner.refine_poses` each
    pose is refined once from its translation times each factor (along its ray), and the refinement with the
    most ``evidence`` is kept (the first on a tie; refinements without enough evidence do not compete): a
    wider basin in depth, the quantity keypoints measure worst. ``roll_hypotheses``: further starts, each the
    pose turned by that many degrees about the line of sight through the object's centre (at the estimated
    depth), competing with the depth hypotheses in the same way: a wider basin for the in-plane rotation,
    which the tight rotation prior otherwise barely moves. ``local_regions``: more than one, and the colour
    histograms are counted per angular sector about the silhouette's centroid, each pixel's posterior taken from
    its sector's pair, so each stretch of the contour is judged against its own surroundings (a dark part of the
    object before a dark background elsewhere no longer reads as background); ``local_prior`` pseudo-pixels of
    the whole silhouette's histograms are mixed into each sector's (few pixels: close to the whole pair).
    """

    scales: tuple[float, ...] = (0.25, 0.18, 0.12, 0.09, 0.07, 0.06)
    line_steps: int = 8
    min_step: float = 1.0
    num_lines: int = 200
    hist_bins: int = 16
    fg_margin: int = 1  # px inside the silhouette's edge left out of the foreground histogram
    bg_margin: int = 2  # px outside it left out of the background histogram
    amplitude: float = 0.43
    slope: float = 0.5
    prior_rotation: float = 0.02
    prior_translation: float = 10.0
    min_lines: int = 20
    viewport: int = 192
    ring: float = 0.15  # background ring width, as a fraction of the projected diameter
    occlusion: bool = False  # the image's other estimated objects mask the line samples they cover
    edge_offset: float = 0.5  # viewport px from a contour pixel's centre out to where the silhouette's edge is taken
    cover_box: str = "none"  # none | before | after the region steps: a pose too small for its box moves closer (cover_box())
    depth_hypotheses: tuple[float, ...] = (1.0,)  # refine from the translation times each; keep the most evidence
    roll_hypotheses: tuple[float, ...] = ()  # degrees about the line of sight: more starts competing the same way
    local_regions: int = 0  # > 1: colour histograms per angular sector about the silhouette (0 / 1: one pair)
    local_prior: float = 100.0  # pseudo-pixels of the whole silhouette's histograms in each sector's

    def __post_init__(self) -> None:
        object.__setattr__(self, "depth_hypotheses", tuple(float(v) for v in self.depth_hypotheses))
        if not self.depth_hypotheses or any(not (0.5 <= f <= 2.0) for f in self.depth_hypotheses):
            raise ValueError(f"region refinement: depth_hypotheses must be factors in [0.5, 2] on the estimated "
                             f"translation, got {self.depth_hypotheses}")
        object.__setattr__(self, "roll_hypotheses", tuple(float(v) for v in self.roll_hypotheses))
        if any(not (-90.0 <= r <= 90.0) or r == 0.0 for r in self.roll_hypotheses):
            raise ValueError(f"region refinement: roll_hypotheses must be non-zero angles in [-90, 90] degrees (the "
                             f"unturned start is the depth hypotheses'), got {self.roll_hypotheses}")
        if self.cover_box not in COVER_BOX:
            raise ValueError(f"region refinement: cover_box must be one of {', '.join(COVER_BOX)}, got {self.cover_box!r}")
        object.__setattr__(self, "scales", tuple(float(v) for v in self.scales))
        if not self.scales or any(not (s > 0) for s in self.scales):
            raise ValueError(f"region refinement: scales must be positive fractions of the projected diameter, got {self.scales}")
        for name in ("fg_margin", "bg_margin"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or v < 0 or int(v) != v:
                raise ValueError(f"region refinement: {name} must be a whole number of px >= 0, got {v!r}")
            object.__setattr__(self, name, int(v))
        for name in ("line_steps", "num_lines", "hist_bins", "min_lines", "viewport"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"region refinement: {name} must be >= 1, got {getattr(self, name)}")
        if not (0 < self.amplitude < 0.5):
            raise ValueError(f"region refinement: amplitude must lie in (0, 0.5), got {self.amplitude}")
        for name in ("slope", "min_step", "prior_rotation", "prior_translation", "ring"):
            if not (getattr(self, name) > 0):
                raise ValueError(f"region refinement: {name} must be > 0, got {getattr(self, name)}")
        if isinstance(self.local_regions, bool) or int(self.local_regions) != self.local_regions or self.local_regions < 0:
            raise ValueError(f"region refinement: local_regions must be a whole number >= 0, got {self.local_regions!r}")
        object.__setattr__(self, "local_regions", int(self.local_regions))
        if not (self.local_prior >= 0):
            raise ValueError(f"region refinement: local_prior must be >= 0 (pseudo-pixels), got {self.local_prior}")
        if not (0 <= self.edge_offset <= 1):
            raise ValueError(f"region refinement: edge_offset must lie in [0, 1] (viewport px), got {self.edge_offset}")


def cover_box(points, R, t, K, box, image_size, iterations: int = 3) -> tuple[np.ndarray, float]:
    """The translation ``t`` (3,) mm scaled along its ray (``t * f``, ``f <= 1``) so that ``points`` (N, 3) mm
    of the object, posed by (``R``, ``t``) and projected by ``K``, cover ``box`` (4,) xywh px in width and in
    height, both clipped to the image (``image_size`` = (H, W)). Returns ``(t * f, f)``; ``f = 1`` when the
    projection covers the box already, or when it cannot be measured (points behind the camera, nothing
    of it left in the image, an empty box).

    The projected size goes as about ``1 / depth``: ``f`` is multiplied by the smallest ratio of projected
    to box side up to ``iterations`` times (a fixed point, following the perspective of a near, deep object);
    it never goes above 1 nor below a quarter (a box far larger than the object says more about the box than about the depth).
    """
    H, W = int(image_size[0]), int(image_size[1])
    t = np.asarray(t, np.float64).reshape(3)
    b = np.asarray(box, np.float64).reshape(4)
    want = np.minimum(b[:2] + b[2:], [W, H]) - np.maximum(b[:2], 0.0)
    if not (np.isfinite(want).all() and (want > 0).all()):
        return t, 1.0
    f = 1.0
    for _ in range(int(iterations)):
        uv, z = project_points(points, K, R, t * f, return_depth=True)
        if not (z > 0).all() or not np.isfinite(uv).all():
            break
        size = np.clip(uv.max(0), 0, [W, H]) - np.clip(uv.min(0), 0, [W, H])
        if not (size > 0).all():
            break
        ratio = float((size / want).min())
        if (f == 1.0 and ratio >= 1.0) or abs(ratio - 1.0) < 1e-4:
            break
        f = min(1.0, max(0.25, f * ratio))
    return t * f, f


@dataclass
class RefineResult:
    R: np.ndarray
    t: np.ndarray
    ok: bool
    lines: int = 0  # informative lines in the last iteration
    evidence: float = 0.0  # how much of the contour the image confirms, 0..1 (:meth:`RegionRefiner.refine`)
    history: list = field(default_factory=list)  # (R, t) after each step


def _box_centre(model) -> np.ndarray:
    """The centre of the model's bounding box (model frame, mm): the point the refiner's steps turn about."""
    return np.asarray(model.mesh.bounds, np.float64).mean(0)


def _so3_exp(w: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    return rotation_about_axis(w / angle, angle)


def contour_jacobian(X: np.ndarray, normals: np.ndarray, centre: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(n, 6): how far each projected point of ``X`` (n, 3, camera frame, mm) moves along its image
    ``normals`` (n, 2, unit) per unit of the pose step ``theta = (w, v)`` of :func:`apply_pose_step`
    (a rotation w about ``centre``, then a translation v), at theta = 0."""
    z = X[:, 2]
    dpi = np.zeros((len(X), 2, 3))  # d pi / dX
    dpi[:, 0, 0] = K[0, 0] / z
    dpi[:, 0, 2] = -K[0, 0] * X[:, 0] / z ** 2
    dpi[:, 1, 1] = K[1, 1] / z
    dpi[:, 1, 2] = -K[1, 1] * X[:, 1] / z ** 2
    g = np.einsum("ni,nij->nj", normals, dpi)  # d(normal displacement) / dX
    return np.concatenate([np.cross(X - centre, g), g], axis=1)  # d/dw of (w x (X - c)) . g = (X - c) x g


def apply_pose_step(R: np.ndarray, t: np.ndarray, centre: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pose (R, t) after the step ``theta = (w, v)``: every camera-frame point X goes to
    ``exp(w) (X - centre) + centre + v``."""
    dR = _so3_exp(np.asarray(theta[:3], np.float64))
    return dR @ R, dR @ (t - centre) + centre + np.asarray(theta[3:], np.float64)


class RegionRefiner:
    """Refines poses of :class:`~kpd6d.objects.ObjectModel` s in an RGB image (uint8, H x W x 3) seen
    by a camera ``K``. ``models``: obj_id -> model, for :meth:`refine_poses` (a pipeline's pose dicts
    name objects by id; :meth:`set_models` sets them later). Holds one small offscreen renderer
    (created on first use)."""

    def __init__(self, config: RegionRefineConfig | None = None, models: Mapping[int, Any] | None = None,
                 renderer=None) -> None:
        self.config = config or RegionRefineConfig()
        self.models: dict[int, Any] = {}
        self.models_source = "models given in code"
        if models is not None:
            self.set_models(models)
        self._renderer = renderer
        self._full_frame = False  # True: the posterior on the whole image (tests: the window changes nothing)

    def set_models(self, models: Mapping[int, Any] | Any, source: str | None = None) -> None:
        """obj_id -> :class:`~kpd6d.objects.ObjectModel` (a mapping, or a list of models)."""
        items = models.items() if isinstance(models, Mapping) else ((m.obj_id, m) for m in models)
        self.models = {int(o): m for o, m in items}
        if source is not None:
            self.models_source = source

    def settings(self) -> dict:
        """The refiner's name and settings, JSON-ready (what an evaluation records)."""
        return {"name": "region", **{f.name: (list(v) if isinstance(v := getattr(self.config, f.name), tuple) else v)
                                     for f in fields(self.config)}}

    def refine_poses(self, images, Ks, poses: list[list[dict]]) -> list[list[dict]]:
        """Refine, in place, each ``ok`` pose dict of ``poses`` (one list per image of ``images``,
        uint8 RGB; ``Ks`` (B, 3, 3)). Each pose dict gets ``refined`` (bool: the pose moved) and
        ``evidence`` (the share of its contour the image confirms, 0..1, measured at the last step); a
        pose whose refinement found too little evidence keeps the estimate it had."""
        for b, plist in enumerate(poses):
            todo = [p for p in plist if p.get("ok")]
            if not todo:
                continue
            image = np.asarray(images[b])
            if image.ndim != 3 or image.shape[2] < 3 or image.dtype != np.uint8:
                raise ValueError(f"pose refinement needs uint8 RGB images (H, W, 3), got {image.dtype} {image.shape}")
            for p in plist:
                p["refined"] = False
            for p in todo:
                oid = int(p["obj_id"])
                if oid not in self.models:
                    raise KeyError(f"pose refinement: no mesh for object {oid} ({self.models_source} has "
                                   f"{sorted(self.models) or 'none'})")
            if self.config.cover_box == "before":
                self._cover_boxes(todo, Ks[b], image.shape[:2])
            for p in todo:
                others = [(self.models[int(q["obj_id"])], q["R"], q["t"]) for q in todo
                          if q is not p] if self.config.occlusion else ()
                res = self._refine_hypotheses(image, self.models[int(p["obj_id"])], p["R"], p["t"], Ks[b], others)
                p["evidence"] = res.evidence
                if res.ok:
                    p["R"], p["t"], p["refined"] = res.R, res.t, True
            if self.config.cover_box == "after":
                self._cover_boxes(todo, Ks[b], image.shape[:2])
        return poses

    def _refine_hypotheses(self, image, model, R, t, K, others=()) -> RefineResult:
        """:meth:`refine` from ``t`` times each of ``depth_hypotheses`` and from the pose turned by each of
        ``roll_hypotheses`` about its line of sight: the ok result with the most evidence (the first on a tie),
        else the first start's (not ok: the caller keeps its input pose)."""
        R = np.asarray(R, np.float64)
        t = np.asarray(t, np.float64).reshape(3)
        starts = [(R, t * f) for f in self.config.depth_hypotheses]
        if self.config.roll_hypotheses:
            c = R @ _box_centre(model) + t  # the object's centre, camera frame
            axis = c / max(float(np.linalg.norm(c)), 1e-9)
            for deg in self.config.roll_hypotheses:
                Q = _so3_exp(axis * np.radians(deg))
                starts.append((Q @ R, Q @ (t - c) + c))  # turned about the centre: it stays where it was
        results = [self.refine(image, model, R0, t0, K, others=others) for R0, t0 in starts]
        return max((r for r in results if r.ok), key=lambda r: r.evidence, default=results[0])

    def _cover_boxes(self, poses: list[dict], K, image_size) -> None:
        """:func:`cover_box` on each pose dict with a ``box``, in place; ``cover_factor`` records its f."""
        for p in poses:
            if p.get("box") is None:
                continue
            model = self.models[int(p["obj_id"])]
            p["t"], p["cover_factor"] = cover_box(model.vertices, np.asarray(p["R"], np.float64), p["t"], K,
                                                  p["box"], image_size)
            if p["cover_factor"] < 1.0:
                p["refined"] = True

    @property
    def renderer(self):
        if self._renderer is None:
            from kpd6d.render import Renderer

            s = self.config.viewport
            self._renderer = Renderer(s, s, antialias=False)
        return self._renderer

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # -- one silhouette -------------------------------------------------------------------------
    def _contour(self, model, R, t, K, centre_px, diameter_px, others=()):
        """3D contour points (camera frame, mm), their outward image normals, the edge offset (px),
        the silhouette as (mask, affine viewport -> image, Kv), and the depth of ``others`` where one
        of them is in front of the object and hides it or its surroundings (viewport, 0 elsewhere; None
        without others), or None if the object is not visible."""
        import cv2

        s = self.config.viewport
        a = min(4.0, 0.8 * s / max(diameter_px, 1.0))
        Kv = np.array([[a * K[0, 0], 0.0, a * (K[0, 2] - centre_px[0]) + (s - 1) / 2],
                       [0.0, a * K[1, 1], a * (K[1, 2] - centre_px[1]) + (s - 1) / 2],
                       [0.0, 0.0, 1.0]])
        depth = self.renderer.render([(model, R, t)], K=Kv, depth_only=True).depth
        mask = (depth > 0).astype(np.uint8)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        contours = [c[:, 0, :] for c in contours if len(c) >= 8]
        if not contours:
            return None
        n_total = sum(len(c) for c in contours)
        pts, nrm = [], []
        for c in contours:
            k = max(1, round(self.config.num_lines * len(c) / n_total))
            idx = np.linspace(0, len(c), k, endpoint=False).astype(int)
            tan = (np.roll(c, -2, axis=0) - np.roll(c, 2, axis=0)).astype(np.float64)[idx]
            nv = np.stack([tan[:, 1], -tan[:, 0]], 1)
            nv /= np.maximum(np.linalg.norm(nv, axis=1, keepdims=True), 1e-9)
            p = c[idx].astype(np.float64)
            probe = np.round(p + 2.0 * nv).astype(int)
            inside = np.zeros(len(p), bool)
            ok = (probe[:, 0] >= 0) & (probe[:, 0] < s) & (probe[:, 1] >= 0) & (probe[:, 1] < s)
            inside[ok] = mask[probe[ok, 1], probe[ok, 0]] > 0
            nv[inside] *= -1.0
            pts.append(p)
            nrm.append(nv)
        p = np.concatenate(pts)
        nv = np.concatenate(nrm)
        z = depth[p[:, 1].astype(int), p[:, 0].astype(int)].astype(np.float64)
        X = backproject(p, z, Kv)
        A = np.array([[1.0 / a, 0.0, centre_px[0] - (s - 1) / 2 / a],
                      [0.0, 1.0 / a, centre_px[1] - (s - 1) / 2 / a]])  # viewport px -> image px
        occ = None
        if others:
            res = self.renderer.render([(model, R, t), *others], K=Kv, depth_only=True)
            occ = np.where(res.masks_visib[0], 0.0, res.depth).astype(np.float32)  # the front-most other object
        return X, nv, self.config.edge_offset / a, (mask, A, a), occ

    def _posterior(self, image, mask, A, diameter_px, hidden=None, reach=None):
        """Per-pixel foreground posterior (float32), from colour histograms of the silhouette (eroded; less
        the ``hidden`` viewport pixels) and a ring around it, the silhouette in image pixels (bool), and
        their window's origin (x0, y0) in the image. ``reach``: px beyond the silhouette's box the window
        must cover besides the ring (None: the whole image). The window holds every pixel the histograms
        count, so the values are the whole image's there."""
        import cv2

        H, W = image.shape[:2]
        ring = max(3, round(self.config.ring * diameter_px))
        a = 1.0 / A[0, 0]  # A: viewport px -> image px, a scale and a shift
        if reach is None:
            x0, y0, x1, y1 = 0, 0, W, H
        else:
            bx, by, bw, bh = cv2.boundingRect(mask)
            m = max(ring + self.config.bg_margin, reach) + 3
            x0 = max(0, int(np.floor(bx / a + A[0, 2] - m)))
            y0 = max(0, int(np.floor(by / a + A[1, 2] - m)))
            x1 = min(W, int(np.ceil((bx + bw) / a + A[0, 2] + m)) + 1)
            y1 = min(H, int(np.ceil((by + bh) / a + A[1, 2] + m)) + 1)
            if x1 <= x0 or y1 <= y0:
                return None, np.zeros((max(y1 - y0, 0), max(x1 - x0, 0)), bool), (x0, y0)
        # image pixel -> viewport coordinates, from the pixel's absolute position (the same for any window)
        mx, my = np.meshgrid(((np.arange(x0, x1) - A[0, 2]) * a).astype(np.float32),
                             ((np.arange(y0, y1) - A[1, 2]) * a).astype(np.float32))
        sil = cv2.remap(mask * 255, mx, my, cv2.INTER_LINEAR) > 127
        k3 = np.ones((3, 3), np.uint8)
        fg = cv2.erode(sil.astype(np.uint8), k3, iterations=self.config.fg_margin) > 0  # 0 iterations: a copy
        if hidden is not None:
            fg &= ~(cv2.remap(hidden.astype(np.uint8) * 255, mx, my, cv2.INTER_NEAREST) > 127)
        grown = cv2.dilate(sil.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * ring + 1,) * 2)) > 0
        near = cv2.dilate(sil.astype(np.uint8), k3, iterations=self.config.bg_margin) > 0
        bg = grown & ~near
        b = self.config.hist_bins
        shift = 8 - int(np.log2(b))
        q = (image[y0:y1, x0:x1] >> shift).astype(np.int32)
        code = (q[..., 0] * b + q[..., 1]) * b + q[..., 2]
        n = b ** 3
        S = max(1, self.config.local_regions)
        key = code
        if S > 1:  # each angular sector about the silhouette's centroid: its own histograms, the whole one's as a prior
            ys, xs = np.nonzero(sil)
            cx, cy = xs.mean() + x0, ys.mean() + y0  # absolute image px: the same for any window
            ang = np.arctan2((np.arange(y0, y1) - cy)[:, None], (np.arange(x0, x1) - cx)[None, :])
            key = np.minimum(((ang + np.pi) * (S / (2 * np.pi))).astype(np.int32), S - 1) * n + code
        # counts per sector (one sector: the whole silhouette's); the whole pair is their sum
        cf = np.bincount(key[fg], minlength=S * n).reshape(S, n).astype(np.float64)
        cb = np.bincount(key[bg], minlength=S * n).reshape(S, n).astype(np.float64)
        hf, hb = cf.sum(0), cb.sum(0)
        if hf.sum() < 10 or hb.sum() < 10:
            return None, sil, (x0, y0)
        hf = hf / hf.sum()
        hb = hb / hb.sum()
        if S > 1:
            beta = self.config.local_prior

            def mixed(counts, whole):  # (counts + beta * whole) / (N + beta); a sector with neither: the whole pair
                total = counts.sum(1, keepdims=True)
                w = np.divide(total, total + beta, out=np.zeros_like(total), where=total + beta > 0)
                return w * counts / np.maximum(total, 1.0) + (1.0 - w) * whole + 1e-6

            lf, lb = mixed(cf, hf), mixed(cb, hb)
            pf = (lf / (lf + lb)).astype(np.float32).ravel()
            return pf[key], sil, (x0, y0)
        hf, hb = hf + 1e-6, hb + 1e-6
        pf = (hf / (hf + hb)).astype(np.float32)
        return pf[code], sil, (x0, y0)

    def refine(self, image: np.ndarray, model, R, t, K, others=()) -> RefineResult:
        """Refine the pose (R, t: model -> OpenCV camera, mm) of ``model`` in ``image``; ``others``:
        ``(model, R, t)`` of the other objects in the image, which may hide it (``occlusion``)."""
        import cv2

        cfg = self.config
        image = np.ascontiguousarray(image[..., :3])
        K = np.asarray(K, np.float64)
        R = np.asarray(R, np.float64).copy()
        t = np.asarray(t, np.float64).reshape(3).copy()
        H, W = image.shape[:2]
        centre_m = _box_centre(model)
        L = int(cfg.line_steps)
        s_grid = np.arange(-L, L + 1, dtype=np.float64)  # sample positions, in steps, outward positive
        d_grid = np.arange(-(L - 1), L - 1 + 0.25, 0.5)  # candidate contour positions
        prior = np.diag([1.0 / cfg.prior_rotation ** 2] * 3 + [1.0 / cfg.prior_translation ** 2] * 3)
        history, lines, ok, evidence = [], 0, False, 0.0
        for scale in cfg.scales:
            c = R @ centre_m + t
            if c[2] <= 1e-3:
                break
            centre_px = (K @ c)[:2] / c[2]
            diameter_px = float(K[0, 0] * model.diameter / c[2])
            got = self._contour(model, R, t, K, centre_px, diameter_px, others)
            if got is None:
                break
            X, nv, edge, (mask, A, a), occ = got
            step = max(cfg.min_step, scale * diameter_px / L)
            kk = round(step) | 1 if step > 1.5 else 1  # each sample stands for its stretch of the line
            # the posterior on a window that holds the lines and the blur around them (the whole image: the same)
            reach = None if self._full_frame else L * step + abs(edge) + kk // 2 + 2
            # inside the silhouette, where another object is the front-most: not this object's colours
            pf, sil, (ox, oy) = self._posterior(image, mask, A, diameter_px,
                                                None if occ is None else (occ > 0) & (mask > 0), reach)
            if pf is None:
                break
            if kk > 1:
                pf = cv2.blur(pf, (kk, kk))
            base = project_points(X, K) + edge * nv
            pos = base[:, None, :] + (s_grid[None, :, None] * step) * nv[:, None, :]  # (n, 2L+1, 2)
            inside_img = (pos[..., 0] >= 0) & (pos[..., 0] <= W - 1) & (pos[..., 1] >= 0) & (pos[..., 1] <= H - 1)
            # window coordinates: the image's float32 ones less an integer (exact, so the same samples)
            mx = np.clip(np.clip(pos[..., 0], 0, W - 1).astype(np.float32) - np.float32(ox), 0, pf.shape[1] - 1)
            my = np.clip(np.clip(pos[..., 1], 0, H - 1).astype(np.float32) - np.float32(oy), 0, pf.shape[0] - 1)
            p = cv2.remap(pf, mx, my, cv2.INTER_LINEAR)
            # inner samples past the far side of the silhouette see background again: not this edge's
            on_sil = cv2.remap(sil.astype(np.float32), mx, my, cv2.INTER_NEAREST) > 0.5
            valid = inside_img & ((s_grid[None, :] >= 0) | on_sil)
            if occ is not None:  # samples where another object lies in front of this contour: no evidence
                sv = occ.shape[0]
                pv = a * (pos - centre_px) + (sv - 1) / 2
                iv = np.round(pv).astype(int)
                inv = (iv >= 0).all(-1) & (iv < sv).all(-1)
                d = np.zeros(inv.shape, np.float32)
                d[inv] = occ[iv[inv][:, 1], iv[inv][:, 0]]
                occluded = (d > 0) & (d < X[:, 2:3] - 0.05 * float(model.diameter))
                valid &= ~occluded
                valid &= ~occluded[:, L:L + 1]  # the contour point itself hidden: the whole line
            x = s_grid[None, None, :] - d_grid[None, :, None]  # (1, D, S)
            hf = 0.5 - cfg.amplitude * np.tanh(x / (2.0 * cfg.slope))
            pp = p[:, None, :].astype(np.float64)
            like = np.log(np.clip(hf * pp + (1.0 - hf) * (1.0 - pp), 1e-9, None))
            logp = np.sum(like * valid[:, None, :], axis=2)  # (n, D)
            logp -= logp.max(axis=1, keepdims=True)
            prob = np.exp(logp)
            prob /= prob.sum(axis=1, keepdims=True)
            mu = prob @ d_grid
            var = prob @ (d_grid ** 2) - mu ** 2
            use = (valid.sum(1) >= L) & (np.abs(mu) < L - 2) & (var < (0.5 * L) ** 2)
            lines = int(use.sum())
            # the share of the contour with an image edge where it is now (within 1.5 steps), over all
            # its lines (hidden, out-of-image and uninformative ones count as none)
            evidence = float(prob[use][:, np.abs(d_grid) <= 1.5].sum()) / max(len(X), 1)
            if lines < cfg.min_lines:
                break
            mu_px = mu[use] * step
            w = 1.0 / (var[use] * step ** 2 + step ** 2 / 12.0)
            J = contour_jacobian(X[use], nv[use], c, K)
            Hm = (J * w[:, None]).T @ J + prior
            theta = np.linalg.solve(Hm, (J * w[:, None]).T @ mu_px)
            R, t = apply_pose_step(R, t, c, theta)
            history.append((R.copy(), t.copy()))
            ok = True
        return RefineResult(R=R, t=t, ok=ok, lines=lines, evidence=evidence, history=history)


@REFINERS.register("none")
def no_refiner(models_dir: str | None = None) -> None:
    """No refinement: the KPD + PnP poses as they are (the paper)."""
    return None


def region_refiner(models_dir: str | None = None, **settings: Any) -> RegionRefiner:
    """:class:`RegionRefiner` with :class:`RegionRefineConfig` ``settings``; ``models_dir``: a BOP models
    folder with the objects' meshes (None: set them later, e.g. kpd6d-evaluate's dataset models)."""
    ref = RegionRefiner(RegionRefineConfig(**settings))
    if models_dir is not None:
        from kpd6d.objects import load_bop_models

        ref.set_models(load_bop_models(models_dir), source=f"models_dir={models_dir}")
    return ref


# the factory's signature lists the config's fields (their defaults in one place: RegionRefineConfig), so
# the registry names them in errors and conf/refiner/region.yaml is checked against them
region_refiner.__signature__ = inspect.Signature(
    [inspect.Parameter("models_dir", inspect.Parameter.KEYWORD_ONLY, default=None)]
    + [inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, default=f.default) for f in fields(RegionRefineConfig)])
REFINERS.register("region")(region_refiner)


def build_refiner(cfg: Any, models: Any = None, where: str = "refiner", source: str | None = None) -> Any:
    """The refiner a config's ``refiner`` group describes (None, or ``name: none``: no refinement).

    A refiner with no meshes of its own (``models_dir: null``) takes ``models`` (a mapping or list of
    :class:`~kpd6d.objects.ObjectModel`, or a callable returning one, called only then; ``source`` says
    where they came from); with neither it raises, naming ``<where>.models_dir``."""
    if cfg is None:
        return None
    ref = build_from_cfg(REFINERS, cfg)
    if ref is not None and not ref.models:
        if models is None:
            raise ValueError(f"{where}.models_dir is required: pose refinement needs the objects' meshes "
                             f"(a BOP models folder)")
        ref.set_models(models() if callable(models) else models, source=source)
    return ref
