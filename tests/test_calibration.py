"""Depth calibration (kpd6d.evaluation.calibration, ``depth_calibration`` of the pose pipelines):
the fit recovers a known depth bias from a BOP results file, leaves out estimates of the wrong
place, composes with a factor already applied, and its record is what the pipelines read."""

from __future__ import annotations

import json

import numpy as np
import pytest

from kpd6d.data.bop_io import save_scene_camera, save_scene_gt, save_scene_gt_info
from kpd6d.evaluation.calibration import fit_depth_calibration, write_depth_calibration
from kpd6d.evaluation.results_io import PoseResult, write_bop_results
from kpd6d.geometry import LINEMOD_K, random_rotation
from kpd6d.pnp.estimator import parse_depth_calibration

DIAMETERS = {1: 100.0, 5: 200.0}
BIAS = {1: 1.10, 5: 1.05}  # the estimator's translations are this much too long


def _dataset(root, rng, n_images=12):
    """A BOP split 'val' with objects 1 and 5 in every image (visible), 1 once more but 5 % visible."""
    gt, cam, info = {}, {}, {}
    for im in range(n_images):
        gt[im] = [{"obj_id": 1, "R": random_rotation(rng), "t": np.array([rng.uniform(-150, 0), rng.uniform(-100, 100), rng.uniform(600, 1100)])},
                  {"obj_id": 5, "R": random_rotation(rng), "t": np.array([rng.uniform(50, 200), rng.uniform(-100, 100), rng.uniform(600, 1100)])},
                  {"obj_id": 1, "R": random_rotation(rng), "t": np.array([200.0, 150.0, 900.0])}]
        cam[im] = {"K": LINEMOD_K}
        info[im] = [{"bbox_obj": [0, 0, 1, 1], "bbox_visib": [0, 0, 1, 1], "px_count_visib": 1, "visib_fract": v}
                    for v in (0.8, 0.6, 0.05)]
    sd = root / "val" / "000000"
    save_scene_gt(sd / "scene_gt.json", gt)
    save_scene_camera(sd / "scene_camera.json", cam)
    save_scene_gt_info(sd / "scene_gt_info.json", info)
    (root / "models").mkdir(parents=True)
    (root / "models" / "models_info.json").write_text(json.dumps({str(k): {"diameter": d} for k, d in DIAMETERS.items()}))
    return gt


def _estimates(gt, rng, bias, noise=0.01):
    out = []
    for im, insts in gt.items():
        for inst in insts[:2]:
            s = bias[inst["obj_id"]] * (1 + rng.normal(0, noise))
            out.append(PoseResult(0, im, inst["obj_id"], 1.0, inst["R"], s * inst["t"]))
    return out


def test_fit_recovers_a_known_depth_bias_per_object(tmp_path):
    rng = np.random.default_rng(0)
    gt = _dataset(tmp_path, rng)
    results = _estimates(gt, rng, BIAS)
    # wild estimates: far from every instance of their object (skipped), and one behind the camera
    results.append(PoseResult(0, 0, 1, 1.0, np.eye(3), np.array([3000.0, 2000.0, 5000.0])))
    results.append(PoseResult(0, 1, 5, 1.0, np.eye(3), np.array([0.0, 0.0, -800.0])))
    csv = write_bop_results(tmp_path / "results.csv", results)
    fit = fit_depth_calibration(csv, tmp_path, "val", per_object=True, min_instances=10)
    for oid, b in BIAS.items():
        assert fit["per_object"][oid] == pytest.approx(1 / b, rel=0.01)  # t_gt = t_est / bias
        assert fit["instances"][oid] == 12
        lo, hi = fit["iqr"][oid]
        assert lo <= fit["per_object"][oid] <= hi
    assert 1 / BIAS[1] <= fit["global"] <= 1 / BIAS[5]
    # fewer pairs than min_instances: no factor of its own, the global one serves
    assert fit_depth_calibration(csv, tmp_path, "val", per_object=True, min_instances=13)["per_object"] == {}
    # by default one factor for all objects; the per-object medians are reported all the same
    one = fit_depth_calibration(csv, tmp_path, "val")
    assert one["per_object"] == {} and one["global"] == fit["global"]
    assert one["median_per_object"] == pytest.approx(fit["per_object"])
    # estimates made with a factor applied: the fit stays absolute
    applied = {1: 0.5, "default": 2.0}
    scaled = [PoseResult(r.scene_id, r.im_id, r.obj_id, r.score, r.R, r.t * (0.5 if r.obj_id == 1 else 2.0))
              for r in _estimates(gt, np.random.default_rng(0), BIAS, noise=0.0)]
    fit2 = fit_depth_calibration(scaled, tmp_path, "val", per_object=True, applied=applied)
    for oid, b in BIAS.items():
        assert fit2["per_object"][oid] == pytest.approx(1 / b, rel=1e-9)
    # the record is what the pipelines read
    path = write_depth_calibration(fit2, tmp_path / "depth_calibration.json")
    default, per = parse_depth_calibration(str(path))
    assert default == pytest.approx(fit2["global"]) and per == pytest.approx({1: 1 / BIAS[1], 5: 1 / BIAS[5]})


