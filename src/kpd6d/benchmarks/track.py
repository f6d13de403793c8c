"""``kpd6d-benchmark track``: a measured tracked-video benchmark (fps and accuracy against ground truth).

Where ``kpd6d-benchmark pipeline`` derives a tracked fps from stage timings, this one renders a video
with known poses, runs the real tracker over it and measures:

1. the video (:func:`make_video`): the objects (a BOP models folder, ``--models-dir``, or the
   procedural objects) each move along a smooth known trajectory: side to side, up and down and
   nearer / farther (600-900 mm, +-60 mm) in its own cell of the image (one row of cells, two for more
   than 3 objects), staying in view (objects larger than their cell overlap), while the
   camera's viewpoint on it turns about the object's z axis (~0.8 deg per frame, from above:
   elevation 20-45 deg, wobbling) -- rendered with :class:`kpd6d.render.Renderer` at the camera K
   (default LineMod's, 640x480) over one procedural background (:mod:`kpd6d.synth.backgrounds`),
   with a little per-frame sensor noise. ``--leave N``: in the middle of the video every object slides
   out past the nearer side edge (over :data:`RAMP_FRAMES` frames), stays entirely out for N frames and
   slides back, so loss and re-acquisition are exercised (each is out of view a few frames longer than
   N: the report counts the out-of-view frames from the ground truth).
2. the modes, on the same frames: ``tracked`` (:class:`kpd6d.tracking.PoseTracker` with
   ``--detect-every``, ``--lost-threshold``, ``--smoothing``; each ``update`` timed) and
   ``detect_every_frame`` (``pipeline.predict_batch([frame], K)``, each call timed). ``--warmup``
   frames run through each first, untimed.
3. the report per mode: fps (frames / timed seconds), median and 95th-percentile latency per frame,
   the fraction of frames the detector ran on, and against the ground truth, per object-frame in view
   (at least half of the object's projected box in the image): the fraction with an ok pose, the
   ADD(-S) < 0.1 d pass rate of the ok poses (ADD-S for symmetric objects; :mod:`kpd6d.evaluation`;
   2000 model vertices) and of all in-view object-frames, the median rotation (deg) and translation
   (mm) errors of the ok poses (geodesic: for a symmetric object it includes the symmetry's
   ambiguity); the object-frames out of view (none of the projected box in the
   image), those reported lost (not ok, or not reported yet; in or out of view), lost while in view
   and ok while out of view (object-frames partly in the image count in neither), and for each return
   into view after being entirely out, the frames from its first in-view frame to its first ok pose
   (re-acquisition; None: never). A pose is ok when the pipeline says ok and its confidence is at
   least ``--lost-threshold`` -- the tracker's own gate, applied to the detect-every-frame poses too
   (one per object id: the highest-scored detection) so both modes are gated alike.

The pipeline is :meth:`PosePipeline.from_checkpoints <kpd6d.pipeline.PosePipeline.from_checkpoints>`
(``--kpd-ckpt``, ``--detector-ckpt``; ``oracle``: ground-truth boxes of the visible pixels) or an
export (``--export-dir`` with ``--backend onnxruntime|openvino``, or ``torch`` for the checkpoints it
was made from). ``--json PATH`` also writes the report (per-frame latencies included).
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from kpd6d.geometry import LINEMOD_IMAGE_SIZE, LINEMOD_K, bbox_from_points, pose_from_view

__all__ = ["RAMP_FRAMES", "THRESHOLDS", "Video", "benchmark", "build_pipeline", "calibrate", "format_calibration",
           "format_table", "leave_range", "main", "make_video", "run_detect_every_frame", "run_tracked", "score",
           "trajectories"]

#: distance range of the trajectories' centres (mm); each object moves +- DEPTH_SWING_MM about its own
DISTANCE_MM = (600.0, 900.0)
DEPTH_SWING_MM = 60.0
#: the viewpoint turns about the object's z axis by about this much per frame (degrees)
TURN_DEG_PER_FRAME = 0.8
#: frames to slide out of view and back in (``leave``)
RAMP_FRAMES = 12
#: an object-frame is in view when at least this fraction of its projected box lies in the image
IN_VIEW = 0.5
#: model points for ADD(-S) (a vertex subsample)
MODEL_POINTS = 2000
MODES = ("tracked", "detect_every_frame")


@dataclass
class Video:
    """Rendered frames and their ground truth.

    ``frames``: uint8 RGB (H, W, 3). ``gt[i]``: one dict per object in frame ``i``: ``obj_id``, ``R``
    (3, 3), ``t`` (3,) mm (model -> camera), ``in_view`` (fraction of the projected box in the image),
    ``visible_px`` (rendered visible pixels), ``box`` (xywh of the visible pixels, None when none) and,
    when asked, ``mask`` (H, W) bool. ``leave``: ``(start, stop)`` frames during which every object is
    entirely out of the image, or None."""

    frames: list[np.ndarray]
    gt: list[list[dict]]
    K: np.ndarray
    leave: tuple[int, int] | None = None

    @property
    def obj_ids(self) -> list[int]:
        return [int(g["obj_id"]) for g in self.gt[0]] if self.gt else []

    def targets(self, i: int) -> dict:
        """The oracle detector's targets of frame ``i``: the boxes of the visible pixels."""
        seen = [g for g in self.gt[i] if g["box"] is not None]
        return {"boxes": np.array([g["box"] for g in seen], dtype=np.float64).reshape(-1, 4),
                "obj_ids": np.array([g["obj_id"] for g in seen], dtype=np.int64)}


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def leave_range(num_frames: int, leave: int) -> tuple[int, int, int] | None:
    """``(exit start, first frame all the way out, start of the return)`` of a ``leave``-frame stretch
    out of view in the middle of ``num_frames`` frames (the ramps take :data:`RAMP_FRAMES` each; None
    when ``leave`` is 0); ValueError when it does not fit."""
    if int(leave) < 0:
        raise ValueError(f"leave must be >= 0 frames (0: off), got {leave}")
    if not leave:
        return None
    need = int(leave) + 2 * RAMP_FRAMES + 4
    if num_frames < need:
        raise ValueError(f"leave={leave} needs at least {need} frames ({RAMP_FRAMES} to leave, {leave} out, "
                         f"{RAMP_FRAMES} to come back, 2 before and after), got {num_frames}")
    s0 = (num_frames - (int(leave) + 2 * RAMP_FRAMES)) // 2
    return s0, s0 + RAMP_FRAMES, s0 + RAMP_FRAMES + int(leave)


