"""Tracking (kpd6d.tracking) on generated videos, the pose confidence formula and SE(3) smoothing.

The videos: a procedural object (lblock) rendered with kpd6d.render.Renderer along known smooth
trajectories over a procedural background; one also leaves the image, comes back and is covered by
an occluder. The networks are stand-ins that read the ground truth of the frame they are given (found
by the frame's pixels): ``GTDetector`` boxes the object's visible pixels, ``GTKPD`` returns the
projected keypoints quantised to a heatmap grid of its crop, confident only where the keypoint lies
in the crop on a visible pixel of the object. Everything else is the production code:
``PosePipeline.detect`` / ``predict_boxes`` (crops, top-l, PnP, confidence) called by the tracker.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import sys

import cv2
import numpy as np
import pytest
import torch

from kpd6d.detection.detections import Detections
from kpd6d.geometry import (
    LINEMOD_K,
    affine_apply,
    bbox_from_points,
    box_to_crop_affine,
    invert_affine,
    pose_from_view,
    project_points,
    rotation_about_axis,
    rotation_error_deg,
)
from kpd6d.pipeline import PosePipeline
from kpd6d.pnp.confidence import pose_confidence, reprojection_residuals
from kpd6d.tracking import (
    PoseTracker,
    matrix_from_quat,
    projected_box,
    quat_from_matrix,
    slerp_rotation,
    smooth_pose,
    track_frames,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

W, H = 320, 240
K = LINEMOD_K * np.array([[0.5], [0.5], [1.0]])
CROP, CROP_SCALE = 64, 1.25


def _key(rgb: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(rgb).tobytes()).hexdigest()


def _tensor_key(x: torch.Tensor) -> str:
    """The key of one (3, H, W) float [0, 1] image: the uint8 frame it was made from."""
    return _key((x * 255).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy())


class GroundTruth:
    """frame key -> (R, t, visible (H, W) bool) of the object in that frame."""

    def __init__(self):
        self.frames: dict[str, tuple] = {}

    def add(self, rgb, R, t, visible):
        self.frames[_key(rgb)] = (R, t, visible)

    def __getitem__(self, x):
        return self.frames[_tensor_key(x)]


class GTDetector:
    """A detector stand-in: the box of the object's visible pixels (none under 30 pixels)."""

    def __init__(self, gt: GroundTruth, obj_id: int = 1):
        self.gt, self.obj_id, self.calls = gt, obj_id, 0

    def predict(self, images, targets=None):
        self.calls += 1
        out = []
        for x in images:
            _, _, vis = self.gt[x]
            ys, xs = np.nonzero(vis)
            if len(xs) < 30:
                out.append(Detections.empty())
                continue
            box = bbox_from_points(np.c_[xs, ys].astype(np.float64))
            out.append(Detections(torch.tensor(box[None], dtype=torch.float32), torch.tensor([self.obj_id]),
                                  torch.tensor([0.9])))
        return out


