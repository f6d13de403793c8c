"""PosePipeline plumbing: oracle detector -> fake KPD (projected GT keypoints, via a crop) -> top-l -> PnP."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from kpd6d.geometry import (
    LINEMOD_K,
    affine_apply,
    bbox_from_points,
    box_to_crop_affine,
    invert_affine,
    pose_from_view,
    project_points,
    rotation_error_deg,
)
from kpd6d.pipeline import PipelineInputError, PosePipeline
from kpd6d.registry import DETECTORS

K_PTS = 12


class FakeKPD:
    """Returns the GT keypoints as a heatmap KPD would see them: in the crop of the given box,
    quantised to a 64x64 heatmap grid at quarter-pixel resolution, mapped back to the image.

    ``gt[(image_index, obj_id)] = (R, t, K)``; ``bad`` keypoints get moved far away with a low
    confidence (top-l must drop them).
    """

    def __init__(self, keypoints_3d, gt, bad=0):
        self.keypoints_3d = keypoints_3d
        self.gt = gt
        self.bad = bad
        self.calls = 0

    def predict_keypoints(self, images, boxes, image_index, obj_ids):
        assert images.ndim == 4 and images.dtype == torch.float32
        self.calls += 1
        kps, confs = [], []
        for box, b, oid in zip(boxes.cpu().numpy(), image_index.tolist(), obj_ids.tolist()):
            R, t, K = self.gt[(b, oid)]
            uv = project_points(self.keypoints_3d[oid], K, R, t)
            A = box_to_crop_affine(box.astype(np.float64), 64, scale=1.2)
            crop_uv = np.round(affine_apply(A, uv) * 4) / 4  # sub-pixel heatmap decoding
            uv_back = affine_apply(invert_affine(A), crop_uv)
            conf = np.linspace(1.0, 0.6, K_PTS)
            if self.bad:
                uv_back[-self.bad:] += 80.0
                conf[-self.bad:] = 0.01
            kps.append(uv_back)
            confs.append(conf)
        return torch.tensor(np.stack(kps), dtype=torch.float32), torch.tensor(np.stack(confs), dtype=torch.float32)


def _scene(rng):
    kp3d = {oid: rng.uniform(-40, 40, (K_PTS, 3)) for oid in (1, 2, 3)}
    poses = {
        (0, 1): pose_from_view(0.3, 0.5, 700, 0.1), (0, 2): pose_from_view(2.0, 0.9, 900, -0.3),
        (1, 3): pose_from_view(-1.0, 0.2, 800, 0.5),
    }
    shift = {(0, 1): [-80, 30, 0], (0, 2): [90, -40, 0], (1, 3): [10, 10, 0]}
    gt = {k: (R, t + np.asarray(shift[k], float), LINEMOD_K) for k, (R, t) in poses.items()}
    targets = []
    for b in (0, 1):
        items = [(oid, gt[(bb, oid)]) for (bb, oid) in gt if bb == b]
        boxes = [bbox_from_points(project_points(kp3d[oid], K, R, t)) for oid, (R, t, K) in items]
        targets.append({"boxes": np.stack(boxes), "obj_ids": np.array([o for o, _ in items]),
                        "scores": np.array([0.9 - 0.1 * i for i in range(len(items))])})
    return kp3d, gt, targets


def _images(n=2):
    return [np.zeros((480, 640, 3), np.uint8) for _ in range(n)]


@pytest.mark.parametrize("solver", ["epnp", "epnp_ransac"])
def test_fake_kpd_recovers_gt_poses_batched(solver):
    kp3d, gt, targets = _scene(np.random.default_rng(0))
    kpd = FakeKPD(kp3d, gt)
    pipe = PosePipeline(DETECTORS.build("oracle"), kpd, pnp=solver, top_l=8, device="cpu")
    out = pipe.predict_batch(_images(), LINEMOD_K, targets)
    assert kpd.calls == 1  # one KPD call for every object of every image
    assert [sorted(p["obj_id"] for p in o) for o in out] == [[1, 2], [3]]
    for b, preds in enumerate(out):
        for p in preds:
            R, t, _ = gt[(b, p["obj_id"])]
            assert p["ok"], p["reason"]
            assert rotation_error_deg(p["R"], R) < 1.0
            assert np.linalg.norm(p["t"] - t) < 10.0  # mm at 700-900 mm
            assert p["keypoints_2d"].shape == (K_PTS, 2) and p["confidences"].shape == (K_PTS,)
            assert p["used"].sum() == 8
            np.testing.assert_array_equal(np.flatnonzero(p["used"]), np.arange(8))  # most confident first
    assert out[0][0]["score"] == pytest.approx(0.9)
    assert set(pipe.last_timings) == {"detect", "kpd", "pnp", "total"}


def test_single_image_call_matches_batch():
    kp3d, gt, targets = _scene(np.random.default_rng(1))
    pipe = PosePipeline(DETECTORS.build("oracle"), FakeKPD(kp3d, gt), pnp="epnp", top_l=None, device="cpu")
    batch = pipe.predict_batch(_images(), np.stack([LINEMOD_K, LINEMOD_K]), targets)
    gt0 = {k: v for k, v in gt.items() if k[0] == 0}
    single = PosePipeline(DETECTORS.build("oracle"), FakeKPD(kp3d, gt0), pnp="epnp", top_l=None,
                          device="cpu")(_images(1)[0], LINEMOD_K, targets[0])
    assert [p["obj_id"] for p in single] == [p["obj_id"] for p in batch[0]]
    for a, b in zip(single, batch[0]):
        np.testing.assert_allclose(a["R"], b["R"], atol=1e-9)
        np.testing.assert_allclose(a["t"], b["t"], atol=1e-6)


def test_top_l_drops_low_confidence_outliers():
    kp3d, gt, targets = _scene(np.random.default_rng(2))
    bad = 4
    good = PosePipeline(DETECTORS.build("oracle"), FakeKPD(kp3d, gt, bad=bad), pnp="epnp", top_l=K_PTS - bad,
                        device="cpu").predict_batch(_images(), LINEMOD_K, targets)
    # the validity gate off: the far-off plain-EPnP poses are compared, not rejected (tests/test_validation.py)
    allp = PosePipeline(DETECTORS.build("oracle"), FakeKPD(kp3d, gt, bad=bad),
                        pnp={"name": "epnp", "max_relative_residual": None}, top_l=None,
                        device="cpu").predict_batch(_images(), LINEMOD_K, targets)
    for b in (0, 1):
        for pg, pa in zip(good[b], allp[b]):
            _, t, _ = gt[(b, pg["obj_id"])]
            assert np.linalg.norm(pg["t"] - t) < 10.0
            assert not pg["used"][-bad:].any()
            # with the 4 outliers (80 px off) plain EPnP is far off: top-l is what makes it work
            assert np.linalg.norm(pa["t"] - t) > 3 * np.linalg.norm(pg["t"] - t)


def test_no_detections_and_unknown_objects():
    kp3d, gt, targets = _scene(np.random.default_rng(3))
    kp_only_1 = {1: kp3d[1]}
    pipe = PosePipeline(DETECTORS.build("oracle"), FakeKPD(kp_only_1, gt), pnp="epnp", device="cpu")
    out = pipe.predict_batch(_images(), LINEMOD_K, targets)
    assert [[p["obj_id"] for p in o] for o in out] == [[1], []]
    empty = [{"boxes": np.zeros((0, 4)), "obj_ids": np.zeros(0, int)}] * 2
    assert pipe.predict_batch(_images(), LINEMOD_K, empty) == [[], []]


def test_bad_inputs_are_named():
    kp3d, gt, targets = _scene(np.random.default_rng(4))
    pipe = PosePipeline(DETECTORS.build("oracle"), FakeKPD(kp3d, gt), pnp="epnp", device="cpu")
    with pytest.raises(PipelineInputError, match="uint8"):
        pipe(np.zeros((480, 640, 3), np.float32), LINEMOD_K, targets[0])
    with pytest.raises(PipelineInputError, match=r"\(H, W, 3\)"):
        pipe(np.zeros((480, 640), np.uint8), LINEMOD_K, targets[0])
    with pytest.raises(PipelineInputError, match="K must be"):
        pipe(_images(1)[0], np.eye(4), targets[0])
    with pytest.raises(PipelineInputError, match="top_l must be >= 4"):
        PosePipeline(DETECTORS.build("oracle"), FakeKPD(kp3d, gt), top_l=3)
    with pytest.raises(PipelineInputError, match="predict_keypoints"):
        PosePipeline(DETECTORS.build("oracle"), object())


def test_benchmark_pipeline_runs_and_prints_stages(capsys):
    from kpd6d.benchmarks.pipeline import main

    assert main(["--configs", "fast", "--batch-sizes", "1", "--repeats", "1", "--warmup", "0", "--objects", "1",
                 "--keypoints", "8", "--top-l", "6", "--device", "cpu"]) == 0
    out = capsys.readouterr().out
    assert "| fast | cpu | 1 | 1 |" in out and "detect ms" in out and "25 fps" in out


class BoxSensitiveKPD(FakeKPD):
    """Keypoints displaced by half the offset between the given box's centre and the object's true box
    centre: a KPD that is only as good as its crop."""

    def predict_keypoints(self, images, boxes, image_index, obj_ids):
        self.calls += 1
        self.boxes_seen.append(boxes.cpu().numpy().copy())
        kps, confs = [], []
        for box, b, oid in zip(boxes.cpu().numpy().astype(np.float64), image_index.tolist(), obj_ids.tolist()):
            R, t, K = self.gt[(b, oid)]
            uv = project_points(self.keypoints_3d[oid], K, R, t)
            true = bbox_from_points(uv)
            offset = (box[:2] + box[2:] / 2) - (true[:2] + true[2:] / 2)
            kps.append(uv + 0.5 * offset)
            confs.append(np.ones(K_PTS))
        return torch.tensor(np.stack(kps), dtype=torch.float32), torch.tensor(np.stack(confs), dtype=torch.float32)


def test_refine_boxes_recrops_on_the_estimated_pose():
    kp3d, gt, targets = _scene(np.random.default_rng(0))
    shifted = [dict(tg, boxes=tg["boxes"] + np.array([24.0, -16.0, 0.0, 0.0])) for tg in targets]  # detector error
    errors = []
    for n in (0, 1, 2):
        kpd = BoxSensitiveKPD(kp3d, gt)
        kpd.boxes_seen = []
        pipe = PosePipeline(DETECTORS.build("oracle"), kpd, pnp="epnp", top_l=None, device="cpu", refine_boxes=n)
        out = pipe.predict_batch(_images(), LINEMOD_K, shifted)
        assert kpd.calls == n + 1
        err = []
        for b, preds in enumerate(out):
            for p in preds:
                R, t, K = gt[(b, p["obj_id"])]
                want = project_points(kp3d[p["obj_id"]], K, R, t)
                got = project_points(kp3d[p["obj_id"]], K, p["R"], p["t"])
                err.append(np.linalg.norm(got - want, axis=1).mean())
                np.testing.assert_allclose(p["box"], shifted[b]["boxes"][list(shifted[b]["obj_ids"]).index(p["obj_id"])])
        errors.append(float(np.mean(err)))
    # the box-centre error halves with every pass: ~14.4 px -> ~7.2 -> ~3.6 (the KPD moves points by half of it)
    assert errors[0] == pytest.approx(0.5 * np.hypot(24, 16), rel=0.05)
    assert errors[1] == pytest.approx(errors[0] / 2, rel=0.1) and errors[2] == pytest.approx(errors[0] / 4, rel=0.1)


def test_refine_boxes_must_be_non_negative():
    with pytest.raises(PipelineInputError, match="refine_boxes"):
        PosePipeline(DETECTORS.build("oracle"), FakeKPD({}, {}), pnp="epnp", refine_boxes=-1, device="cpu")


class BoxRecordingKPD(FakeKPD):
    """FakeKPD that records the boxes it is asked to crop on."""

    def predict_keypoints(self, images, boxes, image_index, obj_ids):
        self.boxes_seen = [*getattr(self, "boxes_seen", []), boxes.cpu().numpy().astype(np.float64)]
        return super().predict_keypoints(images, boxes, image_index, obj_ids)


@pytest.mark.parametrize("refine", [0, 1])
def test_box_scale_grows_the_kpd_crops_and_keeps_the_reported_boxes(refine):
    """box_scale=s: the KPD crops on every box grown s times about its centre (first pass and refined
    passes); the pose dicts report the boxes as given; poses are still exact with a KPD that sees the
    keypoints wherever the crop is. Bad values name box_scale."""
    kp3d, gt, targets = _scene(np.random.default_rng(0))
    runs = {}
    for s in (1.0, 1.3):
        kpd = BoxRecordingKPD(kp3d, gt)
        pipe = PosePipeline(DETECTORS.build("oracle"), kpd, pnp="epnp", top_l=None, device="cpu", refine_boxes=refine,
                            box_scale=s)
        runs[s] = (pipe.predict_batch(_images(), LINEMOD_K, targets), kpd.boxes_seen)
    (_out1, seen1), (out13, seen13) = runs[1.0], runs[1.3]
    assert len(seen1) == len(seen13) == refine + 1
    for i, (a, b) in enumerate(zip(seen1, seen13)):
        # the first pass crops on the given boxes; a refined pass on boxes of poses that differ by the
        # fake KPD's quantisation (a quarter crop pixel) between the two runs
        rtol, atol = (1e-5, 1e-3) if i == 0 else (1e-2, 1.0)
        np.testing.assert_allclose(b[:, 2:], 1.3 * a[:, 2:], rtol=rtol)  # grown ...
        np.testing.assert_allclose(b[:, :2] + b[:, 2:] / 2, a[:, :2] + a[:, 2:] / 2, atol=atol)  # ... about the centre
    flat_given = np.concatenate([t["boxes"] for t in targets])
    np.testing.assert_allclose(np.stack([p["box"] for preds in out13 for p in preds]), flat_given, atol=1e-4)
    for b, preds in enumerate(out13):
        for p in preds:
            _R, t, _ = gt[(b, p["obj_id"])]
            assert p["ok"] and np.linalg.norm(p["t"] - t) < 2.0
    for bad in (0, -1.0, float("nan"), "big"):
        with pytest.raises(PipelineInputError, match="box_scale"):
            PosePipeline(DETECTORS.build("oracle"), FakeKPD({}, {}), pnp="epnp", device="cpu", box_scale=bad)


def test_depth_calibration_scales_the_reported_translations_and_the_refined_boxes():
    """depth_calibration: every reported t is the PnP t times its object's factor (R, ok and the pose
    confidence are the PnP pose's); box refinement projects the calibrated pose (nearer: a larger
    box). Bad values name depth_calibration."""
    kp3d, gt, targets = _scene(np.random.default_rng(0))
    factors = {1: 0.9, "default": 1.2}
    runs = {}
    for refine in (0, 1):
        for cal in (1.0, factors):
            kpd = BoxRecordingKPD(kp3d, gt)
            pipe = PosePipeline(DETECTORS.build("oracle"), kpd, pnp="epnp", top_l=None, device="cpu",
                                refine_boxes=refine, depth_calibration=cal)
            runs[refine, cal == 1.0] = (pipe.predict_batch(_images(), LINEMOD_K, targets), kpd.boxes_seen)
    (raw, _), (cal, _) = runs[0, True], runs[0, False]
    n = 0
    for preds_raw, preds_cal in zip(raw, cal):
        for a, b in zip(preds_raw, preds_cal):
            f = 0.9 if a["obj_id"] == 1 else 1.2
            assert a["ok"] and b["ok"]
            np.testing.assert_array_equal(b["R"], a["R"])
            np.testing.assert_allclose(b["t"], f * a["t"], rtol=1e-12)
            assert b["confidence"] == a["confidence"] and b["residual_px"] == a["residual_px"]
            n += 1
    assert n == 3
    # the refined pass crops on the projection of the calibrated pose: side ~ 1 / factor
    (_, seen_raw), (_, seen_cal) = runs[1, True], runs[1, False]
    flat_ids = [o for tg in targets for o in tg["obj_ids"]]
    want = np.array([1 / 0.9 if o == 1 else 1 / 1.2 for o in flat_ids])
    np.testing.assert_allclose((seen_cal[1][:, 2:] / seen_raw[1][:, 2:]).mean(1), want, rtol=0.03)
    np.testing.assert_allclose(seen_cal[0], seen_raw[0])  # the first pass: the detector's boxes
    for bad in (0, -1.0, float("nan"), "big", {"x": 1.0}):
        with pytest.raises(PipelineInputError, match="depth_calibration"):
            PosePipeline(DETECTORS.build("oracle"), FakeKPD({}, {}), pnp="epnp", device="cpu", depth_calibration=bad)


class DecoyAwareKPD(FakeKPD):
    """As FakeKPD on boxes that overlap the object's true box; on a box elsewhere (a false detection)
    scattered keypoints with low confidence, as a KPD gives on background."""

    def __init__(self, keypoints_3d, gt, true_boxes):
        super().__init__(keypoints_3d, gt)
        self.true_boxes = true_boxes
        self.rng = np.random.default_rng(0)

    def predict_keypoints(self, images, boxes, image_index, obj_ids):
        any_pose = next(iter(self.gt.values()))  # an object not in the image: a crop of background
        for b, oid in zip(image_index.tolist(), obj_ids.tolist()):
            self.gt.setdefault((b, oid), any_pose)
        kps, confs = super().predict_keypoints(images, boxes, image_index, obj_ids)
        for n, (box, b, oid) in enumerate(zip(boxes.cpu().numpy(), image_index.tolist(), obj_ids.tolist())):
            tx, ty, tw, th = self.true_boxes.get((b, oid), (-1e4, -1e4, 1.0, 1.0))
            x, y, w, h = box
            if x > tx + tw or tx > x + w or y > ty + th or ty > y + h:  # no overlap: background
                kps[n] = torch.tensor(self.rng.uniform([x, y], [x + w, y + h], (K_PTS, 2)), dtype=torch.float32)
                confs[n] = torch.full((K_PTS,), 0.15)
        return kps, confs


def test_candidates_keep_the_pose_the_keypoints_verify():
    """A false detection of object 1 scores above the true one: the best-scoring box alone (what
    one_per_object gives) yields a wrong pose; with candidates=2 both are estimated and the pose with
    the higher pose confidence (the true box's) is kept, one per object."""
    from kpd6d.pnp.estimator import best_candidates, candidate_options, top_candidates

    kp3d, gt, targets = _scene(np.random.default_rng(5))
    true_boxes = {(b, int(o)): box for b, t in enumerate(targets) for box, o in zip(t["boxes"], t["obj_ids"])}
    decoy = np.array([500.0, 380.0, 90.0, 80.0])  # far from every object
    t0 = targets[0]
    with_decoy = [{"boxes": np.vstack([decoy, t0["boxes"]]), "obj_ids": np.concatenate([[1], t0["obj_ids"]]),
                   "scores": np.concatenate([[0.99], t0["scores"]])}, targets[1]]

    def run(candidates, one_per_object):
        det = DETECTORS.build("oracle", one_per_object=one_per_object)
        pipe = PosePipeline(det, DecoyAwareKPD(kp3d, gt, true_boxes), pnp="sqpnp", top_l=None, device="cpu",
                            candidates=candidates)
        return pipe.predict_batch(_images(), LINEMOD_K, with_decoy)

    def t_error(p, b):
        return np.linalg.norm(p["t"] - gt[(b, p["obj_id"])][1]) if p["ok"] else np.inf

    single = run(1, True)  # the detector's best box per object: the decoy for object 1
    p1 = [p for p in single[0] if p["obj_id"] == 1]
    assert len(p1) == 1 and t_error(p1[0], 0) > 100.0
    both = run(1, False)  # every detection gives a pose
    assert sorted(p["obj_id"] for p in both[0]) == [1, 1, 2]
    verified = run(2, False)
    assert [sorted(p["obj_id"] for p in o) for o in verified] == [[1, 2], [3]]
    for b, poses in enumerate(verified):
        for p in poses:
            assert t_error(p, b) < 10.0
    assert [p["candidates"] for p in verified[0] if p["obj_id"] == 1] == [2]
    assert all(p["candidates"] == 1 for p in verified[1])

    # the pure helpers
    dets = [{"image_index": 0, "obj_id": 1, "score": s, "box": [s] * 4} for s in (0.2, 0.9, 0.5, 0.7)]
    dets += [{"image_index": 1, "obj_id": 1, "score": 0.1, "box": [0] * 4}]
    assert [d["score"] for d in top_candidates(dets, 2)] == [0.9, 0.7, 0.1]  # detection order kept
    poses = [{"obj_id": 1, "score": 0.9, "confidence": 0.2}, {"obj_id": 1, "score": 0.5, "confidence": 0.6},
             {"obj_id": 2, "score": 0.3, "confidence": 0.0}, {"obj_id": 1, "score": 0.7, "confidence": 0.6}]
    kept = best_candidates(poses)
    assert [(p["obj_id"], p["score"], p["candidates"]) for p in kept] == [(1, 0.7, 3), (2, 0.3, 1)]
    assert candidate_options(1, "det.pt") == {} and candidate_options(3, "oracle") == {}
    assert candidate_options(3, "det.pt") == {"candidates": 3, "one_per_object": False}
    with pytest.raises(ValueError, match="candidates must be an integer >= 1, got 0"):
        candidate_options(0, "det.pt")
    # detector overrides ride along (not for the oracle); one_per_object=true contradicts several candidates
    thr = {"score_threshold": 0.05}
    assert candidate_options(1, "det.pt", ValueError, thr) == thr and candidate_options(3, "oracle", ValueError, thr) == {}
    assert candidate_options(3, "det.pt", ValueError, thr) == {**thr, "candidates": 3, "one_per_object": False}
    with pytest.raises(ValueError, match="one_per_object=true contradicts candidates=3"):
        candidate_options(3, "det.pt", ValueError, {"one_per_object": True})
    with pytest.raises(PipelineInputError, match="candidates must be an integer >= 1"):
        PosePipeline(DETECTORS.build("oracle"), FakeKPD(kp3d, gt), candidates=0, device="cpu")


class RecordingDecoyKPD(DecoyAwareKPD):
    """DecoyAwareKPD that records the boxes of every call."""

    def __init__(self, *a):
        super().__init__(*a)
        self.boxes_seen = []

    def predict_keypoints(self, images, boxes, image_index, obj_ids):
        self.boxes_seen.append((boxes.cpu().numpy().astype(np.float64), obj_ids.tolist()))
        return super().predict_keypoints(images, boxes, image_index, obj_ids)


def test_verify_crops_verifies_with_few_crops_then_estimates_the_kept_with_crop_tta():
    """candidates {per_object: 2, verify_crops: 1} with crop_tta 3: one KPD call on every candidate box
    (one crop each), then one on the kept boxes' 3 crops (tta_boxes); the picks are those of crop_tta 1
    and the poses those of crop_tta 3 on the kept boxes (predict_boxes), each keeping its candidate count."""
    from kpd6d.pnp.estimator import candidates_record, check_candidates, tta_boxes

    kp3d, gt, targets = _scene(np.random.default_rng(5))
    true_boxes = {(b, int(o)): box for b, t in enumerate(targets) for box, o in zip(t["boxes"], t["obj_ids"])}
    decoy = np.array([500.0, 380.0, 90.0, 80.0])
    t0 = targets[0]
    with_decoy = [{"boxes": np.vstack([decoy, t0["boxes"]]), "obj_ids": np.concatenate([[1], t0["obj_ids"]]),
                   "scores": np.concatenate([[0.99], t0["scores"]])}, targets[1]]

    def pipe(candidates, crop_tta):
        kpd = RecordingDecoyKPD(kp3d, gt, true_boxes)
        return PosePipeline(DETECTORS.build("oracle", one_per_object=False), kpd, pnp="sqpnp", top_l=None,
                            device="cpu", candidates=candidates, crop_tta=crop_tta), kpd

    fast, kpd = pipe({"per_object": 2, "verify_crops": 1}, 3)
    got = fast.predict_batch(_images(), LINEMOD_K, with_decoy)
    ref = pipe(2, 1)[0].predict_batch(_images(), LINEMOD_K, with_decoy)
    assert len(kpd.boxes_seen) == 2
    all_boxes = np.concatenate([t["boxes"] for t in with_decoy])
    np.testing.assert_allclose(kpd.boxes_seen[0][0], all_boxes, atol=1e-4)  # every candidate, one crop
    kept = [p for ps in got for p in ps]
    assert [(p["obj_id"], p["score"]) for ps in got for p in ps] == [(p["obj_id"], p["score"]) for ps in ref for p in ps]
    np.testing.assert_allclose(kpd.boxes_seen[1][0], tta_boxes(np.stack([p["box"] for p in kept]), 3), atol=1e-4)
    assert [p["candidates"] for p in kept] == [p["candidates"] for ps in ref for p in ps] and max(
        p["candidates"] for p in kept) == 2
    direct = pipe(1, 3)[0].predict_boxes(_images(), LINEMOD_K, np.stack([p["box"] for p in kept]),
                                         [p["obj_id"] for p in kept], [b for b, ps in enumerate(got) for _ in ps],
                                         [p["score"] for p in kept])
    for a, b in zip(kept, [p for ps in direct for p in ps]):
        np.testing.assert_allclose(a["R"], b["R"], atol=1e-9)
        np.testing.assert_allclose(a["t"], b["t"], atol=1e-6)
        assert a["confidence"] == pytest.approx(b["confidence"])
    assert fast.last_timings["kpd"] > 0
    assert check_candidates({"per_object": 5, "verify_crops": 1}) == (5, 0, 1.0, 1, 0.0, 1)
    assert candidates_record(5, 0, 1.0, 1) == {"per_object": 5, "verify_crops": 1}
    for bad in (0, 10, 1.5):
        with pytest.raises(ValueError, match=r"candidates.verify_crops must be an integer (>= 1|from 1 to 9)"):
            check_candidates({"per_object": 2, "verify_crops": bad})


def test_candidate_rank_weighs_the_detection_score():
    """best_candidates ranks an object's candidates by pose confidence x detection score ** w: w = 0
    is the pose confidence alone, w = 1 (the default) the product, a large w the detector's order;
    check_candidates / candidates_record carry w (only when it is not the default) and name bad values."""
    from kpd6d.pnp.estimator import (
        DETECTOR_WEIGHT,
        best_candidates,
        candidate_options,
        candidates_record,
        check_candidates,
    )

    poses = [{"obj_id": 1, "score": 0.9, "confidence": 0.5},   # products: 0.45
             {"obj_id": 1, "score": 0.3, "confidence": 0.6},   # 0.18: the most confident pose
             {"obj_id": 1, "score": 0.5, "confidence": 0.8},   # 0.40
             {"obj_id": 2, "score": 0.2, "confidence": 0.0}]

    def pick(w):
        return [(p["obj_id"], p["score"]) for p in best_candidates(poses, w)]

    assert DETECTOR_WEIGHT == 1.0 and [(p["obj_id"], p["score"]) for p in best_candidates(poses)] == pick(1.0)
    assert pick(0.0) == [(1, 0.5), (2, 0.2)]     # confidence 0.8 beats 0.6 and 0.5
    assert pick(1.0) == [(1, 0.9), (2, 0.2)]     # 0.45 > 0.40 > 0.18
    assert pick(20.0) == [(1, 0.9), (2, 0.2)]    # the detector's order
    assert pick(0.5) == [(1, 0.5), (2, 0.2)]     # 0.8 * 0.5 ** 0.5 = 0.566 > 0.5 * 0.9 ** 0.5 = 0.474
    # a failed pose (confidence 0) loses whatever its score; equal keys go to the higher score
    assert pick(1.0) == pick(3.0) and best_candidates(
        [{"obj_id": 3, "score": 0.2, "confidence": 0.5}, {"obj_id": 3, "score": 0.4, "confidence": 0.25}], 1.0
    )[0]["score"] == 0.4

    assert check_candidates({"per_object": 5, "detector_weight": 0}) == (5, 0, 0.0, None, 0.0, 1)
    assert candidates_record(5, 0, 1.0) == 5 and candidates_record(5, 0, 0.0) == {"per_object": 5, "detector_weight": 0.0}
    assert candidates_record(*check_candidates({"per_object": 2, "any_class": 1, "detector_weight": 2})) == {
        "per_object": 2, "any_class": 1, "detector_weight": 2.0}
    assert candidate_options({"per_object": 5, "detector_weight": 0.5}, "det.pt") == {
        "candidates": {"per_object": 5, "detector_weight": 0.5}, "one_per_object": False}
    for bad in (-1, float("nan"), "high", True):
        with pytest.raises(ValueError, match=r"evaluate.candidates.detector_weight must be a finite number >= 0, got"):
            check_candidates({"per_object": 2, "detector_weight": bad}, key="evaluate.candidates")
    with pytest.raises(ValueError, match=r"known: \['any_class', 'detector_weight', 'max_instances', 'per_object', 'refine_weight', 'verify_crops'\]"):
        check_candidates({"weight": 1})


class MultiInstanceKPD:
    """Exact keypoints on a box that overlaps an instance's true box (IoU >= 0.3: the best such instance of
    the box's object), scattered low-confidence keypoints elsewhere (background)."""

    def __init__(self, keypoints_3d, instances):
        self.keypoints_3d = keypoints_3d
        self.instances = instances  # [(image_index, obj_id, true box, R, t)]
        self.rng = np.random.default_rng(0)

    def predict_keypoints(self, images, boxes, image_index, obj_ids):
        from kpd6d.geometry import box_iou_xywh

        kps, confs = [], []
        for box, b, oid in zip(boxes.cpu().numpy().astype(np.float64), image_index.tolist(), obj_ids.tolist()):
            mine = [(float(box_iou_xywh(box, tb)[0]), R, t) for bb, o, tb, R, t in self.instances if (bb, o) == (b, oid)]
            iou, R, t = max(mine, key=lambda m: m[0]) if mine else (0.0, None, None)
            if iou >= 0.3:
                kps.append(project_points(self.keypoints_3d[oid], LINEMOD_K, R, t))
                confs.append(np.full(K_PTS, 0.9))
            else:
                x, y, w, h = box
                kps.append(self.rng.uniform([x, y], [x + w, y + h], (K_PTS, 2)))
                confs.append(np.full(K_PTS, 0.15))
        return torch.tensor(np.stack(kps), dtype=torch.float32), torch.tensor(np.stack(confs), dtype=torch.float32)


def test_candidates_keep_several_instances_of_an_object_with_max_instances():
    """Two instances of object 1 in one image, a false box of it scoring above both and a second box on
    instance A (IoU > 0.5 with A's): max_instances 1 keeps one pose (the best-ranked true one); 2 keeps a
    right pose of each instance, never two of A; best_candidates drops zero-rank candidates and boxes that
    overlap a kept one by SAME_INSTANCE_IOU; check_candidates / candidates_record carry max_instances."""
    from kpd6d.geometry import box_iou_xywh
    from kpd6d.pnp.estimator import (
        SAME_INSTANCE_IOU,
        best_candidates,
        candidates_record,
        check_candidates,
    )

    rng = np.random.default_rng(3)
    kp3d = {1: rng.uniform(-40, 40, (K_PTS, 3))}
    insts = []
    for az, shift in ((0.3, [-120.0, 20.0, 0.0]), (1.9, [110.0, -30.0, 0.0])):
        R, t = pose_from_view(az, 0.6, 800, 0.2)
        t = t + np.asarray(shift)
        insts.append((0, 1, bbox_from_points(project_points(kp3d[1], LINEMOD_K, R, t)), R, t))
    box_a, box_b = insts[0][2], insts[1][2]
    dup_a = box_a + np.array([0.05, 0.05, 0.0, 0.0]) * box_a[[2, 3, 2, 3]]  # same instance, shifted 5 %
    assert box_iou_xywh(dup_a, box_a)[0] > SAME_INSTANCE_IOU and box_iou_xywh(box_a, box_b)[0] == 0.0
    decoy = np.array([280.0, 380.0, 80.0, 80.0])
    boxes = np.stack([decoy, dup_a, box_a, box_b])
    targets = [{"boxes": boxes, "obj_ids": np.array([1, 1, 1, 1]), "scores": np.array([0.95, 0.9, 0.8, 0.7])}]

    def run(candidates):
        pipe = PosePipeline(DETECTORS.build("oracle", one_per_object=False), MultiInstanceKPD(kp3d, insts),
                            pnp="sqpnp", top_l=None, device="cpu", candidates=candidates)
        return pipe.predict_batch(_images(1), LINEMOD_K, targets)[0]

    def nearest(p):  # (instance index, translation error mm)
        err = [np.linalg.norm(p["t"] - t) if p["ok"] else np.inf for *_, t in insts]
        return int(np.argmin(err)), float(min(err))

    one = run({"per_object": 4})
    assert len(one) == 1 and one[0]["candidates"] == 4 and one[0]["score"] == pytest.approx(0.9)  # dup_a: A
    assert nearest(one[0])[0] == 0 and nearest(one[0])[1] < 1.0
    two = run({"per_object": 4, "max_instances": 2})
    assert [p["score"] for p in two] == pytest.approx([0.9, 0.7]) and all(p["candidates"] == 4 for p in two)
    assert [nearest(p)[0] for p in two] == [0, 1] and max(nearest(p)[1] for p in two) < 1.0
    four = run({"per_object": 4, "max_instances": 4})  # box_a (A again) is never kept beside dup_a
    scores = [round(p["score"], 3) for p in four]
    assert 0.8 not in scores and {0.9, 0.7} <= set(scores)

    # the pure helper: rank order, zero-rank candidates and overlapping boxes dropped, the cap
    b0, b1, b2 = [0, 0, 10, 10], [4, 0, 10, 10], [50, 50, 10, 10]  # IoU(b0, b1) = 0.6 / 1.4 = 0.43
    poses = [{"obj_id": 1, "score": 0.9, "confidence": 0.5, "box": b0},
             {"obj_id": 1, "score": 0.8, "confidence": 0.5, "box": list(np.add(b0, [1, 0, 0, 0]))},  # IoU 0.82
             {"obj_id": 1, "score": 0.6, "confidence": 0.5, "box": b1},
             {"obj_id": 1, "score": 0.7, "confidence": 0.0, "box": b2},  # failed: never a second instance
             {"obj_id": 2, "score": 0.5, "confidence": 0.2, "box": b2}]
    np.testing.assert_allclose(box_iou_xywh(b0, [b1, b0, [20, 20, 5, 5]]), [60 / 140, 1.0, 0.0])  # by hand

    def kept(m):
        return [(p["obj_id"], p["score"]) for p in best_candidates(poses, 1.0, 0.0, m)]

    assert kept(1) == [(1, 0.9), (2, 0.5)] == [(p["obj_id"], p["score"]) for p in best_candidates(poses)]
    assert kept(2) == kept(5) == [(1, 0.9), (1, 0.6), (2, 0.5)]
    assert check_candidates({"per_object": 3, "max_instances": 2}) == (3, 0, 1.0, None, 0.0, 2)
    assert candidates_record(*check_candidates({"per_object": 3, "max_instances": 2})) == {
        "per_object": 3, "max_instances": 2}
    assert candidates_record(*check_candidates({"per_object": 3, "max_instances": 1})) == 3
    with pytest.raises(ValueError, match=r"evaluate.candidates.max_instances=3 exceeds per_object=2"):
        check_candidates({"per_object": 2, "max_instances": 3}, key="evaluate.candidates")
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match=r"candidates.max_instances must be an integer >= 1, got"):
            check_candidates({"per_object": 2, "max_instances": bad})


