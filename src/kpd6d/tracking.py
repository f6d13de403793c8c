"""Pose tracking over video / camera frames: the detector only when needed, KPD + PnP every frame.

:class:`PoseTracker` ``(pipeline, detect_every=0, lost_threshold=0.3, smoothing=0.0, margin=0.15,
min_in_view=0.3, obj_ids=None, search_every=1)`` holds one track per object id; ``tracker.update(image, K)`` processes
the next frame and returns ``{"frame", "detected", "detector_calls", "poses"}``.
:func:`track_frames` runs it over an iterable of frames. ``pipeline`` is a
:class:`kpd6d.pipeline.PosePipeline` or a :class:`kpd6d.deploy.runtime.RuntimePipeline`: the tracker
calls their ``detect`` (the detector alone) and ``predict_boxes`` (KPD + PnP on given boxes, with
the pipeline's top-l, ``refine_boxes`` and ``min_confidence``), the same code ``predict_batch`` runs.

Per frame:

1. each active track's crop box is the box of its object's points (``pipeline.object_points``: the
   checkpoint's surface points, else its keypoints) projected with K and the track's previous
   (unsmoothed) pose, grown by ``margin`` (``1 + margin`` times its width and height, same centre)
   and clipped to the image. A track whose projected box lies less than ``min_in_view`` inside the
   image (or behind the camera) is lost before the KPD runs;
2. the detector runs on the first frame; while no track is active, a track is lost or an object of
   ``obj_ids`` has no active track, at most every ``search_every`` frames (1: every frame; more
   spares the detector while an object stays out of view, at the cost of up to ``search_every - 1``
   frames of re-acquisition delay); and every ``detect_every`` frames (0: only when needed). On such a frame a detected object is estimated from its detection box (its highest
   score; one instance per object id), an active track not detected from its own box;
3. one ``predict_boxes`` call estimates every box. A pose is ``ok`` when the pipeline says ok, its
   ``confidence`` (the pipeline's, :mod:`kpd6d.pnp.confidence`) is at least ``lost_threshold`` and its
   projection lies at least ``min_in_view`` inside the image; otherwise the track is lost (``R``,
   ``t`` NaN, ``reason`` says why) and the next frame runs the detector. A lost object the detector
   does not find is reported every frame with ``ok`` False, ``source`` ``"detector"`` and
   confidence 0 until it is found again (re-acquisition);
4. smoothing ``alpha`` in [0, 1) (0: off) filters the reported pose on SE(3):
   ``R_s = slerp(R_s_prev, R, 1 - alpha)`` (quaternion slerp, the geodesic), ``t_s = alpha t_s_prev +
   (1 - alpha) t``; a new or re-acquired track starts from its measurement. The crops follow the
   unsmoothed poses.

Each pose dict: ``obj_id``, ``R``, ``t`` (the smoothed pose), ``confidence``, ``ok``, ``source``
(``"detector"``: estimated from this frame's detection box, ``"track"``: from the previous pose),
``reason`` ("" when ok), ``score`` (the detection score the track started from), ``box`` (the crop
box), ``raw_R`` / ``raw_t`` (the unsmoothed estimate), ``residual_px``, ``keypoints_2d``,
``confidences``, ``used``. :attr:`PoseTracker.stats` counts ``frames``, ``detector_calls`` and
``kpd_calls``. numpy only; no torch import here.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from kpd6d.geometry import clip_box_to_image, project_points

__all__ = ["PoseTracker", "Track", "matrix_from_quat", "projected_box", "quat_from_matrix", "slerp_rotation",
           "smooth_pose", "track_frames"]

SOURCES = ("detector", "track")


# -- SE(3) smoothing -------------------------------------------------------------------------------
def quat_from_matrix(R) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (3, 3) (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    d = np.array([tr, R[0, 0], R[1, 1], R[2, 2]])
    i = int(np.argmax(d))
    if i == 0:
        s = 2.0 * np.sqrt(max(1.0 + tr, 1e-300))
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    elif i == 1:
        s = 2.0 * np.sqrt(max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 1e-300))
        q = np.array([(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s])
    elif i == 2:
        s = 2.0 * np.sqrt(max(1.0 + R[1, 1] - R[0, 0] - R[2, 2], 1e-300))
        q = np.array([(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s])
    else:
        s = 2.0 * np.sqrt(max(1.0 + R[2, 2] - R[0, 0] - R[1, 1], 1e-300))
        q = np.array([(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def matrix_from_quat(q) -> np.ndarray:
    """Rotation matrix (3, 3) of a quaternion (w, x, y, z) (normalised first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def slerp_rotation(R0, R1, s: float) -> np.ndarray:
    """The rotation a fraction ``s`` of the way from ``R0`` to ``R1`` along the shorter geodesic
    (quaternion slerp; ``s=0``: R0, ``s=1``: R1)."""
    q0, q1 = quat_from_matrix(R0), quat_from_matrix(R1)
    dot = float(q0 @ q1)
    if dot < 0:  # q and -q are the same rotation: take the short way
        q1, dot = -q1, -dot
    dot = min(dot, 1.0)
    theta = np.arccos(dot)
    if theta < 1e-8:
        q = (1 - s) * q0 + s * q1
    else:
        q = (np.sin((1 - s) * theta) * q0 + np.sin(s * theta) * q1) / np.sin(theta)
    return matrix_from_quat(q)


def smooth_pose(R_prev, t_prev, R, t, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """One exponential smoothing step on SE(3): ``(slerp(R_prev, R, 1 - alpha), alpha t_prev + (1 - alpha) t)``."""
    if not 0.0 <= alpha < 1.0:
        raise ValueError(f"smoothing alpha must be in [0, 1), got {alpha}")
    if alpha == 0.0:
        return np.asarray(R, dtype=np.float64).copy(), np.asarray(t, dtype=np.float64).copy()
    R_s = slerp_rotation(R_prev, R, 1.0 - alpha)
    t_s = alpha * np.asarray(t_prev, dtype=np.float64) + (1.0 - alpha) * np.asarray(t, dtype=np.float64)
    return R_s, t_s


# -- crop boxes from poses -------------------------------------------------------------------------
def projected_box(points, K, R, t, image_hw, margin: float = 0.0) -> tuple[np.ndarray | None, float]:
    """(box, in_view): the box (4,) xywh of ``points`` (P, 3) mm projected with ``K``, ``R``, ``t``,
    grown to ``1 + margin`` times its width and height about its centre and clipped to the image of
    ``image_hw`` = (H, W) (None when nothing of it is left, at least :data:`MIN_BOX_PX` a side, or a
    point is behind the camera); ``in_view`` the fraction of the unclipped, ungrown box's area inside
    the image (0 when behind the camera)."""
    H, W = int(image_hw[0]), int(image_hw[1])
    R, t = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        return None, 0.0
    uv, z = project_points(np.asarray(points, dtype=np.float64), np.asarray(K, dtype=np.float64), R, t,
                           return_depth=True)
    if not (z > 0).all() or not np.isfinite(uv).all():
        return None, 0.0
    lo, hi = uv.min(0), uv.max(0)
    area = float(np.prod(np.maximum(hi - lo, 1e-9)))
    ilo, ihi = np.clip(lo, 0, [W, H]), np.clip(hi, 0, [W, H])
    in_view = float(np.prod(np.maximum(ihi - ilo, 0.0))) / area
    c, half = (lo + hi) / 2, (hi - lo) * (1.0 + margin) / 2
    return clip_box_to_image(c - half, c + half, W, H), in_view


# -- the tracker -----------------------------------------------------------------------------------
@dataclass
class Track:
    """One object's state: the last unsmoothed pose (the crops follow it), the reported smoothed pose,
    whether it is lost, and since which frame it runs."""

    obj_id: int
    R: np.ndarray
    t: np.ndarray
    R_s: np.ndarray
    t_s: np.ndarray
    score: float = 1.0
    lost: bool = False
    started: int = 0


def _nan_pose() -> tuple[np.ndarray, np.ndarray]:
    return np.full((3, 3), np.nan), np.full(3, np.nan)


class PoseTracker:
    """Tracks the objects in a stream of frames with a pose ``pipeline`` (module docstring)."""

    def __init__(self, pipeline, *, detect_every: int = 0, lost_threshold: float = 0.3, smoothing: float = 0.0,
                 margin: float = 0.15, min_in_view: float = 0.3, obj_ids: Iterable[int] | None = None,
                 search_every: int = 1) -> None:
        for name in ("detect", "predict_boxes", "object_points"):
            if not hasattr(pipeline, name):
                raise TypeError(f"tracking needs a pipeline with .{name}() (PosePipeline or RuntimePipeline), "
                                f"got {type(pipeline).__name__}")
        if int(detect_every) < 0:
            raise ValueError(f"detect_every must be >= 0 (0: only when needed), got {detect_every}")
        if int(search_every) < 1:
            raise ValueError(f"search_every must be >= 1 (1: search on every frame while a track is lost), "
                             f"got {search_every}")
        if not 0.0 <= float(lost_threshold) <= 1.0:
            raise ValueError(f"lost_threshold must be in [0, 1], got {lost_threshold}")
        if not 0.0 <= float(smoothing) < 1.0:
            raise ValueError(f"smoothing must be in [0, 1) (0: off), got {smoothing}")
        if not float(margin) >= 0.0:
            raise ValueError(f"margin must be >= 0, got {margin}")
        if not 0.0 < float(min_in_view) <= 1.0:
            raise ValueError(f"min_in_view must be in (0, 1], got {min_in_view}")
        self.pipeline = pipeline
        self.detect_every, self.lost_threshold = int(detect_every), float(lost_threshold)
        self.search_every = int(search_every)
        self.smoothing, self.margin, self.min_in_view = float(smoothing), float(margin), float(min_in_view)
        self.obj_ids = None if obj_ids is None else [int(o) for o in obj_ids]
        if self.obj_ids is not None:
            known = {int(o) for o in pipeline.kpd.keypoints_3d}
            unknown = sorted(set(self.obj_ids) - known)
            if unknown:
                raise ValueError(f"obj_ids {unknown}: the KPD has no keypoints for them (known: {sorted(known)})")
        self._points: dict[int, np.ndarray] = {}
        self.reset()

    def reset(self) -> None:
        """Forget every track and counter (a new stream)."""
        self.tracks: dict[int, Track] = {}
        self.frame = 0
        self.last_detection: int | None = None
        self.stats = {"frames": 0, "detector_calls": 0, "kpd_calls": 0}

    def _object_points(self, oid: int) -> np.ndarray:
        if oid not in self._points:
            self._points[oid] = self.pipeline.object_points(oid)
        return self._points[oid]

    def _needs_detection(self, active: dict[int, Track]) -> bool:
        if self.last_detection is None:
            return True
        since = self.frame - self.last_detection
        searching = (not active or any(tr.lost for tr in self.tracks.values())
                     or (self.obj_ids is not None and any(o not in active for o in self.obj_ids)))
        if searching and since >= self.search_every:  # a lost or missing object: search, at most this often
            return True
        return self.detect_every > 0 and since >= self.detect_every

    def update(self, image: np.ndarray, K, targets: dict | None = None) -> dict[str, Any]:
        """Process the next frame (uint8 (H, W, 3) RGB, intrinsics ``K`` (3, 3)); ``targets`` goes to the
        detector when it runs (the oracle's GT boxes). Returns ``{"frame": index, "detected": whether
        the detector ran, "detector_calls": so far, "poses": [pose dict per tracked object]}``."""
        K = np.asarray(K, dtype=np.float64)
        hw = np.asarray(image).shape[:2]
        frame = self.frame
        poses: dict[int, dict] = {}
        # 1. crop boxes from the previous poses; a projection leaving the image loses the track
        boxes: dict[int, tuple[np.ndarray, str, float]] = {}
        for oid, tr in self.tracks.items():
            if tr.lost:
                continue
            box, in_view = projected_box(self._object_points(oid), K, tr.R, tr.t, hw, self.margin)
            if box is None or in_view < self.min_in_view:
                tr.lost = True
                poses[oid] = self._lost(oid, "track", f"the pose's projection left the image ({in_view:.0%} in view "
                                                      f"< min_in_view={self.min_in_view:g})")
            else:
                boxes[oid] = (box, "track", tr.score)
        active = {o: tr for o, tr in self.tracks.items() if not tr.lost}
        # 2. the detector, when needed
        detected = self._needs_detection(active)
        if detected:
            dets = self.pipeline.detect([image], None if targets is None else [targets])[0]
            self.stats["detector_calls"] += 1
            self.last_detection = frame
            found: set[int] = set()
            for d in dets:  # highest score first: the first box of an object id is its instance
                oid = int(d["obj_id"])
                if oid in found or (self.obj_ids is not None and oid not in self.obj_ids):
                    continue
                found.add(oid)
                boxes[oid] = (np.asarray(d["box"], dtype=np.float64), "detector", float(d["score"]))
        # 3. KPD + PnP on every box at once
        order = list(boxes)
        if order:
            preds = self.pipeline.predict_boxes([image], K, np.stack([boxes[o][0] for o in order]), order,
                                                scores=[boxes[o][2] for o in order])[0]
            self.stats["kpd_calls"] += 1
            for oid, p in zip(order, preds):
                poses[oid] = self._measure(oid, p, boxes[oid][1], K, hw, frame)
        # lost objects the detector did not find this frame
        for oid, tr in self.tracks.items():
            if oid not in poses:
                tr.lost = True
                poses[oid] = self._lost(oid, "detector", "lost: not found by the detector")
        self.frame += 1
        self.stats["frames"] += 1
        return {"frame": frame, "detected": detected, "detector_calls": self.stats["detector_calls"],
                "poses": [poses[o] for o in sorted(poses)]}

    def _measure(self, oid: int, p: dict, source: str, K, hw, frame: int) -> dict:
        """The track update from one pipeline estimate ``p`` (a pose dict of ``predict_boxes``)."""
        conf = float(p.get("confidence", 0.0))
        R, t = np.asarray(p["R"], dtype=np.float64), np.asarray(p["t"], dtype=np.float64)
        reason = "" if p["ok"] else f"lost: {p.get('reason') or 'not ok'}"
        if not reason and not conf >= self.lost_threshold:
            reason = f"lost: confidence {conf:.3g} < lost_threshold={self.lost_threshold:g}"
        if not reason:
            _, in_view = projected_box(self._object_points(oid), K, R, t, hw)
            if in_view < self.min_in_view:
                reason = f"lost: the pose's projection left the image ({in_view:.0%} in view)"
        tr = self.tracks.get(oid)
        rec = {"obj_id": oid, "confidence": conf, "ok": not reason, "source": source, "reason": reason,
               "score": float(p.get("score", 1.0)), "box": np.asarray(p["box"], dtype=np.float64),
               "residual_px": float(p.get("residual_px", np.nan)), "keypoints_2d": p["keypoints_2d"],
               "confidences": p["confidences"], "used": p["used"]}
        if reason:
            if tr is not None:
                tr.lost = True
            rec["R"], rec["t"] = _nan_pose()
            rec["raw_R"], rec["raw_t"] = _nan_pose()
            return rec
        if tr is None or tr.lost:  # a new or re-acquired track: smoothing starts from the measurement
            tr = Track(oid, R.copy(), t.copy(), R.copy(), t.copy(), score=rec["score"], started=frame)
            self.tracks[oid] = tr
        else:
            tr.R_s, tr.t_s = smooth_pose(tr.R_s, tr.t_s, R, t, self.smoothing)
            tr.R, tr.t = R.copy(), t.copy()
            if source == "detector":
                tr.score = rec["score"]
        rec["R"], rec["t"] = tr.R_s.copy(), tr.t_s.copy()
        rec["raw_R"], rec["raw_t"] = R.copy(), t.copy()
        return rec

    def _lost(self, oid: int, source: str, reason: str) -> dict:
        R, t = _nan_pose()
        return {"obj_id": oid, "R": R, "t": t, "raw_R": R.copy(), "raw_t": t.copy(), "confidence": 0.0, "ok": False,
                "source": source, "reason": reason, "score": 0.0, "box": np.full(4, np.nan), "residual_px": np.nan,
                "keypoints_2d": np.zeros((0, 2)), "confidences": np.zeros(0), "used": np.zeros(0, bool)}


def track_frames(pipeline, frames: Iterable[np.ndarray], K, targets: Iterable[dict | None] | None = None,
                 **options: Any) -> Iterator[dict[str, Any]]:
    """:meth:`PoseTracker.update` over ``frames`` in order (``options``: :class:`PoseTracker`'s); ``targets``
    an iterable of per-frame detector targets (the oracle), or None. Yields each frame's result."""
    tracker = PoseTracker(pipeline, **options)
    tg = iter(targets) if targets is not None else None
    for image in frames:
        yield tracker.update(image, K, next(tg) if tg is not None else None)
