"""The evaluation loop on a hand-made BOP dataset with the oracle detector and a GT-aware fake KPD."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
import trimesh

from kpd6d.data import BopDataset
from kpd6d.evaluation.bop19 import score_bop19_file
from kpd6d.evaluation.results_io import read_bop_results
from kpd6d.evaluation.runner import evaluate
from kpd6d.geometry import LINEMOD_K, bbox_from_points, pose_from_view, project_points
from kpd6d.pipeline import PosePipeline
from kpd6d.registry import DETECTORS

EXTENTS = {1: (60.0, 60.0, 60.0), 2: (80.0, 40.0, 30.0)}


def _keypoints(oid):
    corners = trimesh.creation.box(extents=EXTENTS[oid]).vertices
    return np.concatenate([corners, 0.5 * corners[:4] + [3.0, -2.0, 1.0]])


def make_dataset(root, n_frames=3, hidden=None, symmetries=None):
    """Scene 1 with ``n_frames`` black 320x240 images, objects 1 and 2 in each; ``hidden=(im, obj)`` has an empty
    visible box; ``symmetries={obj_id: [4x4, ...]}`` go into models_info as ``symmetries_discrete``."""
    mdir = root / "models"
    mdir.mkdir(parents=True)
    info = {}
    for oid, ext in EXTENTS.items():
        box = trimesh.creation.box(extents=ext)
        box.export(mdir / f"obj_{oid:06d}.ply")
        info[str(oid)] = {"diameter": float(np.linalg.norm(ext))}
        if symmetries and oid in symmetries:
            info[str(oid)]["symmetries_discrete"] = [np.asarray(S, float).reshape(-1).tolist() for S in symmetries[oid]]
    (mdir / "models_info.json").write_text(json.dumps(info))
    sdir = root / "test" / "000001"
    (sdir / "rgb").mkdir(parents=True)
    K = LINEMOD_K.copy()
    K[0, 2], K[1, 2] = 160.0, 120.0
    gt, gi, cam, poses = {}, {}, {}, {}
    for im in range(n_frames):
        cv2.imwrite(str(sdir / "rgb" / f"{im:06d}.png"), np.full((240, 320, 3), 40, np.uint8))
        gt[str(im)], gi[str(im)] = [], []
        for j, oid in enumerate((1, 2)):
            R, t = pose_from_view(0.4 * im + j, 0.5, 900.0, 0.2 * j)
            t = t + np.array([-60.0 + 120 * j, 10.0 * im, 0.0])
            poses[(im, oid)] = (R, t)
            box = bbox_from_points(project_points(_keypoints(oid)[:8], K, R, t)).round().astype(int).tolist()
            vis = [0, 0, 0, 0] if hidden == (im, oid) else box
            gt[str(im)].append({"obj_id": oid, "cam_R_m2c": R.reshape(-1).tolist(), "cam_t_m2c": t.tolist()})
            gi[str(im)].append({"bbox_obj": box, "bbox_visib": vis, "px_count_all": 100, "px_count_valid": 100,
                                "px_count_visib": 0 if vis == [0, 0, 0, 0] else 90,
                                "visib_fract": 0.0 if vis == [0, 0, 0, 0] else 0.9})
        cam[str(im)] = {"cam_K": K.reshape(-1).tolist(), "depth_scale": 1.0}
    for name, d in (("scene_gt", gt), ("scene_gt_info", gi), ("scene_camera", cam)):
        (sdir / f"{name}.json").write_text(json.dumps(d))
    (root / "camera.json").write_text(json.dumps({"width": 320, "height": 240, "fx": K[0, 0], "fy": K[1, 1],
                                                  "cx": 160.0, "cy": 120.0, "depth_scale": 1.0}))
    return root, poses, K


class BoxKeyedKPD:
    """Finds the GT pose of each box (the oracle passes the GT boxes) and returns the exact projected
    keypoints of that pose, optionally offset in 3D (``offset[obj_id]`` mm) or broken (``nan_obj``)."""

    def __init__(self, root, poses, K, offset=None, nan_obj=None, sym=None, shrink=None):
        self.keypoints_3d = {o: _keypoints(o) for o in EXTENTS}
        self.by_box = {}
        for (_im, oid), (R, t) in poses.items():
            box = tuple(bbox_from_points(project_points(self.keypoints_3d[oid][:8], K, R, t)).round().astype(int))
            self.by_box[(oid, box)] = (R, t)
        self.K, self.offset, self.nan_obj, self.sym = K, offset or {}, nan_obj, sym or {}
        self.shrink = shrink or {}  # obj_id -> factor: the keypoints drawn towards their centroid
        self.calls = 0

    def predict_keypoints(self, images, boxes, image_index, obj_ids):
        self.calls += 1
        kps = []
        for box, oid in zip(boxes.cpu().numpy().round().astype(int), obj_ids.tolist()):
            R, t = self.by_box[(oid, tuple(box))]
            if oid in self.sym:  # the pose of GT composed with a symmetry S of the object: R S_R, R S_t + t
                S = self.sym[oid]
                R, t = R @ S[:3, :3], R @ S[:3, 3] + t
            uv = project_points(self.keypoints_3d[oid], self.K, R, t + np.asarray(self.offset.get(oid, [0, 0, 0.0])))
            uv = uv.mean(0) + self.shrink.get(oid, 1.0) * (uv - uv.mean(0))
            kps.append(np.full_like(uv, np.nan) if oid == self.nan_obj else uv)
        n = len(kps)
        return torch.tensor(np.stack(kps)), torch.ones(n, len(self.keypoints_3d[1]), dtype=torch.float64)


def _pipeline(kpd):
    return PosePipeline(DETECTORS.build("oracle"), kpd, pnp="epnp", top_l=None, device="cpu")


def test_perfect_predictions_write_all_outputs(tmp_path):
    root, poses, K = make_dataset(tmp_path / "ds")
    ds = BopDataset(root)
    out = tmp_path / "run"
    m = evaluate(_pipeline(BoxKeyedKPD(root, poses, K)), ds, out, oracle=True, batch_size=2, n_overlays=2,
                 progress=False)
    for name in ("metrics.json", "results.csv", "report.md", "accuracy_vs_px.png", "accuracy_vs_add.png",
                 "overlays/000001_000000.png", "overlays/000001_000001.png", "predictions.jsonl"):
        assert (out / name).is_file(), name
    assert m["mean"]["add_s_01d"] == 1.0 and m["mean"]["proj2d_5px"] == 1.0 and m["failures"] == 0
    assert m["mean"]["n"] == 6 and set(m["per_object"]) == {"1", "2"}
    assert m["bop19"]["ar_mssd"] == 1.0 and m["bop19"]["ar_mspd"] == 1.0
    assert m["fps"] > 0 and {"detect", "kpd", "pnp"} <= set(m["stage_seconds_per_frame"])
    assert json.loads((out / "metrics.json").read_text())["mean"]["add_s_01d"] == 1.0
    # results.csv is a valid BOP file that the scorer accepts on the dataset itself
    assert len(read_bop_results(out / "results.csv")) == 6
    s = score_bop19_file(out / "results.csv", root, targets_filename=str(out / "test_targets_bop19.json"))
    assert s["ar_mssd"] == 1.0
    report = (out / "report.md").read_text()
    assert "| **mean** | | 6 | **100.0** | **100.0** |" in report and "accuracy_vs_px.png" in report
    # the overlay shows the green GT box where the GT projects (and blue drawn over it)
    ov = cv2.cvtColor(cv2.imread(str(out / "overlays/000001_000000.png")), cv2.COLOR_BGR2RGB)
    assert (np.abs(ov.astype(int) - [30, 90, 255]).sum(-1) < 60).sum() > 100
    assert (np.abs(ov.astype(int) - [40, 40, 40]).sum(-1) == 0).mean() > 0.8


def test_oracle_targets_visible_or_full_boxes_by_hand():
    from kpd6d.data.dataset import Instance
    from kpd6d.evaluation.runner import oracle_targets

    eye = (np.eye(3), np.zeros(3))
    insts = [Instance(1, *eye, bbox_obj=np.array([-10, 20, 50, 40]), bbox_visib=np.array([5, 25, 20, 30])),
             Instance(2, *eye, bbox_obj=np.array([300, 200, 40, 60]), bbox_visib=np.array([300, 200, 20, 40])),
             Instance(5, *eye, bbox_obj=np.array([10, 10, 30, 30]), bbox_visib=np.array([0, 0, 0, 0]))]  # hidden
    vis = oracle_targets(None, insts)
    np.testing.assert_array_equal(vis["boxes"], [[5, 25, 20, 30], [300, 200, 20, 40]])
    assert vis["obj_ids"].tolist() == [1, 2]
    full = oracle_targets(None, insts, "bbox_obj", (320, 240))  # clipped: x 0..40, x 300..320, y 200..240
    np.testing.assert_array_equal(full["boxes"], [[0, 20, 40, 40], [300, 200, 20, 40]])
    assert full["obj_ids"].tolist() == [1, 2]
    with pytest.raises(ValueError, match="needs the image_size"):
        oracle_targets(None, insts, "bbox_obj")
    with pytest.raises(ValueError, match="must be one of"):
        oracle_targets(None, insts, "amodal", (320, 240))


def test_oracle_with_full_boxes_crops_the_whole_object(tmp_path):
    # the visible boxes are half the full ones (occluded objects); a KPD that knows poses only by their full
    # box is exact when the oracle gives full boxes, and is never asked about a visible one
    root, poses, K = make_dataset(tmp_path / "ds", n_frames=2)
    gi_path = root / "test" / "000001" / "scene_gt_info.json"
    gi = json.loads(gi_path.read_text())
    for entries in gi.values():
        for e in entries:
            x, y, w, h = e["bbox_obj"]
            e["bbox_visib"] = [x, y, w // 2, h]
    gi_path.write_text(json.dumps(gi))
    m = evaluate(_pipeline(BoxKeyedKPD(root, poses, K)), BopDataset(root), tmp_path / "run", oracle=True,
                 oracle_box="bbox_obj", progress=False, n_overlays=0)
    assert m["mean"]["add_s_01d"] == 1.0 and m["failures"] == 0 and m["mean"]["n"] == 4
    with pytest.raises(KeyError):  # the same KPD given the visible boxes has no pose for them
        evaluate(_pipeline(BoxKeyedKPD(root, poses, K)), BopDataset(root), tmp_path / "run_visib", oracle=True,
                 progress=False, n_overlays=0)


def test_known_translation_error_gives_known_curves(tmp_path):
    root, poses, K = make_dataset(tmp_path / "ds")
    d1 = float(np.linalg.norm(EXTENTS[1]))  # 103.92 mm
    off = 0.075 * d1  # ADD of a pure translation = its length, for every point
    m = evaluate(_pipeline(BoxKeyedKPD(root, poses, K, offset={1: [off, 0, 0]})), BopDataset(root), tmp_path / "r",
                 oracle=True, n_overlays=0, progress=False)
    o1, o2 = m["per_object"]["1"], m["per_object"]["2"]
    assert o1["add_s_01d"] == 1.0 and o2["add_s_01d"] == 1.0
    curve = np.asarray(o1["curves"]["add_s"])  # thresholds 0, 0.01, ..., 0.5
    assert curve[7] == 0.0 and curve[8] == 1.0  # 0.075 d is not < 0.07 d, but < 0.08 d
    assert o1["auc_add_s"] == pytest.approx((0.5 - 0.075) / 0.5, rel=1e-6)
    assert np.asarray(o2["curves"]["add_s"])[1] == 1.0
    # mean curve = mean of the object curves
    np.testing.assert_allclose(m["mean"]["curves"]["add_s"], (curve + np.asarray(o2["curves"]["add_s"])) / 2)


def test_symmetric_object_estimated_up_to_its_symmetry_is_correct_in_2d_too(tmp_path):
    """Object 2 (an 80x40x30 box) is symmetric under 180 deg about z; the KPD answers GT composed with
    that symmetry. ADD-S and the symmetric 2D projection error accept it; declared non-symmetric, both reject it."""
    S = np.diag([-1.0, -1.0, 1.0, 1.0])
    root, poses, K = make_dataset(tmp_path / "sym", symmetries={2: [S]})
    m = evaluate(_pipeline(BoxKeyedKPD(root, poses, K, sym={2: S})), BopDataset(root), tmp_path / "a", oracle=True,
                 n_overlays=0, progress=False)
    o2 = m["per_object"]["2"]
    assert o2["symmetric"] and o2["add_s_01d"] == 1.0 and o2["proj2d_5px"] == 1.0
    assert m["bop19"]["ar_mspd"] == 1.0
    assert "2D projection error minimised over its symmetries" in (tmp_path / "a" / "report.md").read_text()
    # the keypoint diagnostic compares with the symmetry of GT the keypoints were drawn at
    assert o2["keypoints"]["err_px"] < 0.01 and o2["keypoints"]["scale"] == pytest.approx(1.0, abs=1e-3)  # (stored to 0.01 px)
    root, poses, K = make_dataset(tmp_path / "plain")
    m = evaluate(_pipeline(BoxKeyedKPD(root, poses, K, sym={2: S})), BopDataset(root), tmp_path / "b", oracle=True,
                 n_overlays=0, progress=False)
    o2 = m["per_object"]["2"]
    assert not o2["symmetric"] and o2["add_s_01d"] == 0.0 and o2["proj2d_5px"] == 0.0
    assert m["per_object"]["1"]["proj2d_5px"] == 1.0


def test_depth_by_visibility_measures_a_known_depth_offset(tmp_path):
    """Object 1 estimated 90 mm farther along the optical axis, object 2 exact (both 90 % visible in make_dataset):
    the 0.80-0.95 band holds the six estimates' ratios, computed here from the GT depths; the others are empty."""
    from kpd6d.evaluation.runner import DEPTH_VISIBILITY_BANDS

    root, poses, K = make_dataset(tmp_path / "ds")
    m = evaluate(_pipeline(BoxKeyedKPD(root, poses, K, offset={1: [0.0, 0.0, 90.0]})), BopDataset(root),
                 tmp_path / "r", oracle=True, n_overlays=0, progress=False)
    want = np.array([(t[2] + 90.0) / t[2] if oid == 1 else 1.0 for (_im, oid), (_R, t) in poses.items()])
    bands = m["depth_by_visibility"]
    assert [(b["lo"], b["hi"]) for b in bands] == [tuple(map(float, b)) for b in DEPTH_VISIBILITY_BANDS]
    band = next(b for b in bands if b["lo"] == 0.8)
    assert band["n"] == 6 and sum(b["n"] for b in bands) == 6
    assert band["median"] == pytest.approx(np.median(want), rel=1e-6)
    assert band["q25"] == pytest.approx(np.percentile(want, 25), rel=1e-6)
    assert band["q75"] == pytest.approx(np.percentile(want, 75), rel=1e-6)
    assert band["within"] == 0.5  # object 2's three, not object 1's (~10 % too far)
    report = (tmp_path / "r" / "report.md").read_text()
    assert "Depth by visibility" in report and f"| 0.80–0.95 | 6 | {np.median(want):.3f}" in report