def test_check_detector_overrides_names_the_key_and_value():
    from kpd6d.config import ConfigError
    from kpd6d.detection.detectors import check_detector_overrides

    assert check_detector_overrides(None) == {} and check_detector_overrides({}) == {}
    assert check_detector_overrides({"score_threshold": 0, "max_detections": None, "one_per_object": False}) == {
        "score_threshold": 0.0, "one_per_object": False}
    assert check_detector_overrides({"test_scales": [1, 1.5, 1]}) == {"test_scales": [1.0, 1.5]}
    for value, msg in (({"score_threshold": 1.5}, r"evaluate.detector_overrides.score_threshold must be a number in \[0, 1\], got 1.5"),
                       ({"max_detections": 0}, r"max_detections must be a positive integer, got 0"),
                       ({"one_per_object": "yes"}, r"one_per_object must be true or false, got 'yes'"),
                       ({"nms": 0.5}, r"cannot override \['nms'\]; known: score_threshold, max_detections, one_per_object, test_scales"),
                       ({"test_scales": [1, 0]}, r"test_scales must hold positive numbers .* got 0 in \[1, 0\]"),
                       ({"test_scales": []}, r"detector_overrides.test_scales must be a non-empty list"),
                       (0.05, r"must be a mapping of score_threshold")):
        with pytest.raises(ConfigError, match=msg):
            check_detector_overrides(value, ConfigError, "evaluate.detector_overrides")


