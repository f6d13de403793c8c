"""``kpd6d-benchmark track`` (kpd6d.benchmarks.track): the generated video and its ground truth, the two
modes (tracked, detect every frame) with ground-truth stand-in networks, the scoring, and the CLI.

The stand-ins (as in tests/test_tracking.py, for several objects) read the ground truth of the frame
they are given, found by the frame's pixels: ``GTDetector`` boxes each object's visible pixels,
``GTKPD`` returns the projected keypoints quantised to a heatmap grid of its crop, confident only
where a keypoint lies in the crop on a visible pixel of its object. Everything else is the production
code: PosePipeline's detect / predict_boxes / predict_batch, the tracker, the benchmark.
"""

from __future__ import annotations

import hashlib
import itertools
import json

import cv2
import numpy as np
import pytest
import torch

from kpd6d.benchmarks.track import (
    RAMP_FRAMES,
    benchmark,
    format_table,
    main,
    make_video,
    score,
    trajectories,
)
from kpd6d.detection.detections import Detections
from kpd6d.geometry import (
    LINEMOD_K,
    affine_apply,
    bbox_from_points,
    box_to_crop_affine,
    invert_affine,
    project_points,
    rotation_about_axis,
    rotation_error_deg,
)
from kpd6d.pipeline import PosePipeline

pytestmark = pytest.mark.usefixtures("one_torch_thread")

W, H = 320, 240
K = LINEMOD_K * np.array([[0.5], [0.5], [1.0]])
CROP, CROP_SCALE = 64, 1.25
IDS = [1, 3]  # procedural lblock and wedge
FRAMES, LEAVE_FRAMES, LEAVE = 30, 40, 6


def _key(rgb: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(rgb).tobytes()).hexdigest()


def _tensor_key(x: torch.Tensor) -> str:
    return _key((x * 255).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy())


class GTDetector:
    """The box of each object's visible pixels (none under 30 pixels)."""

    def __init__(self, table):
        self.table, self.calls = table, 0

    def predict(self, images, targets=None):
        self.calls += 1
        out = []
        for x in images:
            boxes, ids = [], []
            for oid, (_, _, vis) in self.table[_tensor_key(x)].items():
                ys, xs = np.nonzero(vis)
                if len(xs) >= 30:
                    boxes.append(bbox_from_points(np.c_[xs, ys].astype(np.float64)))
                    ids.append(oid)
            out.append(Detections(torch.tensor(np.reshape(boxes, (-1, 4)), dtype=torch.float32),
                                  torch.tensor(ids, dtype=torch.long), torch.full((len(ids),), 0.9)))
        return out