def test_undetected_and_failed_pnp_count_as_failures(tmp_path):
    root, poses, K = make_dataset(tmp_path / "ds", hidden=(1, 2))
    kpd = BoxKeyedKPD(root, poses, K, nan_obj=None)
    m = evaluate(_pipeline(kpd), BopDataset(root), tmp_path / "a", oracle=True, n_overlays=0, progress=False)
    assert m["per_object"]["2"]["n"] == 3 and m["per_object"]["2"]["failures"] == 1
    assert m["per_object"]["2"]["add_s_01d"] == pytest.approx(2 / 3)
    assert m["mean"]["add_s_01d"] == pytest.approx((1 + 2 / 3) / 2)
    # object 1's PnP fails everywhere (non-finite keypoints): all three are failures, none dropped
    kpd = BoxKeyedKPD(root, poses, K, nan_obj=1)
    m = evaluate(_pipeline(kpd), BopDataset(root), tmp_path / "b", oracle=True, n_overlays=0, progress=False)
    assert m["per_object"]["1"]["n"] == 3 and m["per_object"]["1"]["add_s_01d"] == 0.0
    assert m["failures"] == 4 and m["per_object"]["1"]["curves"]["proj2d"][-1] == 0.0
    # BOP19 does not count the hidden instance (visib_fract 0 < 0.1): 2 correct of 5 targets
    assert m["bop19"]["ar_mssd"] == pytest.approx(2 / 5) and m["bop19"]["n_targets"] == 5
    # missing estimates stay failures whatever part of a pose comes from the GT; the exact ones stay exact
    assert {k: v["ar_mssd"] for k, v in m["bop19"]["decomposition"].items()} == pytest.approx(
        {"estimated": 2 / 5, "depth": 2 / 5, "translation": 2 / 5, "rotation": 2 / 5})
    assert "| rotation from the GT | 40.0 | 40.0 |" in (tmp_path / "b" / "report.md").read_text()