def test_any_class_candidates_recover_a_misclassified_object():
    """The detector labels object 1's box as object 2 and puts its only object-1 box on clutter: per
    class candidates cannot find object 1; with any_class the image's best boxes are also tried as
    every object, and the keypoints pick object 1's own box for object 1 and object 2's for object 2."""
    from kpd6d.pnp.estimator import candidate_options, candidates_record, check_candidates, top_candidates

    kp3d, gt, targets = _scene(np.random.default_rng(5))
    true_boxes = {(b, int(o)): box for b, t in enumerate(targets) for box, o in zip(t["boxes"], t["obj_ids"])}
    decoy = np.array([500.0, 380.0, 90.0, 80.0])
    box1, box2 = true_boxes[(0, 1)], true_boxes[(0, 2)]
    confused = [{"boxes": np.stack([decoy, box1, box2]), "obj_ids": np.array([1, 2, 2]),
                 "scores": np.array([0.99, 0.8, 0.7])}, targets[1]]

    def run(candidates):
        pipe = PosePipeline(DETECTORS.build("oracle", one_per_object=False), DecoyAwareKPD(kp3d, gt, true_boxes),
                            pnp="sqpnp", top_l=None, device="cpu", candidates=candidates)
        return pipe.predict_batch(_images(), LINEMOD_K, confused)

    def t_error(p, b):
        return np.linalg.norm(p["t"] - gt[(b, p["obj_id"])][1]) if p["ok"] and (b, p["obj_id"]) in gt else np.inf

    per_class = run(2)
    assert [p["obj_id"] for p in per_class[0]] == [1, 2] and t_error(per_class[0][0], 0) > 100.0
    assert t_error(per_class[0][1], 0) < 10.0
    both = run({"per_object": 2, "any_class": 3})
    by_obj = {p["obj_id"]: p for p in both[0]}
    assert t_error(by_obj[1], 0) < 10.0 and t_error(by_obj[2], 0) < 10.0
    # object 1: its decoy + object 2's two boxes; object 2: its two + the decoy; object 3 (known to
    # the KPD, not in the image): the three boxes, none of them its own: its best pose is on clutter
    assert (by_obj[1]["candidates"], by_obj[2]["candidates"], by_obj[3]["candidates"]) == (3, 3, 3)
    assert by_obj[3]["confidence"] < min(by_obj[1]["confidence"], by_obj[2]["confidence"])
    # image 1 (one detection of object 3): objects 1 and 2 are also tried on it
    assert sorted(p["obj_id"] for p in both[1]) == [1, 2, 3] and t_error(
        next(p for p in both[1] if p["obj_id"] == 3), 1) < 10.0

    # the pure helpers
    dets = [{"image_index": 0, "obj_id": o, "score": s, "box": [s] * 4} for o, s in ((1, 0.9), (2, 0.5), (2, 0.4))]
    got = [(d["obj_id"], d["score"]) for d in top_candidates(dets, 1, any_class=2, obj_ids=[1, 2, 3])]
    assert got == [(1, 0.9), (2, 0.5), (2, 0.9), (3, 0.9), (1, 0.5), (3, 0.5)]
    assert check_candidates(None) == (1, 0, 1.0, None, 0.0, 1) and check_candidates(4) == (4, 0, 1.0, None, 0.0, 1)
    assert check_candidates({"any_class": 2}) == (1, 2, 1.0, None, 0.0, 1) and candidates_record(1, 2) == {"per_object": 1, "any_class": 2}
    assert candidate_options({"per_object": 1, "any_class": 2}, "det.pt") == {
        "candidates": {"per_object": 1, "any_class": 2}, "one_per_object": False}
    assert candidate_options({"per_object": 3, "any_class": 0}, "det.pt") == {"candidates": 3, "one_per_object": False}
    with pytest.raises(ValueError, match=r"candidates.any_class must be an integer >= 0, got -1"):
        check_candidates({"any_class": -1})
    with pytest.raises(ValueError, match=r"evaluate.candidates: unknown key\(s\) \['top'\]; known"):
        check_candidates({"top": 2}, key="evaluate.candidates")