def test_fit_errors_name_what_is_wrong(tmp_path):
    rng = np.random.default_rng(1)
    gt = _dataset(tmp_path, rng, n_images=2)
    with pytest.raises(ValueError, match=r"no estimate .* could be paired"):
        fit_depth_calibration([PoseResult(9, 0, 1, 1.0, np.eye(3), np.array([0.0, 0.0, 800.0]))], tmp_path, "val")
    with pytest.raises(ValueError, match="no diameter for object 7"):
        fit_depth_calibration([PoseResult(0, 0, 7, 1.0, np.eye(3), gt[0][0]["t"])], tmp_path, "val")
    (tmp_path / "models" / "models_info.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"models_info\.json"):
        fit_depth_calibration(_estimates(gt, rng, BIAS), tmp_path, "val")


def test_parse_depth_calibration_forms_and_bad_values(tmp_path):
    assert parse_depth_calibration(None) == (1.0, {})
    assert parse_depth_calibration(0.9) == (0.9, {})
    assert parse_depth_calibration("0.9") == (0.9, {})
    assert parse_depth_calibration({"1": 0.9, "default": 0.95}) == (0.95, {1: 0.9})
    assert parse_depth_calibration({"global": 0.93, "per_object": {"5": 0.91}, "instances": {}}) == (0.93, {5: 0.91})
    for bad, named in ((0, "depth_calibration"), (-1.0, "depth_calibration"), (float("nan"), "depth_calibration"),
                       ({"1": "x"}, r"depth_calibration\[1\]"), ({"ape": 0.9}, "object ids"),
                       (str(tmp_path / "none.json"), "none.json does not exist")):
        with pytest.raises(ValueError, match=named):
            parse_depth_calibration(bad)
    broken = tmp_path / "broken.json"
    broken.write_text("{")
    with pytest.raises(ValueError, match=r"broken\.json cannot be read as JSON"):
        parse_depth_calibration(str(broken))
    neg = tmp_path / "neg.json"
    neg.write_text(json.dumps({"global": 1.0, "per_object": {"3": -0.5}}))
    with pytest.raises(ValueError, match=r"neg.json: depth_calibration\[3\] must be a number > 0"):
        parse_depth_calibration(neg)


def test_evaluate_fit_then_apply_removes_a_depth_bias(tmp_path, monkeypatch):
    """kpd6d-evaluate's path (run_evaluation): a KPD whose keypoints are those of the object 10 %
    farther away; fit_depth_calibration=true writes depth_calibration.json (1 / 1.1 per object);
    evaluating again with depth_calibration=<that file> gives exact poses (ADD 100 %, from < 100 %)."""
    from hydra import compose, initialize_config_dir

    import kpd6d.pipeline as pipeline_mod
    from kpd6d.geometry import project_points
    from kpd6d.paths import config_dir
    from kpd6d.registry import DETECTORS
    from kpd6d.workflow import run_evaluation
    from test_evaluate import BoxKeyedKPD, make_dataset

    class FartherKPD(BoxKeyedKPD):
        def predict_keypoints(self, images, boxes, image_index, obj_ids):
            import torch

            kps = []
            for box, oid in zip(boxes.cpu().numpy().round().astype(int), obj_ids.tolist()):
                R, t = self.by_box[(oid, tuple(box))]
                kps.append(project_points(self.keypoints_3d[oid], self.K, R, 1.1 * t))
            return torch.tensor(np.stack(kps)), torch.ones(len(kps), len(self.keypoints_3d[1]), dtype=torch.float64)

    root, poses, K = make_dataset(tmp_path / "ds", n_frames=6)
    seen = {}

    def for_backend(backend="torch", *, detector_ckpt, kpd_ckpt=None, export_dir=None, **kw):
        seen.update(kw)
        return pipeline_mod.PosePipeline(DETECTORS.build("oracle"), FartherKPD(root, poses, K), pnp="epnp",
                                         top_l=None, device="cpu", depth_calibration=kw["depth_calibration"])

    monkeypatch.setattr(pipeline_mod.PosePipeline, "for_backend", staticmethod(for_backend))
    base = [f"data.root={root}", "kpd_ckpt=unused.ckpt", "detector_ckpt=oracle", "progress=false", "overlays=0"]
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        fit_cfg = compose("evaluate", overrides=[*base, "fit_depth_calibration=true"])
        m_raw = run_evaluation(fit_cfg, tmp_path / "fit")
        cal = tmp_path / "fit" / "depth_calibration.json"
        fit = json.loads(cal.read_text())
        assert fit["instances"] == {"1": 6, "2": 6}  # JSON keys
        assert fit["per_object"] == {} and fit["global"] == pytest.approx(1 / 1.1, rel=1e-6)
        for s in fit["median_per_object"].values():
            assert s == pytest.approx(1 / 1.1, rel=1e-6)
        m_cal = run_evaluation(compose("evaluate", overrides=[*base, f"depth_calibration={cal}"]), tmp_path / "cal")
    assert seen["depth_calibration"] == str(cal)
    assert m_raw["mean"]["add_s_01d"] < 0.5 and m_cal["mean"]["add_s_01d"] == 1.0
    assert m_cal["run"]["depth_calibration"] == str(cal)
    assert f"depth_calibration: `{cal}`" in (tmp_path / "cal" / "report.md").read_text()