def test_resume_skips_done_frames(tmp_path):
    root, poses, K = make_dataset(tmp_path / "ds", n_frames=4)
    out = tmp_path / "run"
    first = evaluate(_pipeline(BoxKeyedKPD(root, poses, K)), BopDataset(root), out, oracle=True, n_overlays=0,
                     progress=False, run_info={"pnp": "epnp", "device": "cpu"})
    lines = (out / "predictions.jsonl").read_text().splitlines()
    (out / "predictions.jsonl").write_text("\n".join(lines[:2]) + "\n" + lines[2][:20])  # cut mid-line
    kpd = BoxKeyedKPD(root, poses, K)
    again = evaluate(_pipeline(kpd), BopDataset(root), out, oracle=True, n_overlays=0, progress=False,
                     run_info={"pnp": "epnp", "device": "cuda"})  # another device is the same settings
    assert kpd.calls == 2  # frames 2 and 3 only (batch size 1)
    assert again["mean"] == first["mean"]
    # the same folder with other settings: an error naming them, and the predictions are kept
    with pytest.raises(ValueError, match=r"other settings \(pnp, top_l: pnp was 'epnp', now 'sqpnp'"):
        evaluate(_pipeline(BoxKeyedKPD(root, poses, K)), BopDataset(root), out, oracle=True, n_overlays=0,
                 progress=False, run_info={"pnp": "sqpnp", "top_l": 4})
    # every frame's record is intact, the cut line stays on a line of its own
    recs = (out / "predictions.jsonl").read_text().splitlines()
    assert len(recs) == 5 and sorted(json.loads(r)["im_id"] for r in recs if r != lines[2][:20]) == [0, 1, 2, 3]
    kpd = BoxKeyedKPD(root, poses, K)
    evaluate(_pipeline(kpd), BopDataset(root), out, oracle=True, n_overlays=0, progress=False, run_info={"pnp": "epnp"})
    assert kpd.calls == 0  # same settings: nothing redone