def test_tta_boxes_and_their_median_against_a_direct_computation():
    from kpd6d.pnp.estimator import CROP_TTA_JITTER, combine_tta, tta_boxes

    boxes = np.array([[100.0, 50.0, 40.0, 80.0], [10.0, 20.0, 30.0, 30.0]])
    got = tta_boxes(boxes, 9)
    assert got.shape == (18, 4)
    for j, (f, dx, dy) in enumerate(CROP_TTA_JITTER):
        for i, (x, y, w, h) in enumerate(boxes):
            cx, cy = x + w / 2 + dx * w, y + h / 2 + dy * h
            np.testing.assert_allclose(got[j * 2 + i], [cx - f * w / 2, cy - f * h / 2, f * w, f * h], atol=1e-12)
    np.testing.assert_array_equal(tta_boxes(boxes, 1), boxes)  # the first crop is the box itself
    rng = np.random.default_rng(3)
    kp, conf = rng.normal(size=(3 * 2, 4, 2)), rng.uniform(size=(3 * 2, 4))
    mk, mc = combine_tta(kp, conf, 3)
    for i in range(2):
        for k in range(4):
            for c in range(2):
                assert mk[i, k, c] == sorted(kp[[i, 2 + i, 4 + i], k, c])[1]  # middle of the three crops
            assert mc[i, k] == pytest.approx(conf[[i, 2 + i, 4 + i], k].mean())