class GTKPD:
    """A KPD stand-in: the projected keypoints as a heatmap KPD decodes them in the crop of the given
    box (quantised to 1/4 px of a 64 px crop), confidence 0.9..0.7 for a keypoint in the crop on a
    visible pixel of the object, else a garbage peak with confidence 0.02."""

    def __init__(self, gt: GroundTruth, keypoints_3d: np.ndarray, surface: np.ndarray, obj_id: int = 1):
        self.gt, self.obj_id = gt, obj_id
        self.keypoints_3d = {obj_id: keypoints_3d}
        self._surface = surface
        self.calls = 0
        self.rng = np.random.default_rng(0)

    def surface_points(self, obj_id):
        return self._surface

    def predict_keypoints(self, images, boxes, image_index, obj_ids):
        self.calls += 1
        kps, confs = [], []
        k = len(self.keypoints_3d[self.obj_id])
        for box, b in zip(boxes.cpu().numpy().astype(np.float64), image_index.tolist()):
            R, t, vis = self.gt[images[b]]
            uv = project_points(self.keypoints_3d[self.obj_id], K, R, t)
            A = box_to_crop_affine(box, CROP, scale=CROP_SCALE)
            cuv = affine_apply(A, uv)
            in_crop = ((cuv >= 0) & (cuv <= CROP - 1)).all(1)
            ij = np.rint(uv).astype(int)
            inside = (ij[:, 0] >= 0) & (ij[:, 0] < W) & (ij[:, 1] >= 0) & (ij[:, 1] < H)
            seen = np.zeros(k, bool)
            dil = cv2.dilate(vis.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
            seen[inside] = dil[ij[inside, 1], ij[inside, 0]]
            good = in_crop & seen
            q = np.round(cuv * 4) / 4
            garbage = self.rng.uniform(0, CROP - 1, (k, 2))
            kps.append(affine_apply(invert_affine(A), np.where(good[:, None], q, garbage)))
            confs.append(np.where(good, np.linspace(0.9, 0.7, k), 0.02))
        return torch.tensor(np.stack(kps), dtype=torch.float32), torch.tensor(np.stack(confs), dtype=torch.float32)


def _background(seed=0):
    """A procedural background: a colour gradient with blurred blobs."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W] / max(H, W)
    bg = np.stack([90 + 60 * xx, 110 + 40 * yy, 70 + 50 * (1 - xx)], -1)
    noise = cv2.GaussianBlur(rng.uniform(-40, 40, (H, W, 3)), (0, 0), 6)
    return np.clip(bg + noise, 0, 255).astype(np.uint8)


def _trajectory_follow(n=40):
    """A smooth path: across the image left to right, a little up and down and away, turning."""
    R0, t0 = pose_from_view(0.4, 0.5, 650.0, 0.2)
    poses = []
    for i in range(n):
        s = i / (n - 1)
        R = R0 @ rotation_about_axis([0, 0, 1], 0.9 * s) @ rotation_about_axis([1, 0, 0], 0.3 * np.sin(np.pi * s))
        t = t0 + np.array([-110 + 220 * s, 25 * np.sin(2 * np.pi * s), 60 * s])
        poses.append((R, t))
    return poses


# frames of the lost / re-acquire video: visible 0-9, leaving 10-17, out of view 18-24, back 25-29,
# visible 30-32, fully covered by an occluder 33-38, visible 39-44
OUT_OF_VIEW, OCCLUDED, BACK = range(18, 25), range(33, 39), range(39, 45)


def _trajectory_lost(n=45):
    R0, t0 = pose_from_view(0.4, 0.5, 650.0, 0.2)
    poses = []
    for i in range(n):
        if i < 10:
            x = -50 + 10 * i
        elif i < 18:
            x = 50 + 50 * (i - 9)
        elif i < 25:
            x = 600
        elif i < 30:
            x = 600 - 110 * (i - 24)
        else:
            x = 50 - 2 * (i - 30)
        R = R0 @ rotation_about_axis([0, 0, 1], 0.02 * i)
        poses.append((R, t0 + np.array([x, 0.0, 0.0])))
    return poses


def _render_video(renderer, obj, poses, occluded=()):
    gt, frames = GroundTruth(), []
    bg = _background()
    for i, (R, t) in enumerate(poses):
        res = renderer.render([(obj, R, t)], masks=False)
        mask = res.depth > 0
        img = np.where(mask[..., None], res.rgb, bg)
        if i in occluded:  # a textured board in front of the whole object
            ys, xs = np.nonzero(mask)
            x0, y0, x1, y1 = xs.min() - 12, ys.min() - 12, xs.max() + 12, ys.max() + 12
            board = (_background(seed=i)[::-1] * 0.6).astype(np.uint8)
            img[max(y0, 0):y1, max(x0, 0):x1] = board[max(y0, 0):y1, max(x0, 0):x1]
            mask = mask.copy()
            mask[max(y0, 0):y1, max(x0, 0):x1] = False
        img = np.ascontiguousarray(img)
        img[0, 0] = i  # distinct pixels for every frame (frames are found by their pixels)
        gt.add(img, R, t, mask)
        frames.append(img)
    return frames, gt


@pytest.fixture(scope="module")
def scene():
    from kpd6d.objects import procedural_objects
    from kpd6d.render import Renderer

    obj = procedural_objects(obj_ids=[1])[0]
    renderer = Renderer(W, H, K, antialias=False)
    try:
        follow = _trajectory_follow()
        lost = _trajectory_lost()
        f_frames, gt = _render_video(renderer, obj, follow)
        l_frames, gt_l = _render_video(renderer, obj, lost, occluded=OCCLUDED)
    finally:
        renderer.close()
    gt.frames.update(gt_l.frames)
    kp3d = obj.sample_points(24, seed=3)
    surface = obj.vertices[:: max(1, len(obj.vertices) // 600)]
    return {"obj": obj, "gt": gt, "kp3d": kp3d, "surface": surface, "follow": (f_frames, follow),
            "lost": (l_frames, lost)}


def _pipeline(scene, **kw):
    det = GTDetector(scene["gt"])
    kpd = GTKPD(scene["gt"], scene["kp3d"], scene["surface"])
    return PosePipeline(det, kpd, pnp="epnp_ransac", top_l=16, device="cpu", **kw), det, kpd


def _errors(pose, gt_pose):
    R, t = gt_pose
    return rotation_error_deg(pose["R"], R), float(np.linalg.norm(pose["t"] - t))


# -- tracking ----------------------------------------------------------------------------------
@pytest.mark.parametrize("detect_every", [0, 10])
def test_tracker_follows_the_trajectory_with_few_detector_calls(scene, detect_every):
    frames, poses = scene["follow"]
    pipe, det, kpd = _pipeline(scene)
    out = list(track_frames(pipe, frames, K, detect_every=detect_every))
    assert len(out) == len(frames)
    for i, (res, gt_pose) in enumerate(zip(out, poses)):
        assert [p["obj_id"] for p in res["poses"]] == [1]
        p = res["poses"][0]
        assert p["ok"], (i, p["reason"])
        rot, tra = _errors(p, gt_pose)
        assert rot < 1.5 and tra < 5.0, (i, rot, tra)
        assert 0.3 < p["confidence"] <= 1.0
        assert p["source"] == ("detector" if res["detected"] else "track")
    detected = [r["frame"] for r in out if r["detected"]]
    assert detected == ([0] if detect_every == 0 else [0, 10, 20, 30])
    assert det.calls == out[-1]["detector_calls"] == len(detected) <= 0.1 * len(frames)
    assert kpd.calls == len(frames)  # one KPD call per frame


def test_tracker_reports_lost_and_reacquires_through_the_detector(scene):
    frames, poses = scene["lost"]
    pipe, det, _ = _pipeline(scene)
    tracker = PoseTracker(pipe, detect_every=0, lost_threshold=0.3, smoothing=0.5)
    out = [tracker.update(f, K) for f in frames]
    ok = [r["poses"][0]["ok"] for r in out]
    assert all(ok[:10]) and all(ok[30:33])
    # out of view, and fully covered: reported lost, with NaN poses and a reason
    for gone in (OUT_OF_VIEW, OCCLUDED):
        for i in gone:
            p = out[i]["poses"][0]
            assert not p["ok"] and np.isnan(p["t"]).all() and p["reason"], i
            assert out[i]["detected"] or i == gone[0]  # lost: the detector searches every following frame
    # re-acquired when it is back: through a detector call, the smoothing restarting at the measurement
    for gone in (OUT_OF_VIEW, OCCLUDED):
        back = next(i for i in range(gone[-1] + 1, len(frames)) if ok[i])
        p = out[back]["poses"][0]
        assert out[back]["detected"] and p["source"] == "detector"
        assert out[back]["detector_calls"] > out[back - 1]["detector_calls"]
        np.testing.assert_array_equal(p["R"], p["raw_R"])
        np.testing.assert_array_equal(p["t"], p["raw_t"])
    assert all(ok[i] for i in BACK)
    assert [out[i]["poses"][0]["source"] for i in BACK] == ["detector"] + ["track"] * (len(BACK) - 1)
    for i in (*range(10), *range(30, 33), *BACK):
        p = out[i]["poses"][0]
        rot, tra = _errors({"R": p["raw_R"], "t": p["raw_t"]}, poses[i])
        assert rot < 1.5 and tra < 5.0, (i, rot, tra)
        # smoothing 0.5 lags behind: by alpha / (1 - alpha) = 1 frame's motion (10 mm) in steady motion
        assert _errors(p, poses[i])[1] < 15.0
    assert tracker.stats["detector_calls"] == det.calls == sum(r["detected"] for r in out)
    assert tracker.stats["frames"] == len(frames)


def test_search_every_limits_the_detector_while_a_track_is_lost(scene):
    """search_every=3: while the object is out of view or covered, the detector runs on at most every
    third frame (1, the default, searches on every one); it is still re-acquired after it returns,
    up to 2 frames later, through the detector."""
    frames, _ = scene["lost"]
    runs = {}
    for n in (1, 3):
        pipe, det, _ = _pipeline(scene)
        tracker = PoseTracker(pipe, detect_every=0, search_every=n)
        out = [tracker.update(f, K) for f in frames]
        runs[n] = (out, det.calls)
    def back(out, gone):
        return next(i for i in range(gone[-1] + 1, len(frames)) if out[i]["poses"][0]["ok"])

    for n, (out, calls) in runs.items():
        detected = [r["detected"] for r in out]
        assert calls == sum(detected)
        for gone in (OUT_OF_VIEW, OCCLUDED):
            searched = [i for i in range(gone[0], gone[-1] + 1) if detected[i]]
            # consecutive detector calls while lost are search_every frames apart
            assert all(b - a >= n for a, b in itertools.pairwise(searched)), (n, searched)
            # re-acquired through the detector, at most n - 1 frames after searching every frame does
            i = back(out, gone)
            assert out[i]["poses"][0]["source"] == "detector" and 0 <= i - back(runs[1][0], gone) <= n - 1
    assert runs[3][1] < runs[1][1]
    with pytest.raises(ValueError, match="search_every"):
        PoseTracker(_pipeline(scene)[0], search_every=0)


def test_smoothing_follows_and_smooths(scene):
    frames, poses = scene["follow"]
    raw = [r["poses"][0] for r in track_frames(_pipeline(scene)[0], frames, K)]
    smooth = [r["poses"][0] for r in track_frames(_pipeline(scene)[0], frames, K, smoothing=0.3)]
    for a, b in zip(raw, smooth):
        np.testing.assert_allclose(a["raw_t"], b["raw_t"], atol=1e-6)  # the crops follow the raw poses
        assert b["ok"] and np.allclose(b["R"].T @ b["R"], np.eye(3), atol=1e-9) and np.linalg.det(b["R"]) > 0
    # the smoothed pose is the filter of the raw ones (recomputed here), and stays on the trajectory
    R_s, t_s = raw[0]["R"], raw[0]["t"]
    for i, (a, b) in enumerate(zip(raw, smooth)):
        if i:
            R_s, t_s = slerp_rotation(R_s, a["R"], 0.7), 0.3 * t_s + 0.7 * a["t"]
        np.testing.assert_allclose(b["R"], R_s, atol=1e-9)
        np.testing.assert_allclose(b["t"], t_s, atol=1e-6)
        rot, tra = _errors(b, poses[i])
        assert rot < 2.0 and tra < 6.0


def test_tracker_options_are_checked(scene):
    pipe = _pipeline(scene)[0]
    for kw, match in (({"detect_every": -1}, "detect_every"), ({"lost_threshold": 1.5}, "lost_threshold"),
                      ({"smoothing": 1.0}, "smoothing"), ({"margin": -0.1}, "margin"),
                      ({"min_in_view": 0.0}, "min_in_view"), ({"obj_ids": [9]}, "no keypoints")):
        with pytest.raises(ValueError, match=match):
            PoseTracker(pipe, **kw)
    with pytest.raises(TypeError, match=r"\.detect\(\)"):
        PoseTracker(object())


def test_projected_box_margin_and_in_view():
    pts = np.array([[x, y, z] for x in (-10, 10) for y in (-10, 10) for z in (-10, 10)], float)
    R = np.eye(3)
    box, inview = projected_box(pts, K, R, np.array([0, 0, 500.0]), (H, W), margin=0.5)
    uv = project_points(pts, K, R, np.array([0, 0, 500.0]))
    tight = bbox_from_points(uv)
    assert inview == pytest.approx(1.0)
    np.testing.assert_allclose(box[2:], tight[2:] * 1.5)
    np.testing.assert_allclose(box[:2] + box[2:] / 2, tight[:2] + tight[2:] / 2)
    # half of it off the right edge: half in view, the box clipped
    t = np.array([(W - K[0, 2]) * 500 / K[0, 0], 0, 500.0])  # the centre projects onto the right edge
    box, inview = projected_box(pts, K, R, t, (H, W))
    assert 0.4 < inview < 0.6 and box[0] + box[2] == pytest.approx(W)
    assert projected_box(pts, K, R, np.array([0, 0, -500.0]), (H, W)) == (None, 0.0)
    assert projected_box(pts, K, R, np.array([5000.0, 0, 500.0]), (H, W))[0] is None


# -- SE(3) smoothing against an independent computation -------------------------------------------
def test_slerp_matches_scipy():
    from scipy.spatial.transform import Rotation, Slerp

    rng = np.random.default_rng(0)
    for _ in range(20):
        r = Rotation.random(2, random_state=int(rng.integers(1 << 30)))
        s = float(rng.uniform(0, 1))
        want = Slerp([0, 1], r)([0.5, s]).as_matrix()
        np.testing.assert_allclose(slerp_rotation(r[0].as_matrix(), r[1].as_matrix(), 0.5), want[0], atol=1e-9)
        np.testing.assert_allclose(slerp_rotation(r[0].as_matrix(), r[1].as_matrix(), s), want[1], atol=1e-9)
        q = Rotation.from_matrix(r[0].as_matrix()).as_quat()  # x, y, z, w
        q = np.r_[q[3], q[:3]] * np.sign(q[3])
        np.testing.assert_allclose(quat_from_matrix(r[0].as_matrix()), q, atol=1e-12)
        np.testing.assert_allclose(matrix_from_quat(q), r[0].as_matrix(), atol=1e-12)
    # near-pi turns (the quaternion branch where the trace is small), and the short way round
    for axis in ([1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]):
        Ra = rotation_about_axis(axis, np.pi - 1e-3)
        np.testing.assert_allclose(matrix_from_quat(quat_from_matrix(Ra)), Ra, atol=1e-12)
    R0, R1 = rotation_about_axis([0, 0, 1], 0.1), rotation_about_axis([0, 0, 1], -0.1 + 2 * np.pi)
    np.testing.assert_allclose(slerp_rotation(R0, R1, 0.5), np.eye(3), atol=1e-12)
    np.testing.assert_allclose(slerp_rotation(R0, R0, 0.3), R0, atol=1e-12)


def test_smoothing_a_constant_pose_leaves_it_unchanged_and_is_not_per_entry():
    rng = np.random.default_rng(1)
    from scipy.spatial.transform import Rotation

    R = Rotation.random(random_state=3).as_matrix()
    t = rng.normal(size=3) * 100
    R_s, t_s = R, t
    for _ in range(10):
        R_s, t_s = smooth_pose(R_s, t_s, R, t, 0.8)
    np.testing.assert_allclose(R_s, R, atol=1e-12)
    np.testing.assert_allclose(t_s, t, atol=1e-9)
    # a half-way step between two rotations 120 degrees apart: the geodesic midpoint (60 degrees from
    # each), a rotation -- averaging the entries would give a matrix that is not one
    Ra, Rb = np.eye(3), rotation_about_axis([0, 0, 1], 2 * np.pi / 3)
    Rm, tm = smooth_pose(Ra, np.zeros(3), Rb, np.array([10.0, 0, 0]), 0.5)
    assert rotation_error_deg(Rm, Ra) == pytest.approx(60.0) and rotation_error_deg(Rm, Rb) == pytest.approx(60.0)
    np.testing.assert_allclose(tm, [5.0, 0, 0])
    assert abs(np.linalg.det((Ra + Rb) / 2) - 1) > 0.1
    np.testing.assert_array_equal(smooth_pose(Ra, np.zeros(3), Rb, np.ones(3), 0.0)[0], Rb)  # alpha 0: off
    with pytest.raises(ValueError, match="alpha"):
        smooth_pose(Ra, np.zeros(3), Rb, np.ones(3), 1.0)


# -- the confidence formula on hand-made inputs ----------------------------------------------------
def test_pose_confidence_formula():
    c = np.array([[1.0, 0.5, 0.8, 2.0, -1.0, 0.9]])  # > 1 and < 0 are clipped
    used = np.array([[True, True, True, True, True, False]])
    inliers = np.array([[True, True, False, True, True, True]])  # the unused 6th does not count
    res = np.array([5.0])
    want = (1.0 + 0.5 + 1.0 + 0.0) / 5 * np.exp(-5.0 / 10.0)
    np.testing.assert_allclose(pose_confidence(c, used, inliers, res), [want])
    np.testing.assert_allclose(pose_confidence(c, used, inliers, res, residual_scale_px=2.5),
                               [2.5 / 5 * np.exp(-2.0)])
    assert pose_confidence(c, used, inliers, res, ok=[False])[0] == 0.0
    assert pose_confidence(c, used, inliers, [np.nan])[0] == 0.0
    assert pose_confidence(c, np.zeros_like(used), inliers, res)[0] == 0.0
    perfect = pose_confidence(np.ones((1, 6)), np.ones((1, 6), bool), np.ones((1, 6), bool), [0.0])
    assert perfect[0] == 1.0
    with pytest.raises(ValueError, match="residual_scale_px"):
        pose_confidence(c, used, inliers, res, residual_scale_px=0)


def test_reprojection_residuals_and_pipeline_confidence():
    rng = np.random.default_rng(0)
    X = rng.uniform(-40, 40, (1, 10, 3))
    R, t = pose_from_view(0.3, 0.4, 600.0)
    uv = project_points(X[0], LINEMOD_K, R, t)
    off = np.where(np.arange(10)[:, None] % 2 == 0, [3.0, 4.0], [0.0, 0.0])  # 5 px on half of them
    mask = np.ones((1, 10), bool)
    np.testing.assert_allclose(reprojection_residuals(X, (uv + off)[None], LINEMOD_K, R[None], t[None], mask), [2.5])
    mask[0, 1::2] = False
    np.testing.assert_allclose(reprojection_residuals(X, (uv + off)[None], LINEMOD_K, R[None], t[None], mask), [5.0])
    assert np.isnan(reprojection_residuals(X, uv[None], LINEMOD_K, np.full((1, 3, 3), np.nan), t[None], mask))[0]

    # the pipeline's pose dicts: confidence from the used keypoints and the residual, ok gated by it
    class KPD:
        def __init__(self):
            self.keypoints_3d = {1: X[0]}

        def predict_keypoints(self, images, boxes, image_index, obj_ids):
            conf = np.linspace(0.9, 0.5, 10)
            return torch.tensor(uv[None], dtype=torch.float32), torch.tensor(conf[None], dtype=torch.float32)

    from kpd6d.registry import DETECTORS

    box = bbox_from_points(uv)
    tg = [{"boxes": box[None], "obj_ids": np.array([1])}]
    img = [np.zeros((480, 640, 3), np.uint8)]
    p = PosePipeline(DETECTORS.build("oracle"), KPD(), pnp="epnp", top_l=8, device="cpu").predict_batch(img, LINEMOD_K,
                                                                                                        tg)[0][0]
    assert p["ok"] and p["residual_px"] < 0.01  # float32 keypoints
    assert p["confidence"] == pytest.approx(np.linspace(0.9, 0.5, 10)[:8].mean() * np.exp(-p["residual_px"] / 10))
    gated = PosePipeline(DETECTORS.build("oracle"), KPD(), pnp="epnp", top_l=8, device="cpu", min_confidence=0.9)
    q = gated.predict_batch(img, LINEMOD_K, tg)[0][0]
    assert not q["ok"] and np.isnan(q["R"]).all() and "min_confidence" in q["reason"]
    assert q["confidence"] == pytest.approx(p["confidence"])
    # predict_boxes: the same as predict_batch on the detector's boxes, without the detector
    r = PosePipeline(DETECTORS.build("oracle"), KPD(), pnp="epnp", top_l=8, device="cpu").predict_boxes(img, LINEMOD_K,
                                                                                                         [box], [1])[0][0]
    np.testing.assert_allclose(r["R"], p["R"], atol=1e-9)
    assert r["confidence"] == pytest.approx(p["confidence"]) and r["score"] == 1.0


# -- kpd6d-predict track=true -------------------------------------------------------------------
def test_predict_inputs_tracks_a_video(scene, tmp_path):
    from kpd6d.predict import predict_inputs, track_options

    frames, _ = scene["follow"]
    path = tmp_path / "clip.mp4"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (W, H))
    for f in frames[:8]:
        w.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    w.release()
    # a lossy video's frames are not the rendered ones: the stand-ins look up the decoded frames
    cap, decoded = cv2.VideoCapture(str(path)), []
    while (r := cap.read())[0]:
        decoded.append(cv2.cvtColor(r[1], cv2.COLOR_BGR2RGB))
    gt = scene["gt"]
    for f, d in zip(frames, decoded):
        gt.frames[_key(d)] = gt.frames[_key(f)]
    pipe, det, _ = _pipeline(scene)
    opts = track_options({"enabled": True, "detect_every": 4, "lost_threshold": 0.3, "smoothing": 0.0})
    info = predict_inputs(pipe, path, K, tmp_path / "out", {1: scene["obj"].bbox_corners}, progress=False, track=opts)
    assert info["frames"] == 8 and info["poses"] == 8 and info["detector_calls"] == 2 == det.calls
    data = json.loads((tmp_path / "out" / "poses.json").read_text())
    assert [f["detected"] for f in data["frames"]] == [True, False, False, False, True, False, False, False]
    for f in data["frames"]:
        (p,) = f["poses"]
        assert p["ok"] and 0.3 < p["confidence"] <= 1 and p["source"] in ("detector", "track")
    assert data["tracking"]["detector_calls"] == 2 and data["tracking"]["detect_every"] == 4
    assert (tmp_path / "out" / "overlay.mp4").is_file()
    assert track_options({"enabled": False, "detect_every": 3}) is None and track_options(True) == {}
    with pytest.raises(ValueError, match=r"track\.nonsense"):
        track_options({"enabled": True, "nonsense": 1})


def test_track_override_and_camera_input():
    from kpd6d.predict import expand_track_override, is_camera

    assert expand_track_override(["input=a.mp4", "track=true", "track.detect_every=5", "track=False"]) == [
        "input=a.mp4", "track.enabled=true", "track.detect_every=5", "track.enabled=false"]
    assert is_camera(0) and is_camera("1") and not is_camera(True) and not is_camera("clip.mp4")
    from kpd6d.predict import track_options

    assert track_options({"enabled": True, "search_every": "4", "detect_every": 0}) == {"search_every": 4,
                                                                                      "detect_every": 0}


def test_cli_tracks_a_video_with_real_untrained_checkpoints(tmp_path, monkeypatch, capsys):
    """kpd6d-predict input=VIDEO track=true on the real networks (untrained: the poses are poor; the
    code path and the output fields are what is checked)."""
    import pytorch_lightning as pl

    from kpd6d.cli.predict import main
    from kpd6d.detection import build_detector, save_detector
    from kpd6d.kpd.module import KPDModule

    corners = np.array([[x, y, z] for z in (-20, 20) for y in (-20, 20) for x in (-20, 20)], float)
    torch.manual_seed(0)
    det = build_detector("centernet", obj_ids=[1], backbone="resnet10t", neck_channels=16, head_channels=16,
                         input_size=[128, 96], score_threshold=0.0, max_detections=3)
    save_detector(det, tmp_path / "det.pt")
    kpd = KPDModule(obj_ids=[1], keypoints_3d=[corners], diameters=[69.3], backbone={"name": "resnet18"},
                    head={"name": "deconv", "deconv_channels": 16}, input_size=64, out_stride=4)
    trainer = pl.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, default_root_dir=tmp_path)
    trainer.strategy.connect(kpd)
    trainer.save_checkpoint(tmp_path / "kpd.ckpt")
    path = tmp_path / "clip.mp4"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (160, 120))
    rng = np.random.default_rng(0)
    for _ in range(4):
        w.write(rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
    w.release()
    out = tmp_path / "run"
    monkeypatch.setattr(sys, "argv", ["kpd6d-predict", f"input={path}", f"kpd_ckpt={tmp_path / 'kpd.ckpt'}",
                                      f"detector_ckpt={tmp_path / 'det.pt'}", "device=cpu", "progress=false",
                                      "select.top_l=null", "track=true", "track.detect_every=2",
                                      "track.smoothing=0.5", "overlays=false", f"hydra.run.dir={out}"])
    main()
    data = json.loads((out / "poses.json").read_text())
    assert len(data["frames"]) == 4 and data["tracking"]["detect_every"] == 2
    assert data["frames"][0]["detected"] and data["tracking"]["detector_calls"] >= 2
    for f in data["frames"]:
        for p in f["poses"]:
            assert {"confidence", "ok", "source", "reason"} <= set(p) and 0 <= p["confidence"] <= 1
    assert "detector calls" in capsys.readouterr().out