def _tiny_kpd_checkpoint(path):
    import pytorch_lightning as pl

    from kpd6d.kpd.module import KPDModule

    torch.manual_seed(0)
    m = KPDModule(obj_ids=[1, 2], keypoints_3d=[_keypoints(1), _keypoints(2)], diameters=[103.9, 94.3],
                  backbone={"name": "resnet18"}, head={"name": "deconv", "deconv_channels": 32}, input_size=64,
                  out_stride=4)
    trainer = pl.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, default_root_dir=path.parent)
    trainer.strategy.connect(m)
    trainer.save_checkpoint(path)
    return path


def test_kpd6d_evaluate_cli_with_a_real_untrained_kpd(tmp_path, monkeypatch, capsys):
    import sys

    from kpd6d.cli.evaluate import main

    root, _, _ = make_dataset(tmp_path / "ds", n_frames=2)
    ckpt = _tiny_kpd_checkpoint(tmp_path / "kpd.ckpt")
    out = tmp_path / "run"
    monkeypatch.setattr(sys, "argv", ["kpd6d-evaluate", f"data.root={root}", f"kpd_ckpt={ckpt}", "detector_ckpt=oracle",
                                      "device=cpu", "progress=false", "overlays=1", "pnp=epnp_ransac", "select.top_l=20",
                                      "crop_tta={crops:3,stability:0.1}", "refiner=region", "refiner.scales=[0.2,0.1]", f"hydra.run.dir={out}"])
    main()
    m = json.loads((out / "metrics.json").read_text())
    # the region refiner on the dataset's own meshes, recorded with its settings; each pose says if it moved
    assert m["run"]["refiner"]["name"] == "region" and m["run"]["refiner"]["scales"] == [0.2, 0.1]
    preds = [p for line in (out / "predictions.jsonl").read_text().splitlines() for p in json.loads(line)["preds"]]
    assert preds and all("refined" in p for p in preds if p["ok"])
    assert m["mean"]["n"] == 4  # every instance evaluated, however bad the untrained KPD is
    assert m["run"]["pnp"]["name"] == "epnp_ransac" and m["run"]["top_l"] == 20 and m["run"]["device"] == "cpu"
    assert m["run"]["crop_tta"] == {"crops": 3, "stability": 0.1}
    assert "- crop_tta: `{'crops': 3, 'stability': 0.1}`" in (out / "report.md").read_text()
    for name in ("results.csv", "report.md", "accuracy_vs_px.png", "accuracy_vs_add.png", "overlays/000001_000000.png"):
        assert (out / name).is_file(), name
    assert "wrote" in capsys.readouterr().out