class CropOffsetKPD(FakeKPD):
    """Exact GT keypoints, except that the j-th of ``n_crops`` blocks of boxes in a call (crop j of
    crop_tta) is moved by ``offsets[j]`` px: only the median over the crops gets the GT back."""

    def __init__(self, keypoints_3d, gt, offsets, n_crops):
        super().__init__(keypoints_3d, gt)
        self.offsets, self.n_crops, self.seen = offsets, n_crops, []

    def predict_keypoints(self, images, boxes, image_index, obj_ids):
        self.seen.append(boxes.cpu().numpy().astype(np.float64))
        n = len(boxes)
        block = n // self.n_crops
        kps = []
        for r, (b, oid) in enumerate(zip(image_index.tolist(), obj_ids.tolist())):
            R, t, K = self.gt[(b, oid)]
            kps.append(project_points(self.keypoints_3d[oid], K, R, t) + self.offsets[r // block])
        return torch.tensor(np.stack(kps)), torch.full((n, K_PTS), 0.8)


def test_crop_tta_takes_the_median_of_the_crops_keypoints():
    """crop_tta=3: one KPD call on the 3 crops of every box (tta_boxes), each keypoint the median of
    its 3 locations — a +40 px and a -40 px crop leave the exact GT crop's pose; crop_tta=1 sees the
    first crop only. Bad values name crop_tta."""
    from kpd6d.pnp.estimator import tta_boxes

    kp3d, gt, targets = _scene(np.random.default_rng(0))
    offsets = [np.array([40.0, 0.0]), np.array([0.0, 0.0]), np.array([-40.0, 0.0])]
    kpd = CropOffsetKPD(kp3d, gt, offsets, 3)
    pipe = PosePipeline(DETECTORS.build("oracle"), kpd, pnp="epnp", top_l=None, device="cpu", crop_tta=3)
    out = pipe.predict_batch(_images(), LINEMOD_K, targets)
    given = np.concatenate([t["boxes"] for t in targets])
    assert len(kpd.seen) == 1
    np.testing.assert_allclose(kpd.seen[0], tta_boxes(given, 3), atol=1e-4)
    for b, preds in enumerate(out):
        for p in preds:
            R, t, _ = gt[(b, p["obj_id"])]
            assert p["ok"] and rotation_error_deg(p["R"], R) < 0.1 and np.linalg.norm(p["t"] - t) < 1.0
            np.testing.assert_allclose(p["confidences"], 0.8, atol=1e-6)
    single = PosePipeline(DETECTORS.build("oracle"), CropOffsetKPD(kp3d, gt, offsets, 1), pnp="epnp", top_l=None,
                          device="cpu").predict_batch(_images(), LINEMOD_K, targets)
    errs = [np.abs(p["keypoints_2d"] - project_points(kp3d[p["obj_id"]], LINEMOD_K, *gt[(b, p["obj_id"])][:2])).max()
            for b, preds in enumerate(single) for p in preds]
    assert len(errs) == 3 and min(errs) == pytest.approx(40.0, abs=1e-3)  # crop_tta=1: the first crop's keypoints, 40 px off
    for bad in (0, 10, 2.5, True, "3"):
        with pytest.raises(PipelineInputError, match="crop_tta must be an integer from 1 to 9"):
            PosePipeline(DETECTORS.build("oracle"), FakeKPD({}, {}), pnp="epnp", device="cpu", crop_tta=bad)


def test_crop_tta_stability_weighs_each_confidence_by_its_spread_over_the_crops():
    """combine_tta(..., stability=τ) against a direct computation: confidence x exp(-(mad / (τ r))^2), mad the
    median distance of a keypoint's crops from its median, r the RMS radius of the median pattern."""
    from kpd6d.pnp.estimator import combine_tta

    rng = np.random.default_rng(5)
    n, N, k = 5, 3, 6
    kp, conf = rng.normal(0, 20, size=(n * N, k, 2)), rng.uniform(0.2, 1.0, size=(n * N, k))
    med, plain = combine_tta(kp, conf, n)
    mk, mc = combine_tta(kp, conf, n, stability=0.2)
    np.testing.assert_array_equal(mk, med)  # the locations do not change
    for i in range(N):
        rows = [j * N + i for j in range(n)]
        pattern = np.array([[np.median(kp[rows, q, c]) for c in range(2)] for q in range(k)])
        r = math.sqrt(np.mean(np.sum((pattern - pattern.mean(0)) ** 2, axis=1)))
        for q in range(k):
            mad = np.median([math.dist(kp[j, q], pattern[q]) for j in rows])
            want = max(np.mean(conf[rows, q]) * math.exp(-((mad / (0.2 * r)) ** 2)), 1e-6)
            assert mc[i, q] == pytest.approx(want, rel=1e-9)
            assert mc[i, q] <= plain[i, q] + 1e-12


class CropFollowingKPD(FakeKPD):
    """Exact keypoints 0..5 in every crop (confidence 0.8); keypoints 6..11 placed from the crop itself:
    20 px right of their GT plus the crop's own shift from the box (confidence 0.9, so top-l by confidence
    alone would choose them) — their median over the crops is 20 px off and they move from crop to crop."""

    def __init__(self, keypoints_3d, gt, boxes_by_key):
        super().__init__(keypoints_3d, gt)
        self.boxes_by_key = boxes_by_key

    def predict_keypoints(self, images, boxes, image_index, obj_ids):
        b = boxes.cpu().numpy().astype(np.float64)
        kps, confs = [], []
        for r, (im, oid) in enumerate(zip(image_index.tolist(), obj_ids.tolist())):
            R, t, K = self.gt[(im, oid)]
            uv = project_points(self.keypoints_3d[oid], K, R, t)
            box = self.boxes_by_key[(im, oid)]
            moved = (b[r, :2] + b[r, 2:] / 2) - (box[:2] + box[2:] / 2)  # the crop's centre shift
            uv[6:] += np.array([20.0, 0.0]) + moved
            kps.append(uv)
            confs.append(np.r_[np.full(6, 0.8), np.full(6, 0.9)])
        return torch.tensor(np.stack(kps)), torch.tensor(np.stack(confs))


def test_crop_tta_stability_keeps_the_keypoints_the_image_pins_down():
    """crop_tta {crops: 9, stability: 0.1} with top_l 6: the six keypoints that move with the crop lose their
    weight, PnP gets the six exact ones and the GT pose; by confidence alone (crops 9, no stability) top-6 takes
    the 20-px-off ones. The setting is checked (names the key) and recorded as given."""
    from kpd6d.pnp.estimator import check_crop_tta, crop_tta_record

    kp3d, gt, targets = _scene(np.random.default_rng(0))
    boxes = {(b, int(o)): np.asarray(bx, float) for b, t in enumerate(targets) for bx, o in zip(t["boxes"], t["obj_ids"])}

    def run(crop_tta):
        pipe = PosePipeline(DETECTORS.build("oracle"), CropFollowingKPD(kp3d, gt, boxes), pnp="epnp", top_l=6,
                            device="cpu", crop_tta=crop_tta)
        return [(p, gt[(b, p["obj_id"])]) for b, preds in enumerate(pipe.predict_batch(_images(), LINEMOD_K, targets))
                for p in preds]

    for p, (R, t, _) in run({"crops": 9, "stability": 0.1}):
        assert p["ok"] and rotation_error_deg(p["R"], R) < 0.1 and np.linalg.norm(p["t"] - t) < 1.0
    off = [np.linalg.norm(p["t"] - t) for p, (R, t, _) in run(9)]
    assert len(off) == 3 and min(off) > 5.0  # the shifted keypoints: the pose is off
    assert check_crop_tta(3) == (3, None) and check_crop_tta({"crops": 9, "stability": 0.1}) == (9, 0.1)
    assert check_crop_tta({"crops": 4}) == (4, None)
    assert crop_tta_record(9, 0.1) == {"crops": 9, "stability": 0.1} and crop_tta_record(9) == 9
    for bad, msg in [({"crops": 1, "stability": 0.1}, r"crop_tta.stability needs crops >= 2"),
                     ({"crops": 9, "stability": -1}, r"crop_tta.stability must be a number > 0, got -1"),
                     ({"crops": 12}, r"crop_tta.crops must be an integer from 1 to 9, got 12"),
                     ({"crop": 9}, r"crop_tta: unknown key\(s\) \['crop'\]; known: crops, stability")]:
        with pytest.raises(PipelineInputError, match=msg):
            PosePipeline(DETECTORS.build("oracle"), FakeKPD({}, {}), pnp="epnp", device="cpu", crop_tta=bad)


class ShiftingRefiner:
    """A pose refiner that records what it is given and moves every ok pose 5 mm along x."""

    def __init__(self):
        self.seen = []

    def refine_poses(self, images, Ks, poses):
        self.seen.append(([np.asarray(im).shape for im in images], np.asarray(Ks).shape,
                          [[p["obj_id"] for p in ps] for ps in poses]))
        for ps in poses:
            for p in ps:
                if p["ok"]:
                    p["t"] = p["t"] + np.array([5.0, 0.0, 0.0])
                    p["refined"] = True
        return poses


def test_a_refiner_runs_on_the_final_poses_of_predict_batch_and_predict_boxes():
    kp3d, gt, targets = _scene(np.random.default_rng(0))
    pipe = PosePipeline(DETECTORS.build("oracle"), FakeKPD(kp3d, gt), pnp="epnp", top_l=None, device="cpu")
    plain = pipe.predict_batch(_images(), LINEMOD_K, targets)
    ref = ShiftingRefiner()
    pipe.set_refiner(ref)
    out = pipe.predict_batch(_images(), LINEMOD_K, targets)
    assert ref.seen == [([(480, 640, 3)] * 2, (2, 3, 3), [[1, 2], [3]])]  # once, on every image's poses
    for a, b in zip(plain, out):
        for p, q in zip(a, b):
            np.testing.assert_allclose(q["t"] - p["t"], [5.0, 0.0, 0.0], atol=1e-9)
            assert q["refined"] and "refined" not in p
    assert "refine" in pipe.last_timings and pipe.last_timings["total"] >= pipe.last_timings["refine"]
    boxes = pipe.predict_boxes(_images(), LINEMOD_K, targets[0]["boxes"], targets[0]["obj_ids"], [0, 0])
    assert len(ref.seen) == 2 and all(p["refined"] for p in boxes[0])  # tracking's entry point too
    pipe.set_refiner(None)
    assert "refined" not in pipe.predict_batch(_images(), LINEMOD_K, targets)[0][0]
    with pytest.raises(PipelineInputError, match=r"refiner must have \.refine_poses"):
        pipe.set_refiner(object())


class EvidenceRefiner:
    """A refiner that leaves poses where they are and gives each an ``evidence`` from ``rule(pose)``;
    records the (obj_id, score) of the poses of each call."""

    def __init__(self, rule):
        self.rule, self.calls = rule, []

    def refine_poses(self, images, Ks, poses):
        self.calls.append([[(p["obj_id"], round(p["score"], 3)) for p in ps] for ps in poses])
        for ps in poses:
            for p in ps:
                p["evidence"], p["refined"] = self.rule(p), False
        return poses


def test_candidates_ranked_by_refinement_evidence():
    """candidates {per_object: 2, verify_crops: 1, refine_weight: w}: every candidate goes through the
    refiner, its evidence ** w joins its rank, and the kept pose, estimated again with crop_tta's crops,
    is refined again. Object 1 has a second box, shifted by a few pixels and scored higher (0.95 against
    0.9); both give good poses, so the rank follows the score with w = 0. The refiner here favours the
    0.9 box (evidence 1 against 0.01): with w > 0 that one is kept."""
    from kpd6d.pnp.estimator import best_candidates, candidates_record

    kp3d, gt, targets = _scene(np.random.default_rng(5))
    t0 = targets[0]
    i1 = int(np.flatnonzero(t0["obj_ids"] == 1)[0])
    twin = t0["boxes"][i1] + np.array([3.0, 2.0, 0.0, 0.0])
    with_twin = [{"boxes": np.vstack([twin, t0["boxes"]]), "obj_ids": np.concatenate([[1], t0["obj_ids"]]),
                  "scores": np.concatenate([[0.95], t0["scores"]])}, targets[1]]
    assert t0["scores"][i1] == pytest.approx(0.9)

    def run(weight):
        pipe = PosePipeline(DETECTORS.build("oracle", one_per_object=False), FakeKPD(kp3d, gt), pnp="sqpnp",
                            top_l=None, device="cpu", crop_tta=3,
                            candidates={"per_object": 2, "verify_crops": 1, "refine_weight": weight})
        ref = EvidenceRefiner(lambda p: 1.0 if abs(p["score"] - 0.9) < 1e-6 and p["obj_id"] == 1 else 0.01)
        pipe.set_refiner(ref)
        return pipe.predict_batch(_images(), LINEMOD_K, with_twin), ref, pipe

    out, ref, pipe = run(0.0)
    assert [p["score"] for p in out[0] if p["obj_id"] == 1] == [pytest.approx(0.95)]  # the score decides
    assert len(ref.calls) == 1 and sum(map(len, ref.calls[0])) == 3  # only the kept poses refined
    out, ref, pipe = run(2.0)
    assert [p["score"] for p in out[0] if p["obj_id"] == 1] == [pytest.approx(0.9)]  # the evidence decides
    assert len(ref.calls) == 2 and sum(map(len, ref.calls[0])) == 4 and sum(map(len, ref.calls[1])) == 3
    assert pipe.last_timings["refine"] > 0
    # the rank itself: confidence x score ** w_det x evidence ** w_ref
    poses = [{"obj_id": 1, "score": 0.9, "confidence": 0.6, "evidence": 0.2},
             {"obj_id": 1, "score": 0.5, "confidence": 0.5, "evidence": 0.9}]
    assert best_candidates(poses)[0]["score"] == 0.9 and best_candidates(poses, 1.0, 1.0)[0]["score"] == 0.5
    no_ref = PosePipeline(DETECTORS.build("oracle", one_per_object=False), FakeKPD(kp3d, gt), device="cpu",
                          candidates={"per_object": 2, "refine_weight": 1.0})
    with pytest.raises(PipelineInputError, match="refine_weight=1 ranks the candidates by their refinement"):
        no_ref.predict_batch(_images(), LINEMOD_K, targets)
    with pytest.raises(PipelineInputError, match=r"candidates\.refine_weight must be a finite number >= 0"):
        PosePipeline(DETECTORS.build("oracle"), FakeKPD(kp3d, gt), device="cpu",
                     candidates={"per_object": 2, "refine_weight": -1})
    assert candidates_record(2, 0, 1.0, 1, 2.0) == {"per_object": 2, "verify_crops": 1, "refine_weight": 2.0}