def trajectories(objects, K=LINEMOD_K, image_size=LINEMOD_IMAGE_SIZE, num_frames: int = 150, seed: int = 0,
                 leave: int = 0) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """Per object, ``num_frames`` poses ``(R, t)`` (model -> OpenCV camera, mm) of a smooth trajectory
    (module docstring) for a camera ``K`` and ``image_size`` (W, H); deterministic by ``seed``."""
    if int(num_frames) < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    K = np.asarray(K, dtype=np.float64)
    W, H = int(image_size[0]), int(image_size[1])
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    n = len(objects)
    rows = 1 if n <= 3 else 2
    cols = math.ceil(n / rows)
    i = np.arange(int(num_frames), dtype=np.float64)
    lv = leave_range(int(num_frames), leave)
    out = []
    for j, obj in enumerate(objects):
        rng = np.random.default_rng([int(seed), j])
        d = float(obj.diameter)
        z0 = rng.uniform(*DISTANCE_MM)
        r_px = 0.5 * d * fx / max(z0 - DEPTH_SWING_MM, 1.0)  # the object's half size at its nearest
        # its cell of the image (one row of n cells; two rows for more than 3 objects), wholly in view
        u_c = float(np.clip(W * (j % cols + 0.5) / cols, min(r_px + 4, W / 2), max(W - r_px - 4, W / 2)))
        v_c = H * ((j // cols + 0.5) / rows + rng.uniform(-0.05, 0.05) / rows)
        v_c = float(np.clip(v_c, min(r_px + 4, H / 2), max(H - r_px - 4, H / 2)))
        ax = max(0.0, min(0.3 * W / cols, 0.15 * W, u_c - r_px - 4, W - r_px - 4 - u_c))
        ay = max(0.0, min(0.1 * H / rows, v_c - r_px - 4, H - r_px - 4 - v_c))
        ph = rng.uniform(0, 2 * np.pi, 5)
        px, py, pz, pe, pi = rng.uniform(0.8, 1.2, 5) * np.array([120.0, 90.0, 150.0, 110.0, 130.0])
        u = u_c + ax * np.sin(2 * np.pi * i / px + ph[0])
        v = v_c + ay * np.sin(2 * np.pi * i / py + ph[1])
        z = z0 + DEPTH_SWING_MM * np.sin(2 * np.pi * i / pz + ph[2])
        if lv is not None:  # slide out sideways past the nearer edge (by its size beyond it) and back
            s0, _, s2 = lv
            f = _smoothstep((i - s0) / RAMP_FRAMES) - _smoothstep((i - s2) / RAMP_FRAMES)
            side = -1.0 if u_c < W / 2 else 1.0
            to_edge = (u_c if side < 0 else W - u_c) + ax
            u = u + side * f * (to_edge + d * fx / np.maximum(z - d, 1.0) + 8)
        turn = np.deg2rad(TURN_DEG_PER_FRAME) * rng.uniform(0.75, 1.25) * rng.choice([-1.0, 1.0])
        az = rng.uniform(0, 2 * np.pi) + turn * i
        el = rng.uniform(0.35, 0.8) + 0.12 * np.sin(2 * np.pi * i / pe + ph[3])
        inplane = rng.uniform(-0.3, 0.3) + 0.1 * np.sin(2 * np.pi * i / pi + ph[4])
        poses = []
        for k in range(int(num_frames)):
            R = pose_from_view(float(az[k]), float(el[k]), 1.0, float(inplane[k]))[0]
            t = np.array([(u[k] - cx) * z[k] / fx, (v[k] - cy) * z[k] / fy, z[k]])
            poses.append((R, t))
        out.append(poses)
    return out


def _model_points(obj) -> np.ndarray:
    v = obj.vertices
    return v[:: max(1, len(v) // MODEL_POINTS)]


def make_video(objects, K=LINEMOD_K, image_size=LINEMOD_IMAGE_SIZE, num_frames: int = 150, seed: int = 0,
               leave: int = 0, noise: float = 2.0, masks: bool = False, renderer=None) -> Video:
    """Render ``objects`` (:class:`kpd6d.objects.ObjectModel`, distinct ``obj_id``) along
    :func:`trajectories` over one procedural background, with Gaussian pixel noise of std ``noise``
    (grey levels, per frame; 0: none). ``masks=True`` keeps each object's visible mask in its GT.
    ``renderer``: a :class:`kpd6d.render.Renderer` of ``image_size`` and ``K`` to reuse (else one is
    made and closed)."""
    from kpd6d.synth.backgrounds import procedural_background
    from kpd6d.tracking import projected_box

    ids = [int(o.obj_id) for o in objects]
    if len(set(ids)) != len(ids) or not ids:
        raise ValueError(f"make_video needs objects with distinct obj_ids, got {ids}")
    K = np.asarray(K, dtype=np.float64)
    W, H = int(image_size[0]), int(image_size[1])
    paths = trajectories(objects, K, (W, H), num_frames, seed, leave)
    lv = leave_range(int(num_frames), leave)
    bg = procedural_background(np.random.default_rng([int(seed), 1_000_003]), W, H)
    noise_rng = np.random.default_rng([int(seed), 1_000_033])
    points = [_model_points(o) for o in objects]
    own = renderer is None
    if own:
        from kpd6d.render import Renderer

        renderer = Renderer(W, H, K, antialias=False)
    frames, gt = [], []
    try:
        for k in range(int(num_frames)):
            inst = [(o, paths[j][k][0], paths[j][k][1]) for j, o in enumerate(objects)]
            res = renderer.render(inst, K=K, masks=True)
            img = np.where((res.depth > 0)[..., None], res.rgb, bg)
            if noise > 0:
                img = np.clip(img + noise_rng.normal(0.0, float(noise), img.shape), 0, 255)
            frames.append(np.ascontiguousarray(img.astype(np.uint8)))
            recs = []
            for j, (o, R, t) in enumerate(inst):
                m = res.masks_visib[j]
                ys, xs = np.nonzero(m)
                box = bbox_from_points(np.c_[xs, ys].astype(np.float64)) if len(xs) else None
                rec = {"obj_id": int(o.obj_id), "R": R, "t": t, "visible_px": len(xs), "box": box,
                       "in_view": projected_box(points[j], K, R, t, (H, W))[1]}
                if masks:
                    rec["mask"] = m
                recs.append(rec)
            gt.append(recs)
    finally:
        if own:
            renderer.close()
    return Video(frames, gt, K, None if lv is None else (lv[1], lv[2]))


# -- running the two modes -------------------------------------------------------------------------
def _is_oracle(pipeline) -> bool:
    det = getattr(pipeline, "detector", None)
    return getattr(det, "name", None) == "oracle" or type(det).__name__ == "OracleDetector"


def _best_per_object(poses: list[dict]) -> dict[int, dict]:
    """One pose per object id: the highest-scored detection's (the tracker's rule)."""
    out: dict[int, dict] = {}
    for p in poses:
        o = int(p["obj_id"])
        if o not in out or float(p.get("score", 0.0)) > float(out[o].get("score", 0.0)):
            out[o] = p
    return out


def run_tracked(pipeline, video: Video, *, detect_every: int = 10, lost_threshold: float = 0.3,
                smoothing: float = 0.0, warmup: int = 3, **tracker_options: Any) -> dict:
    """The tracker over ``video``: ``{"seconds": per frame, "detected": per frame, "poses": per frame
    {obj_id: (ok, R, t)}, "stats": tracker.stats}``; ``warmup`` frames first, untimed (then reset)."""
    from kpd6d.tracking import PoseTracker

    oracle = _is_oracle(pipeline)
    tracker = PoseTracker(pipeline, detect_every=detect_every, lost_threshold=lost_threshold, smoothing=smoothing,
                          **tracker_options)
    K = video.K
    for i in range(min(int(warmup), len(video.frames))):
        tracker.update(video.frames[i], K, video.targets(i) if oracle else None)
    tracker.reset()
    seconds, detected, poses = [], [], []
    for i, frame in enumerate(video.frames):
        tg = video.targets(i) if oracle else None
        t0 = time.perf_counter()
        res = tracker.update(frame, K, tg)
        seconds.append(time.perf_counter() - t0)
        detected.append(bool(res["detected"]))
        poses.append({int(p["obj_id"]): (bool(p["ok"]), p["R"], p["t"]) for p in res["poses"]})
    return {"seconds": seconds, "detected": detected, "poses": poses, "stats": dict(tracker.stats)}


def run_detect_every_frame(pipeline, video: Video, *, lost_threshold: float = 0.3, warmup: int = 3) -> dict:
    """``pipeline.predict_batch([frame], K)`` on every frame (as :func:`run_tracked`); a pose is ok when
    the pipeline says so and its confidence is at least ``lost_threshold``."""
    oracle = _is_oracle(pipeline)
    K = video.K
    for i in range(min(int(warmup), len(video.frames))):
        pipeline.predict_batch([video.frames[i]], K, [video.targets(i)] if oracle else None)
    seconds, poses, raw, kpd_calls = [], [], [], 0
    for i, frame in enumerate(video.frames):
        tg = [video.targets(i)] if oracle else None
        t0 = time.perf_counter()
        res = pipeline.predict_batch([frame], K, tg)[0]
        seconds.append(time.perf_counter() - t0)
        kpd_calls += bool(res)  # the KPD runs when the detector found something
        best = _best_per_object(res)
        poses.append({o: (bool(p["ok"]) and float(p.get("confidence", 0.0)) >= float(lost_threshold), p["R"], p["t"])
                      for o, p in best.items()})
        raw.append({o: (bool(p["ok"]), float(p.get("confidence", 0.0)), p["R"], p["t"]) for o, p in best.items()})
    n = len(video.frames)
    return {"seconds": seconds, "detected": [True] * n, "poses": poses, "raw": raw,
            "stats": {"frames": n, "detector_calls": n, "kpd_calls": kpd_calls}}


#: the confidence thresholds :func:`calibrate` tries
THRESHOLDS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)


def calibrate(video: Video, objects, raw: list[dict], thresholds=THRESHOLDS, max_add: float = 0.1) -> dict:
    """How well the pose confidence separates right from wrong poses, for choosing ``lost_threshold``
    on a rendered video (synthetic data: nothing real enters the choice).

    ``raw``: per frame ``{obj_id: (pipeline ok, confidence, R, t)}`` (:func:`run_detect_every_frame`'s
    ``"raw"``: one independent estimate per object and frame). Over the object-frames in view with a
    pose the pipeline calls ok, a pose is *right* when its ADD(-S) is below ``max_add`` × the diameter.
    For each threshold τ: ``kept`` (fraction with confidence ≥ τ), ``precision`` (right among kept),
    ``recall`` (kept among right) and ``f1``. ``best`` is the τ of the highest F1 (the lowest on ties).
    """
    from kpd6d.evaluation import add_error, adds_error

    models = {int(o.obj_id): o for o in objects}
    points = {o: _model_points(m) for o, m in models.items()}
    conf, right = [], []
    for i, recs in enumerate(video.gt):
        for g in recs:
            o = int(g["obj_id"])
            if g["in_view"] < IN_VIEW or o not in raw[i] or not raw[i][o][0]:
                continue
            _, c, R, t = raw[i][o]
            err = (adds_error if models[o].is_symmetric else add_error)(R, t, g["R"], g["t"], points[o])
            conf.append(c)
            right.append(err < max_add * models[o].diameter)
    conf_a, right_a = np.asarray(conf, dtype=np.float64), np.asarray(right, dtype=bool)
    rows = []
    for tau in thresholds:
        kept = conf_a >= float(tau)
        tp = int((kept & right_a).sum())
        precision = tp / int(kept.sum()) if kept.any() else None
        recall = tp / int(right_a.sum()) if right_a.any() else None
        f1 = (2 * precision * recall / (precision + recall) if precision and recall else 0.0)
        rows.append({"threshold": float(tau), "kept": float(kept.mean()) if len(kept) else None,
                     "precision": precision, "recall": recall, "f1": f1})
    best = max(rows, key=lambda r: (r["f1"], -r["threshold"]))["threshold"] if rows else None
    return {"poses": len(conf), "right": int(right_a.sum()), "max_add": float(max_add), "rows": rows, "best": best}


def format_calibration(cal: dict) -> str:
    """:func:`calibrate`'s table as markdown."""
    lines = [f"confidence calibration over {cal['poses']} ok poses in view ({cal['right']} right: ADD(-S) < "
             f"{cal['max_add']:g} d); best threshold by F1: {cal['best']}",
             "| threshold | kept | precision | recall | F1 |", "|---|---|---|---|---|"]
    for r in cal["rows"]:
        lines.append(f"| {r['threshold']:.2f} | {_f(r['kept'], '.1%')} | {_f(r['precision'], '.1%')} | "
                     f"{_f(r['recall'], '.1%')} | {r['f1']:.3f} |")
    return "\n".join(lines)


def _median(x: list[float]) -> float | None:
    return float(statistics.median(x)) if x else None


def score(video: Video, objects, run: dict) -> dict:
    """The report of one mode's ``run`` (:func:`run_tracked` / :func:`run_detect_every_frame`) against
    ``video``'s ground truth (module docstring)."""
    from kpd6d.evaluation import add_error, add_s_accuracy, adds_error, rotation_error, translation_error

    models = {int(o.obj_id): o for o in objects}
    points = {o: _model_points(m) for o, m in models.items()}
    sec = np.asarray(run["seconds"], dtype=np.float64)
    n = len(video.frames)
    adds, diam, rot, tra = [], [], [], []
    in_view = ok_in_view = edge = out_view = lost = lost_in_view = ok_out = 0
    reacquire: list[int | None] = []
    been_out: set[int] = set()  # objects entirely out of the image since they were last in view
    waiting: dict[int, int] = {}  # obj_id -> frame it came back into view, until its first ok pose
    for i in range(n):
        for g in video.gt[i]:
            o = int(g["obj_id"])
            ok, R, t = run["poses"][i].get(o, (False, None, None))
            lost += not ok
            if g["in_view"] >= IN_VIEW:
                in_view += 1
                lost_in_view += not ok
                if o in been_out:
                    been_out.discard(o)
                    waiting[o] = i
                if ok:
                    ok_in_view += 1
                    err = (adds_error if models[o].is_symmetric else add_error)(R, t, g["R"], g["t"], points[o])
                    adds.append(err)
                    diam.append(models[o].diameter)
                    rot.append(rotation_error(R, g["R"]))
                    tra.append(translation_error(t, g["t"]))
                    if o in waiting:
                        reacquire.append(i - waiting.pop(o))
            elif g["in_view"] <= 0.0:
                out_view += 1
                ok_out += ok
                been_out.add(o)
                if o in waiting:  # out again before it was found
                    reacquire.append(None)
                    waiting.pop(o)
            else:
                edge += 1
    reacquire += [None] * len(waiting)
    total = float(sec.sum())
    passed = add_s_accuracy(adds, diam, 0.1) if adds else 0.0
    return {
        "frames": n, "seconds": total, "fps": n / total if total > 0 else None,
        "median_ms": 1000 * float(np.median(sec)) if n else None,
        "p95_ms": 1000 * float(np.percentile(sec, 95)) if n else None,
        "detector_calls": int(run["stats"]["detector_calls"]), "detector_fraction": run["stats"]["detector_calls"] / n,
        "kpd_calls": int(run["stats"]["kpd_calls"]),
        "object_frames": n * len(models), "in_view_object_frames": in_view, "edge_object_frames": edge,
        "ok_fraction": ok_in_view / in_view if in_view else None,
        "add_s_pass_of_ok": passed if adds else None,
        "add_s_pass_of_in_view": passed * len(adds) / in_view if in_view else None,
        "median_rot_deg": _median(rot), "median_trans_mm": _median(tra),
        "out_of_view_object_frames": out_view, "lost_object_frames": lost, "lost_in_view_object_frames": lost_in_view,
        "ok_out_of_view_object_frames": ok_out, "reacquire_frames": reacquire,
        "latency_ms": (1000 * sec).round(3).tolist(), "detected": list(run["detected"]),
    }


def benchmark(pipeline, video: Video, objects, *, detect_every: int = 10, lost_threshold: float = 0.3,
              smoothing: float = 0.0, warmup: int = 3, modes=MODES, search_every: int = 1) -> dict:
    """Both modes over ``video`` (``objects``: its :class:`ObjectModel`\\ s, for the GT metrics):
    ``{"video": {...}, "settings": {...}, "modes": [report per mode, with "mode"]}``."""
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        raise ValueError(f"unknown mode(s) {unknown}; known: {', '.join(MODES)}")
    known = {int(o) for o in pipeline.kpd.keypoints_3d}
    missing = sorted(set(video.obj_ids) - known)
    if missing:
        raise ValueError(f"the KPD has no keypoints for object(s) {missing} (it covers {sorted(known)})")
    H, W = video.frames[0].shape[:2]
    rows, calibration = [], None
    for mode in modes:
        if mode == "tracked":
            run = run_tracked(pipeline, video, detect_every=detect_every, lost_threshold=lost_threshold,
                              smoothing=smoothing, warmup=warmup, search_every=search_every)
        else:
            run = run_detect_every_frame(pipeline, video, lost_threshold=lost_threshold, warmup=warmup)
            calibration = calibrate(video, objects, run["raw"])
        rows.append({"mode": mode, **score(video, objects, run)})
    return {"video": {"frames": len(video.frames), "width": int(W), "height": int(H), "obj_ids": video.obj_ids,
                      "K": np.asarray(video.K).tolist(), "leave": list(video.leave) if video.leave else None},
            "settings": {"detect_every": int(detect_every), "search_every": int(search_every),
                         "lost_threshold": float(lost_threshold),
                         "smoothing": float(smoothing), "warmup": int(warmup), "oracle": _is_oracle(pipeline)},
            "modes": rows, "calibration": calibration}


# -- report ----------------------------------------------------------------------------------------
def _f(x, fmt: str) -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)


def format_table(report: dict) -> str:
    """The report's modes as a markdown table."""
    leave = report["video"].get("leave")
    head = ("| mode | fps | median ms | p95 ms | detector on | ok poses | ADD(-S)<0.1d of ok | ADD(-S)<0.1d of in view "
            "| rot med deg | trans med mm |" + (" out of view | lost | lost in view | ok out of view | re-acquired after |"
                                               if leave else ""))
    lines = [head, "|" + "---|" * (10 + 5 * bool(leave))]
    for r in report["modes"]:
        line = (f"| {r['mode']} | {_f(r['fps'], '.2f')} | {_f(r['median_ms'], '.1f')} | {_f(r['p95_ms'], '.1f')} | "
                f"{r['detector_fraction']:.0%} | {_f(r['ok_fraction'], '.1%')} | {_f(r['add_s_pass_of_ok'], '.1%')} | "
                f"{_f(r['add_s_pass_of_in_view'], '.1%')} | {_f(r['median_rot_deg'], '.2f')} | "
                f"{_f(r['median_trans_mm'], '.1f')} |")
        if leave:
            re = ", ".join("never" if x is None else str(x) for x in r["reacquire_frames"]) or "-"
            line += (f" {r['out_of_view_object_frames']} | {r['lost_object_frames']} | {r['lost_in_view_object_frames']} "
                     f"| {r['ok_out_of_view_object_frames']} | {re} |")
        lines.append(line)
    return "\n".join(lines)


# -- the pipeline and the objects from the command line --------------------------------------------
def build_pipeline(backend: str = "torch", *, kpd_ckpt=None, detector_ckpt=None, export_dir=None, pnp: Any = "epnp",
                   top_l: int | None = 10, threads: int | None = None, device=None):
    """The pose pipeline the CLI benchmarks: ``backend=torch`` on ``kpd_ckpt`` + ``detector_ckpt`` (a
    checkpoint or ``"oracle"``), or on the checkpoints ``export_dir`` was exported from when no
    ``kpd_ckpt`` is given; ``onnxruntime`` / ``openvino`` on ``export_dir`` (``detector_ckpt="oracle"``:
    GT boxes instead of the exported detector). ``threads``: torch's CPU threads, or the runtime's."""
    from kpd6d.pipeline import PosePipeline

    det = "oracle" if str(detector_ckpt) == "oracle" else "export"
    if backend == "torch":
        import torch

        if threads:
            torch.set_num_threads(int(threads))
        if kpd_ckpt is None:
            return PosePipeline.from_export(export_dir, "torch", pnp=pnp, top_l=top_l, detector=det, device=device)
        return PosePipeline.from_checkpoints(detector_ckpt, kpd_ckpt, pnp=pnp, top_l=top_l, device=device)
    return PosePipeline.from_export(export_dir, backend, pnp=pnp, top_l=top_l, detector=det, threads=threads)


def _available_ids(models_dir) -> list[int]:
    from kpd6d.objects import PROCEDURAL_NAMES, load_models_info

    if models_dir is None:
        return sorted(PROCEDURAL_NAMES)
    return sorted(load_models_info(Path(models_dir) / "models_info.json"))


def _load_objects(models_dir, obj_ids: list[int], seed: int = 0):
    from kpd6d.objects import load_bop_models, procedural_objects

    if models_dir is None:
        return procedural_objects(seed=seed, obj_ids=obj_ids)
    return load_bop_models(models_dir, obj_ids=obj_ids)


def _parser() -> argparse.ArgumentParser:
    from kpd6d.deploy import BACKENDS

    p = argparse.ArgumentParser(prog="kpd6d-benchmark track", description=__doc__.strip().splitlines()[0])
    p.add_argument("--kpd-ckpt", default=None, help="KPD checkpoint (backend torch)")
    p.add_argument("--detector-ckpt", default=None, help="detector checkpoint, or 'oracle' (GT boxes of the visible pixels)")
    p.add_argument("--export-dir", default=None, help="a kpd6d-export folder (backends onnxruntime / openvino; "
                                                      "torch: its source checkpoints when --kpd-ckpt is not given)")
    p.add_argument("--backend", default="torch", choices=BACKENDS)
    p.add_argument("--models-dir", default=None, help="BOP models folder with models_info.json (default: the "
                                                      "procedural objects)")
    p.add_argument("--obj-ids", type=int, nargs="+", default=None,
                   help="objects in the video (default: every object the KPD covers that the models have)")
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--detect-every", type=int, default=10, help="tracked mode: the detector every N frames as well "
                                                                "(0: only when needed)")
    p.add_argument("--search-every", type=int, default=1, help="tracked mode: while a track is lost, the detector "
                                                                "at most every N frames (1: every frame)")
    p.add_argument("--lost-threshold", type=float, default=0.3, help="a pose below this confidence is lost / not ok")
    p.add_argument("--smoothing", type=float, default=0.0, help="the tracker's SE(3) smoothing alpha in [0, 1)")
    p.add_argument("--threads", type=int, default=None, help="torch / runtime CPU threads (default: their choice)")
    p.add_argument("--device", default=None, help="torch device (default: cuda when available, else cpu)")
    p.add_argument("--pnp", default="epnp", help="PNP_SOLVERS name (default: epnp, as kpd6d-predict)")
    p.add_argument("--top-l", type=int, default=10)
    p.add_argument("--seed", type=int, default=0, help="trajectories, background and noise")
    p.add_argument("--leave", type=int, default=0, help="frames every object spends out of view in the middle of "
                                                        f"the video (0: never; it also takes {2 * RAMP_FRAMES} frames "
                                                        "to leave and come back)")
    p.add_argument("--warmup", type=int, default=3, help="untimed frames before each mode")
    p.add_argument("--json", default=None, help="also write the report as JSON here")
    return p


def main(argv: list[str] | None = None) -> int:
    p = _parser()
    a = p.parse_args(argv)
    if a.frames < 1:
        p.error(f"--frames must be >= 1, got {a.frames}")
    for name in ("detect_every", "warmup"):
        if getattr(a, name) < 0:
            p.error(f"--{name.replace('_', '-')} must be >= 0, got {getattr(a, name)}")
    if a.search_every < 1:
        p.error(f"--search-every must be >= 1, got {a.search_every}")
    try:
        leave_range(a.frames, a.leave)
    except ValueError as exc:
        p.error(f"--leave: {exc}")
    if not 0.0 <= a.lost_threshold <= 1.0:
        p.error(f"--lost-threshold must be in [0, 1], got {a.lost_threshold}")
    if not 0.0 <= a.smoothing < 1.0:
        p.error(f"--smoothing must be in [0, 1) (0: off), got {a.smoothing}")
    if a.threads is not None and a.threads < 1:
        p.error(f"--threads must be >= 1, got {a.threads}")
    # the inputs exist, before anything is loaded
    if a.backend == "torch" and a.kpd_ckpt is None and a.export_dir is None:
        p.error("backend torch needs --kpd-ckpt (and --detector-ckpt), or --export-dir")
    if a.backend != "torch" and a.export_dir is None:
        p.error(f"backend {a.backend} needs --export-dir (a kpd6d-export folder)")
    if a.backend == "torch" and a.kpd_ckpt is not None:
        if a.detector_ckpt is None:
            p.error("--kpd-ckpt needs --detector-ckpt (a detector checkpoint, or oracle)")
        for flag, path in (("--kpd-ckpt", a.kpd_ckpt), ("--detector-ckpt", a.detector_ckpt)):
            if not (flag == "--detector-ckpt" and path == "oracle") and not Path(path).is_file():
                p.error(f"{flag} {path}: no such file")
    else:
        if not Path(a.export_dir).is_dir():
            p.error(f"--export-dir {a.export_dir}: no such folder")
        from kpd6d.deploy import SIDECAR

        if not (Path(a.export_dir) / SIDECAR).is_file():
            p.error(f"--export-dir {a.export_dir}: no {SIDECAR} in it (make one with kpd6d-export)")
    if a.models_dir is not None:
        if not Path(a.models_dir).is_dir():
            p.error(f"--models-dir {a.models_dir}: no such folder")
        if not (Path(a.models_dir) / "models_info.json").is_file():
            p.error(f"--models-dir {a.models_dir}: no models_info.json in it (a BOP models folder holds "
                    "obj_XXXXXX.ply and models_info.json)")
    from kpd6d.objects import ModelError

    source = a.models_dir or "the procedural objects"
    try:
        available = _available_ids(a.models_dir)
    except ModelError as exc:
        p.error(str(exc))
    if a.obj_ids is not None:
        unknown = sorted(set(a.obj_ids) - set(available))
        if unknown:
            p.error(f"--obj-ids: object id(s) {unknown} not in {source} (known: {available})")
        if len(set(a.obj_ids)) != len(a.obj_ids):
            p.error(f"--obj-ids: repeated ids in {a.obj_ids}")
    try:
        pipe = build_pipeline(a.backend, kpd_ckpt=a.kpd_ckpt, detector_ckpt=a.detector_ckpt, export_dir=a.export_dir,
                              pnp=a.pnp, top_l=a.top_l, threads=a.threads, device=a.device)
    except Exception as exc:  # the CLI's boundary: a clear message, no traceback
        what = a.kpd_ckpt if a.backend == "torch" and a.kpd_ckpt else a.export_dir
        p.error(f"cannot load the pipeline ({a.backend}, {what}): {type(exc).__name__}: {exc}")
    covered = sorted(int(o) for o in pipe.kpd.keypoints_3d)
    if a.obj_ids is not None:
        unknown = sorted(set(a.obj_ids) - set(covered))
        if unknown:
            p.error(f"--obj-ids: the KPD has no keypoints for object id(s) {unknown} (it covers {covered})")
        ids = list(a.obj_ids)
    else:
        ids = [o for o in covered if o in available]
        if not ids:
            p.error(f"the KPD covers objects {covered}, none of which is in {source} (known: {available}); "
                    "give --models-dir")
    try:
        objects = _load_objects(a.models_dir, ids)
        video = make_video(objects, LINEMOD_K, LINEMOD_IMAGE_SIZE, a.frames, seed=a.seed, leave=a.leave)
        report = benchmark(pipe, video, objects, detect_every=a.detect_every, lost_threshold=a.lost_threshold,
                           smoothing=a.smoothing, warmup=a.warmup, search_every=a.search_every)
    except (ModelError, ValueError) as exc:
        p.error(str(exc))
    report["settings"].update(backend=a.backend, pnp=a.pnp, top_l=a.top_l, threads=a.threads, seed=a.seed,
                              device=str(getattr(pipe, "device", "cpu")), objects_source=str(source),
                              kpd_ckpt=a.kpd_ckpt, detector_ckpt=a.detector_ckpt, export_dir=a.export_dir)
    threads = a.threads
    if a.backend == "torch":
        import torch

        threads = torch.get_num_threads()
    print(f"tracked-video benchmark: {a.frames} frames {LINEMOD_IMAGE_SIZE[0]}x{LINEMOD_IMAGE_SIZE[1]}, objects {ids} "
          f"({source}), seed {a.seed}" + (f", {a.leave} frames out of view" if a.leave else ""))
    print(f"backend {a.backend} on {report['settings']['device']} ({platform.processor() or 'cpu'}, "
          f"{threads or 'default'} threads); {a.pnp}, top-{a.top_l}; tracked: detect_every={a.detect_every}, "
          f"search_every={a.search_every}, "
          f"lost_threshold={a.lost_threshold:g}, smoothing={a.smoothing:g}; {a.warmup} warm-up frames untimed")
    print(format_table(report))
    if report.get("calibration"):
        print(format_calibration(report["calibration"]))
    if a.json:
        from kpd6d.io import atomic_write_json

        atomic_write_json(a.json, report)
        print(f"report: {a.json}")
    return 0