def test_projection_accuracy_at_5_10_15_px_and_report_columns(tmp_path):
    from kpd6d.evaluation.report import write_report_md
    from kpd6d.evaluation.runner import compute_metrics

    recs = [{"obj_id": 1, "add": 1.0, "proj": p} for p in (3.0, 7.0, 12.0, 20.0)]
    recs += [{"obj_id": 2, "add": 1.0, "proj": p} for p in (9.9, float("inf"))]
    m = compute_metrics(recs, {1: 100.0, 2: 50.0})
    o1, o2 = m["per_object"]["1"], m["per_object"]["2"]
    assert (o1["proj2d_5px"], o1["proj2d_10px"], o1["proj2d_15px"]) == (0.25, 0.5, 0.75)
    assert (o2["proj2d_5px"], o2["proj2d_10px"], o2["proj2d_15px"]) == (0.0, 0.5, 0.5)
    assert m["mean"]["proj2d_15px"] == pytest.approx(0.625)
    text = write_report_md(m, tmp_path / "report.md").read_text()
    assert "| 10 px (%) | 15 px (%) |" in text and "| 75.0 | " in text


def test_keypoint_diagnostic_measures_drawn_in_keypoints(tmp_path):
    """Object 1's keypoints are the GT projections drawn in to 0.8 of their spread about their centroid:
    the diagnostic reports that scale, its median distance (found independently here), and object 2 exact."""
    root, poses, K = make_dataset(tmp_path / "ds", n_frames=2)
    m = evaluate(_pipeline(BoxKeyedKPD(root, poses, K, shrink={1: 0.8})), BopDataset(root), tmp_path / "r",
                 oracle=True, n_overlays=0, progress=False)
    k1, k2 = m["per_object"]["1"]["keypoints"], m["per_object"]["2"]["keypoints"]
    assert k1["n"] == 2 and k1["scale"] == pytest.approx(0.8, abs=1e-3) and k1["centroid_px"] < 0.02
    expect = []
    for im in range(2):
        R, t = poses[(im, 1)]
        uv = project_points(_keypoints(1), K, R, t)
        expect.append(np.median(0.2 * np.linalg.norm(uv - uv.mean(0), axis=1)))
    assert k1["err_px"] == pytest.approx(np.median(expect), abs=0.02)  # (predictions are stored to 0.01 px)
    assert k2["scale"] == pytest.approx(1.0, abs=1e-3) and k2["err_px"] < 0.01
    assert m["mean"]["keypoints"]["scale"] == pytest.approx(0.9, abs=1e-3) and m["mean"]["keypoints"]["n"] == 4
    report = (tmp_path / "r" / "report.md").read_text()
    assert "Keypoints against the ground truth" in report and "| 0.800 |" in report