class GTKPD:
    """Projected keypoints as a heatmap KPD decodes them in the crop of the given box (1/4 px of a 64 px
    crop), confidence 0.9..0.7 in the crop on a visible pixel of the object, else garbage at 0.02."""

    def __init__(self, table, keypoints_3d: dict, surface: dict):
        self.table, self.keypoints_3d, self._surface = table, keypoints_3d, surface
        self.rng = np.random.default_rng(0)

    def surface_points(self, obj_id):
        return self._surface[int(obj_id)]

    def predict_keypoints(self, images, boxes, image_index, obj_ids):
        kps, confs = [], []
        for box, b, oid in zip(boxes.cpu().numpy().astype(np.float64), image_index.tolist(), obj_ids.tolist()):
            R, t, vis = self.table[_tensor_key(images[b])][int(oid)]
            k3 = self.keypoints_3d[int(oid)]
            uv = project_points(k3, K, R, t)
            A = box_to_crop_affine(box, CROP, scale=CROP_SCALE)
            cuv = affine_apply(A, uv)
            in_crop = ((cuv >= 0) & (cuv <= CROP - 1)).all(1)
            ij = np.rint(uv).astype(int)
            inside = (ij[:, 0] >= 0) & (ij[:, 0] < W) & (ij[:, 1] >= 0) & (ij[:, 1] < H)
            seen = np.zeros(len(k3), bool)
            dil = cv2.dilate(vis.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
            seen[inside] = dil[ij[inside, 1], ij[inside, 0]]
            good = in_crop & seen
            garbage = self.rng.uniform(0, CROP - 1, (len(k3), 2))
            kps.append(affine_apply(invert_affine(A), np.where(good[:, None], np.round(cuv * 4) / 4, garbage)))
            confs.append(np.where(good, np.linspace(0.9, 0.7, len(k3)), 0.02))
        return torch.tensor(np.stack(kps), dtype=torch.float32), torch.tensor(np.stack(confs), dtype=torch.float32)


@pytest.fixture(scope="module")
def scene():
    from kpd6d.objects import procedural_objects
    from kpd6d.render import Renderer

    objs = procedural_objects(obj_ids=IDS)
    renderer = Renderer(W, H, K, antialias=False)
    try:
        plain = make_video(objs, K, (W, H), FRAMES, seed=0, masks=True, renderer=renderer)
        leave = make_video(objs, K, (W, H), LEAVE_FRAMES, seed=1, leave=LEAVE, masks=True, renderer=renderer)
    finally:
        renderer.close()
    table = {}
    for v in (plain, leave):
        for f, recs in zip(v.frames, v.gt):
            assert _key(f) not in table  # the noise makes every frame distinct
            table[_key(f)] = {g["obj_id"]: (g["R"], g["t"], g["mask"]) for g in recs}
    kp3d = {o.obj_id: o.sample_points(24, seed=3) for o in objs}
    surface = {o.obj_id: o.vertices[:: max(1, len(o.vertices) // 600)] for o in objs}
    return {"objs": objs, "plain": plain, "leave": leave, "table": table, "kp3d": kp3d, "surface": surface}


def _pipeline(scene):
    det = GTDetector(scene["table"])
    kpd = GTKPD(scene["table"], scene["kp3d"], scene["surface"])
    return PosePipeline(det, kpd, pnp="epnp_ransac", top_l=16, device="cpu"), det


# -- the video --------------------------------------------------------------------------------------
def test_video_ground_truth_matches_the_rendering(scene):
    v, objs = scene["plain"], scene["objs"]
    assert len(v.frames) == len(v.gt) == FRAMES and v.obj_ids == IDS and v.leave is None
    for f, recs in zip(v.frames, v.gt):
        assert f.dtype == np.uint8 and f.shape == (H, W, 3)
        for o, g in zip(objs, recs):
            # the object stays in view, and the box of its model projected with the GT pose is the box
            # of its rendered pixels (pixel centres: up to ~1.5 px inside the continuous outline)
            assert g["in_view"] == 1.0 and g["visible_px"] > 300 and g["visible_px"] == g["mask"].sum()
            uv = project_points(o.vertices, K, g["R"], g["t"])
            proj = bbox_from_points(uv)
            np.testing.assert_allclose(g["box"][:2], proj[:2], atol=1.5)
            np.testing.assert_allclose(g["box"][:2] + g["box"][2:], proj[:2] + proj[2:], atol=2.5)
            # every vertex projects onto the object's silhouette (its rendered pixels: the two objects
            # do not overlap), and the frame shows the object there, not the background
            sil = cv2.dilate(g["mask"].astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
            ij = np.rint(uv).astype(int)
            assert sil[ij[:, 1], ij[:, 0]].mean() > 0.99
        assert not (recs[0]["mask"] & recs[1]["mask"]).any()
    # realistic, smooth motion: distance 500-1000 mm, small steps, and it does move and turn
    for j in range(len(objs)):
        R = [r[j]["R"] for r in v.gt]
        t = np.array([r[j]["t"] for r in v.gt])
        assert (500 < t[:, 2]).all() and (t[:, 2] < 1000).all()
        steps_deg = [rotation_error_deg(a, b) for a, b in itertools.pairwise(R)]
        assert max(steps_deg) < 1.5 and np.linalg.norm(np.diff(t, axis=0), axis=1).max() < 15
        assert rotation_error_deg(R[0], R[-1]) > 10 and np.linalg.norm(t[-1] - t[0]) > 5
    # the GT is the trajectories' (deterministic by seed), the seed changes them
    again = trajectories(objs, K, (W, H), FRAMES, seed=0)
    other = trajectories(objs, K, (W, H), FRAMES, seed=1)
    for j in range(len(objs)):
        for i in (0, FRAMES - 1):
            np.testing.assert_array_equal(again[j][i][1], v.gt[i][j]["t"])
            np.testing.assert_array_equal(again[j][i][0], v.gt[i][j]["R"])
        assert np.linalg.norm(other[j][0][1] - again[j][0][1]) > 1.0


def test_leave_video_goes_entirely_out_of_view_and_back(scene):
    v = scene["leave"]
    s1, s2 = v.leave
    assert s2 - s1 == LEAVE and s1 >= RAMP_FRAMES
    for i, recs in enumerate(v.gt):
        for g in recs:
            if s1 <= i < s2:
                assert g["in_view"] == 0.0 and g["visible_px"] == 0 and g["box"] is None
            if i < 2 or i >= LEAVE_FRAMES - 2:
                assert g["in_view"] == 1.0 and g["visible_px"] > 300
        tg = v.targets(i)
        assert len(tg["obj_ids"]) == len(tg["boxes"])
        if s1 <= i < s2:
            assert len(tg["obj_ids"]) == 0
        if i < 2:
            assert tg["obj_ids"].tolist() == IDS
            np.testing.assert_array_equal(tg["boxes"], [g["box"] for g in recs])
    # one fixed background: with every object away a frame is the background plus the sensor noise;
    # the first frame differs from it only where the objects are
    diff = np.abs(v.frames[0].astype(float) - v.frames[s1].astype(float)).mean(-1)
    objects = v.gt[0][0]["mask"] | v.gt[0][1]["mask"]
    assert 1.0 < diff[~objects].mean() < 4.0 and diff[objects].mean() > 15.0
    with pytest.raises(ValueError, match=r"leave=20 needs at least 48 frames"):
        trajectories(scene["objs"], K, (W, H), 40, leave=20)


# -- the benchmark --------------------------------------------------------------------------------
FIELDS = {"mode", "frames", "seconds", "fps", "median_ms", "p95_ms", "detector_calls", "detector_fraction",
          "kpd_calls", "in_view_object_frames", "ok_fraction", "add_s_pass_of_ok", "add_s_pass_of_in_view",
          "median_rot_deg", "median_trans_mm", "out_of_view_object_frames", "lost_object_frames",
          "lost_in_view_object_frames", "ok_out_of_view_object_frames", "reacquire_frames", "latency_ms", "detected"}


def test_tracked_mode_runs_the_detector_rarely_and_is_accurate(scene):
    pipe, det = _pipeline(scene)
    rep = benchmark(pipe, scene["plain"], scene["objs"], detect_every=10, warmup=2)
    tracked, every = rep["modes"]
    assert tracked["mode"] == "tracked" and every["mode"] == "detect_every_frame"
    for r in (tracked, every):
        assert FIELDS <= set(r) and r["frames"] == FRAMES and len(r["latency_ms"]) == FRAMES
        assert r["fps"] == pytest.approx(FRAMES / r["seconds"]) and r["median_ms"] > 0
        assert r["in_view_object_frames"] == FRAMES * len(IDS) and r["out_of_view_object_frames"] == 0
        assert r["ok_fraction"] >= 0.95 and r["add_s_pass_of_ok"] >= 0.95 and r["add_s_pass_of_in_view"] >= 0.9
        assert r["median_rot_deg"] < 1.5 and r["median_trans_mm"] < 5.0 and r["reacquire_frames"] == []
    # the tracker: the detector on frames 0, 10, 20 only; detect-every-frame: on all of them
    assert tracked["detected"] == [i % 10 == 0 for i in range(FRAMES)]
    assert tracked["detector_calls"] == 3 and tracked["detector_fraction"] == pytest.approx(0.1)
    assert tracked["kpd_calls"] == FRAMES
    assert every["detected"] == [True] * FRAMES and every["detector_fraction"] == 1.0 and every["kpd_calls"] == FRAMES
    # the detector's own count: 1 in the tracker's 2 warm-up frames, 3 tracked, 2 + 30 detect-every-frame
    assert det.calls == 1 + 3 + 2 + FRAMES
    table = format_table(rep)
    assert "| tracked | " in table and "| detect_every_frame | " in table and "10%" in table
    assert "re-acquired" not in table  # no leave: no loss columns


def test_leave_reports_lost_frames_and_reacquisition(scene):
    v = scene["leave"]
    pipe, _ = _pipeline(scene)
    rep = benchmark(pipe, v, scene["objs"], detect_every=0, lost_threshold=0.3, warmup=0)
    tracked, every = rep["modes"]
    out_gt = sum(g["in_view"] <= 0 for recs in v.gt for g in recs)
    s1, s2 = v.leave
    assert out_gt >= len(IDS) * LEAVE and rep["video"]["leave"] == [s1, s2]
    for r in (tracked, every):
        assert r["out_of_view_object_frames"] == out_gt
        assert r["lost_object_frames"] >= out_gt and r["ok_out_of_view_object_frames"] == 0
        # each object comes back once and is found again within 2 frames of being back in view
        assert len(r["reacquire_frames"]) == len(IDS)
        assert all(x is not None and 0 <= x <= 2 for x in r["reacquire_frames"]), r["reacquire_frames"]
        assert r["ok_fraction"] >= 0.9 and r["add_s_pass_of_ok"] >= 0.95
    # the tracker's detector: on the first frame, then from when they are lost (leaving) on every frame
    # until both are found again (back in view), and on no other frame
    det_idx = [i for i, d in enumerate(tracked["detected"]) if d]
    out_frames = [i for i, recs in enumerate(v.gt) if any(g["in_view"] <= 0 for g in recs)]
    run = det_idx[1:]
    assert det_idx[0] == 0 and run == list(range(run[0], run[-1] + 1)), det_idx
    assert run[0] <= out_frames[0] and out_frames[-1] < run[-1] <= out_frames[-1] + 3, (run, out_frames)
    assert tracked["detector_fraction"] == pytest.approx(len(det_idx) / LEAVE_FRAMES) and len(det_idx) < 0.6 * LEAVE_FRAMES
    table = format_table(rep)
    assert "re-acquired after" in table and "| lost |" in table


def test_score_counts_wrong_poses_as_failures(scene):
    """The scorer on made-up runs: the GT itself passes with zero error; a pose turned 45 degrees or
    moved by 0.2 diameters fails ADD(-S) with those errors; a pose reported for an object out of view
    counts as ok-out-of-view."""
    v, objs = scene["leave"], scene["objs"]
    n = len(v.frames)

    def run(f):
        return {"seconds": [0.01] * n, "detected": [True] * n, "stats": {"detector_calls": n, "kpd_calls": n},
                "poses": [{g["obj_id"]: f(g) for g in recs} for recs in v.gt]}

    exact = score(v, objs, run(lambda g: (True, g["R"], g["t"])))
    assert exact["add_s_pass_of_ok"] == 1.0 and exact["median_rot_deg"] == 0.0 and exact["median_trans_mm"] == 0.0
    assert exact["ok_out_of_view_object_frames"] == exact["out_of_view_object_frames"] > 0
    assert exact["fps"] == pytest.approx(100.0) and exact["reacquire_frames"] == [0, 0]
    turned = score(v, objs, run(lambda g: (g["in_view"] > 0, g["R"] @ rotation_about_axis([1, 1, 0], np.deg2rad(45)),
                                           g["t"])))
    assert turned["add_s_pass_of_ok"] == 0.0 and turned["median_rot_deg"] == pytest.approx(45.0)
    assert turned["ok_out_of_view_object_frames"] == 0
    d = {o.obj_id: o.diameter for o in objs}
    moved = score(v, objs, run(lambda g: (True, g["R"], g["t"] + [0.2 * d[g["obj_id"]], 0, 0])))
    assert moved["add_s_pass_of_ok"] == 0.0 and moved["median_rot_deg"] == 0.0
    assert moved["median_trans_mm"] == pytest.approx(0.2 * np.median([d[o] for o in IDS]), rel=0.05)
    never = score(v, objs, run(lambda g: (False, None, None)))
    assert never["ok_fraction"] == 0.0 and never["add_s_pass_of_ok"] is None and never["median_rot_deg"] is None
    assert never["reacquire_frames"] == [None, None] and never["lost_object_frames"] == n * len(IDS)


def test_calibration_separates_right_from_wrong_poses_by_confidence(scene):
    """calibrate() on made-up estimates: the GT pose with confidence 0.9 (right) every other frame, a
    pose turned 45 degrees with confidence 0.2 (wrong) on the others: thresholds up to 0.2 keep both
    (precision = the right share), 0.3 to 0.9 keep only the right ones (precision and recall 1), above
    0.9 none; the best threshold by F1 is the lowest perfect one. Poses the pipeline calls not ok and
    objects out of view are left out."""
    from kpd6d.benchmarks.track import calibrate, format_calibration

    v, objs = scene["leave"], scene["objs"]
    turn = rotation_about_axis([1, 1, 0], np.deg2rad(45))
    raw = [{g["obj_id"]: ((True, 0.9, g["R"], g["t"]) if i % 2 == 0 else (True, 0.2, g["R"] @ turn, g["t"]))
            for g in recs} for i, recs in enumerate(v.gt)]
    raw[0] = {o: (False, 0.95, *rest[2:]) for o, rest in raw[0].items()}  # not ok: not counted
    cal = calibrate(v, objs, raw, thresholds=(0.0, 0.2, 0.3, 0.9, 0.95))
    in_view = [(i, g) for i, recs in enumerate(v.gt) for g in recs if g["in_view"] >= 0.5 and i > 0]
    n_right = sum(i % 2 == 0 for i, _ in in_view)
    assert cal["poses"] == len(in_view) and cal["right"] == n_right > 0
    rows = {r["threshold"]: r for r in cal["rows"]}
    assert rows[0.0]["precision"] == pytest.approx(n_right / len(in_view)) and rows[0.0]["recall"] == 1.0
    assert rows[0.2]["kept"] == 1.0
    assert rows[0.3]["precision"] == rows[0.3]["recall"] == rows[0.9]["recall"] == 1.0
    assert rows[0.95]["kept"] == 0.0 and rows[0.95]["precision"] is None and rows[0.95]["f1"] == 0.0
    assert cal["best"] == 0.3
    assert "best threshold by F1: 0.3" in format_calibration(cal)


# -- the command line -----------------------------------------------------------------------------
def _exit_2(capsys, argv) -> str:
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


def test_cli_bad_inputs_exit_2_naming_what_is_wrong(tmp_path, capsys):
    from kpd6d.cli.benchmark import available
    from kpd6d.cli.benchmark import main as dispatch

    assert "track" in available()
    missing = tmp_path / "nothere" / "kpd.ckpt"
    err = _exit_2(capsys, ["--kpd-ckpt", str(missing), "--detector-ckpt", "oracle"])
    assert str(missing) in err and "no such file" in err
    with pytest.raises(SystemExit) as e:  # the same through kpd6d-benchmark track
        dispatch(["track", "--kpd-ckpt", str(missing), "--detector-ckpt", "oracle"])
    assert e.value.code == 2 and str(missing) in capsys.readouterr().err
    kpd, det = tmp_path / "kpd.ckpt", tmp_path / "det.pt"
    kpd.write_bytes(b"")
    det.write_bytes(b"")
    ok = ["--kpd-ckpt", str(kpd), "--detector-ckpt", str(det)]
    assert str(tmp_path / "d2.pt") in _exit_2(capsys, ["--kpd-ckpt", str(kpd), "--detector-ckpt", str(tmp_path / "d2.pt")])
    models = tmp_path / "models"
    models.mkdir()
    err = _exit_2(capsys, [*ok, "--models-dir", str(models)])
    assert str(models) in err and "models_info.json" in err
    (models / "models_info.json").write_text(json.dumps({"1": {"diameter": 100.0}}))
    err = _exit_2(capsys, [*ok, "--models-dir", str(models), "--obj-ids", "7"])
    assert "[7]" in err and str(models) in err
    err = _exit_2(capsys, [*ok, "--obj-ids", "42"])  # the procedural objects are 1..6
    assert "[42]" in err and "procedural" in err
    assert "--export-dir" in _exit_2(capsys, ["--backend", "onnxruntime"])
    assert str(tmp_path / "exp") in _exit_2(capsys, ["--backend", "openvino", "--export-dir", str(tmp_path / "exp")])
    assert "kpd6d_export.json" in _exit_2(capsys, ["--backend", "onnxruntime", "--export-dir", str(tmp_path)])
    assert "needs at least" in _exit_2(capsys, [*ok, "--frames", "20", "--leave", "10"])
    assert "--smoothing" in _exit_2(capsys, [*ok, "--smoothing", "1.0"])
    assert "'cuda9'" in _exit_2(capsys, [*ok, "--backend", "cuda9"])
    # an empty checkpoint file: loading fails, named, no traceback
    err = _exit_2(capsys, [*ok, "--obj-ids", "1"])
    assert "cannot load the pipeline" in err and str(kpd) in err


def test_cli_runs_on_real_untrained_checkpoints(tmp_path, capsys):
    """The torch path end to end on tiny untrained networks (poses are poor: the code path, the counts
    and the outputs are what is checked)."""
    import pytorch_lightning as pl

    from kpd6d.detection import build_detector, save_detector
    from kpd6d.kpd.module import KPDModule

    corners = np.array([[x, y, z] for z in (-20, 20) for y in (-20, 20) for x in (-20, 20)], float)
    torch.manual_seed(0)
    det = build_detector("centernet", obj_ids=[1], backbone="resnet10t", neck_channels=8, head_channels=8,
                         input_size=[128, 96], score_threshold=0.0, max_detections=3)
    save_detector(det, tmp_path / "det.pt")
    kpd = KPDModule(obj_ids=[1], keypoints_3d=[corners], diameters=[69.3], backbone={"name": "tiny", "width": 8},
                    head={"name": "deconv", "deconv_channels": 16}, input_size=64, out_stride=4)
    trainer = pl.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, default_root_dir=tmp_path)
    trainer.strategy.connect(kpd)
    trainer.save_checkpoint(tmp_path / "kpd.ckpt")
    out = tmp_path / "sub" / "track.json"
    rc = main(["--kpd-ckpt", str(tmp_path / "kpd.ckpt"), "--detector-ckpt", str(tmp_path / "det.pt"), "--frames", "3",
               "--warmup", "1", "--threads", "1", "--device", "cpu", "--detect-every", "2", "--json", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "| tracked | " in text and "| detect_every_frame | " in text and "objects [1]" in text
    rep = json.loads(out.read_text())
    tracked, every = rep["modes"]
    assert rep["video"] == {**rep["video"], "frames": 3, "width": 640, "height": 480, "obj_ids": [1]}
    assert rep["settings"]["backend"] == "torch" and rep["settings"]["detect_every"] == 2
    assert every["detector_calls"] == 3 and every["detected"] == [True] * 3 and len(every["latency_ms"]) == 3
    assert tracked["detected"][0] and tracked["frames"] == 3 and tracked["fps"] > 0
    assert [r["threshold"] for r in rep["calibration"]["rows"]][:2] == [0.0, 0.1] and "confidence calibration" in text
    assert not list(out.parent.glob(".*.tmp"))  # written atomically