class DepthScalingRefiner:
    """A stand-in refiner that moves object 2 to ``factor`` times its depth (object 1 stays) and records the
    poses it was given."""

    def __init__(self, factor):
        self.factor, self.seen = factor, []

    def refine_poses(self, images, Ks, poses):
        for plist in poses:
            for p in plist:
                self.seen.append((p["obj_id"], np.array(p["t"], float)))
                if p["obj_id"] == 2:
                    p["t"] = np.asarray(p["t"], float) * self.factor
                p["refined"] = p["obj_id"] == 2
        return poses


def test_refiner_ceiling_scores_the_gt_poses_refined_in_their_images(tmp_path):
    root, poses, K = make_dataset(tmp_path / "ds")
    pipe = _pipeline(BoxKeyedKPD(root, poses, K))
    ref = DepthScalingRefiner(1.1)
    pipe.set_refiner(ref)
    m = evaluate(pipe, BopDataset(root), tmp_path / "a", oracle=True, n_overlays=0, progress=False, refiner_ceiling=True)
    dec = m["bop19"]["decomposition"]
    # object 2 10 % too far (90 mm, about its 94 mm diameter): wrong at every MSSD threshold; object 1 exact
    assert dec["gt_refined"]["ar_mssd"] == pytest.approx(3 / 6) and dec["estimated"]["ar_mssd"] == pytest.approx(3 / 6)
    assert 0.5 <= dec["gt_refined"]["ar_mspd"] < 1.0
    # the refiner was given the GT translations (after the pipeline's own estimates: 6 of those, then 6 GT poses)
    gt_seen = ref.seen[6:]
    assert len(gt_seen) == 6 and all(np.allclose(t, poses[(i // 2, o)][1]) for i, (o, t) in enumerate(gt_seen))
    assert "| the GT pose, refined (the refiner's ceiling) | 50.0 |" in (tmp_path / "a" / "report.md").read_text()
    # off by default, and without a refiner nothing is refined
    m = evaluate(pipe, BopDataset(root), tmp_path / "b", oracle=True, n_overlays=0, progress=False)
    assert "gt_refined" not in m["bop19"]["decomposition"]
    plain = _pipeline(BoxKeyedKPD(root, poses, K))
    m = evaluate(plain, BopDataset(root), tmp_path / "c", oracle=True, n_overlays=0, progress=False, refiner_ceiling=True)
    assert "gt_refined" not in m["bop19"]["decomposition"] and m["bop19"]["ar_mssd"] == 1.0
