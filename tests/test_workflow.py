"""kpd6d-run / kpd6d.workflow: the whole method on a tiny procedural setting, and its resume."""

from __future__ import annotations

import json

import pytest
from hydra import compose, initialize_config_dir

from kpd6d.config import config_dir

TINY = [
    "experiment=demo", "objects.obj_ids=[1]", "designator.num_keypoints=8",
    "data.num_train=8", "data.num_val=2", "data.num_test=3", "data.workers=1",
    "+data.options.width=160", "+data.options.height=120", "evaluate.overlays=1", "progress=false",
    "detector=centernet_tiny", "detector.input_size=[128,96]", "detector_stage.trainer.max_time=null",
    "detector_recipe@detector_stage=fast", "detector_stage.trainer.max_epochs=1", "detector_stage.batch_size=4",
    "detector_stage.trainer.precision=32-true",
    "backbone@kpd_stage.backbone=tiny", "kpd_stage.kpd.codec.input_size=32", "kpd_stage.kpd.num_workers=0",
    "kpd_stage.kpd.batch_size=4", "kpd_stage.kpd.trainer.max_time=null", "kpd_stage.kpd.trainer.max_epochs=1",
    "kpd_stage.kpd.trainer.precision=32-true", "kpd_stage.kpd.scheduler=null",
]


def _cfg(extra=()):
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return compose("run", overrides=[*TINY, *extra])


@pytest.mark.slow
def test_run_experiment_end_to_end_then_resumes(tmp_path):
    from kpd6d.workflow import run_experiment

    run = tmp_path / "run"
    m = run_experiment(_cfg(), run)
    for f in ("keypoints.json", "detector/detector.pt", "kpd/metrics.json", "eval/metrics.json", "eval/results.csv",
              "eval/report.md", "eval/accuracy_vs_px.png", "metrics.json"):
        assert (run / f).is_file(), f
    assert sorted((run / "data").iterdir()) == [run / "data" / n for n in
                                                 ("camera.json", "dataset_info.json", "models", "test", "train", "val")]
    # every test instance is scored (none dropped): 3 test images with one object each
    assert m["mean"]["n"] == 3
    saved = json.loads((run / "metrics.json").read_text())
    assert saved["run"]["config"]["designator"]["num_keypoints"] == 8
    assert set(saved["run"]["timings"]) >= {"prepare_s", "detector_s", "kpd_s", "evaluate_s", "total_s"}

    # a rerun in the same folder reuses every stage's output
    stamps = {f: (run / f).stat().st_mtime_ns for f in ("keypoints.json", "detector/detector.pt", "kpd/metrics.json")}
    m2 = run_experiment(_cfg(), run)
    assert {f: (run / f).stat().st_mtime_ns for f in stamps} == stamps
    assert m2["mean"]["n"] == 3
    # ... and its stage times add up over both invocations (the skipped stages keep theirs): timings.json
    t1, t2 = saved["run"]["timings"], m2["run"]["timings"]
    assert t2["detector_s"] >= t1["detector_s"] > 0 and t2["kpd_s"] >= t1["kpd_s"] > 0
    assert t2["total_s"] == pytest.approx(sum(v for k, v in t2.items() if k not in ("total_s", "invocation_s")))
    assert t2["invocation_s"] < t2["total_s"]
    assert json.loads((run / "timings.json").read_text())["kpd_s"] == pytest.approx(t2["kpd_s"])


def test_designator_change_redesignates(tmp_path):
    from kpd6d.keypoints import read_keypoint_file
    from kpd6d.objects import procedural_objects
    from kpd6d.workflow import designate_keypoints as designate

    models = procedural_objects(obj_ids=[1])
    f = tmp_path / "keypoints.json"
    fps = designate(models, {"name": "fps", "num_keypoints": 6}, f)
    assert fps[1].shape == (6, 3)
    assert designate(models, {"name": "fps", "num_keypoints": 6}, f)[1].tolist() == fps[1].tolist()
    box = designate(models, {"name": "bbox_corners", "num_keypoints": 9}, f)
    assert box[1].shape == (9, 3) and read_keypoint_file(f).designator == "bbox_corners"
    # per-object overrides are applied and recorded
    per = designate(models, {"name": "fps", "num_keypoints": 6}, f, per_object={1: {"num_keypoints": 4}})
    assert per[1].shape == (4, 3) and read_keypoint_file(f).params["per_object"] == {"1": {"num_keypoints": 4}}


@pytest.mark.slow
def test_kpd6d_run_cli(tmp_path, monkeypatch, capsys):
    """The Hydra entry point the README's demo uses (kpd6d-demo = kpd6d-run experiment=demo)."""
    import sys

    from kpd6d.cli import demo

    out = tmp_path / "demo"
    monkeypatch.setattr(sys, "argv", ["kpd6d-demo", *TINY[1:], "detector_ckpt=oracle", f"hydra.run.dir={out}"])
    demo.main()
    printed = capsys.readouterr().out
    assert f"report: {out}/eval/report.md" in printed and "2D projection 5px" in printed
    assert (out / "eval" / "report.md").is_file() and not (out / "detector").exists()
    assert json.loads((out / "metrics.json").read_text())["run"]["config"]["objects"]["obj_ids"] == [1]


@pytest.mark.slow
def test_evaluation_on_another_dataset_with_oracle_boxes_too(tmp_path):
    """evaluate.data_root scores on a separate BOP dataset (as the real LM-O frames are), and
    evaluate.oracle adds a second evaluation with ground-truth boxes."""
    from kpd6d.synth import generate_dataset
    from kpd6d.workflow import run_experiment

    other = tmp_path / "other"
    generate_dataset(other, obj_ids=[1], num_images=2, split="test", seed=99, workers=1, width=160, height=120)
    run = tmp_path / "run"
    amodal = ["detector_stage.box=bbox_obj", "evaluate.oracle_box=bbox_obj"]  # the detector and the oracle on full boxes
    with pytest.raises(ValueError, match=r"evaluate\.oracle_box='amodal': must be one of bbox_visib, bbox_obj"):
        run_experiment(_cfg(["evaluate.oracle_box=amodal"]), tmp_path / "bad")
    assert not (tmp_path / "bad" / "data").exists()  # stopped before any data is made
    m = run_experiment(_cfg(["data.num_test=0", f"evaluate.data_root={other}", "evaluate.oracle=true", *amodal]), run)
    assert not (run / "data" / "test").exists()  # nothing generated for testing
    assert m["mean"]["n"] == 2 and m["oracle_boxes"]["mean"]["n"] == 2
    oracle = json.loads((run / "eval_oracle" / "metrics.json").read_text())
    assert oracle["run"]["detector"] == "oracle" and oracle["run"]["dataset"] == str(other)
    assert oracle["run"]["oracle_box"] == "bbox_obj"
    from kpd6d.detection import load_detector

    assert load_detector(run / "detector" / "detector.pt").box_field == "bbox_obj"
    assert json.loads((run / "eval" / "metrics.json").read_text())["run"]["dataset"] == str(other)


@pytest.mark.slow
def test_yardsticks_evaluate_the_runs_val_split_and_a_generated_one(tmp_path):
    """evaluate.yardsticks: the run's own val split and a split generated with the run's data options
    updated by the yardstick's (here: fixed lighting, seed 7), each evaluated with the own detector and
    with GT boxes into yardsticks/<name>/; the scores reach metrics.json; a rerun resumes them."""
    from kpd6d.workflow import run_experiment

    extra = ["evaluate.oracle=true", "+evaluate.yardsticks.val.split=val",
             "+evaluate.yardsticks.shifted={num_images: 2, seed: 7, options: {lighting: fixed}}"]
    run = tmp_path / "run"
    m = run_experiment(_cfg(extra), run)
    assert set(m["yardsticks"]) == {"val", "shifted"}
    shifted = run / "yardsticks" / "shifted" / "data"
    assert m["yardsticks"]["val"]["root"] == str(run / "data") and m["yardsticks"]["shifted"]["root"] == str(shifted)
    assert len(list((shifted / "val" / "000000" / "rgb").iterdir())) == 2
    info = json.loads((shifted / "dataset_info.json").read_text())["splits"]["val"]
    assert info["seed"] == 7 and info["config"]["lighting"] == "fixed"
    assert info["config"]["width"] == 160  # the run's own data options, updated by the yardstick's
    assert json.loads((run / "data" / "dataset_info.json").read_text())["splits"]["val"]["config"]["lighting"] != "fixed"
    for name, root in (("val", run / "data"), ("shifted", shifted)):
        for ev, det in (("eval", str(run / "detector" / "detector.pt")), ("eval_oracle", "oracle")):
            saved = json.loads((run / "yardsticks" / name / ev / "metrics.json").read_text())
            assert saved["run"]["dataset"] == str(root) and saved["run"]["split"] == "val"
            assert saved["run"]["detector"] == det
            who = "own" if ev == "eval" else "oracle"
            assert m["yardsticks"][name][who]["ar_mssd"] == saved["mean"]["ar_mssd"]
    # the val yardstick is the val split itself: 2 images, one object each
    assert json.loads((run / "yardsticks" / "val" / "eval_oracle" / "metrics.json").read_text())["mean"]["n"] == 2
    assert set(json.loads((run / "metrics.json").read_text())["yardsticks"]) == {"val", "shifted"}
    stamp = (shifted / "val" / "000000" / "scene_gt.json").stat().st_mtime_ns
    assert run_experiment(_cfg(extra), run)["yardsticks"] == m["yardsticks"]  # resumed: same predictions
    assert (shifted / "val" / "000000" / "scene_gt.json").stat().st_mtime_ns == stamp


def test_yardstick_specs_are_checked(tmp_path):
    """Bad yardstick specs stop with a message naming the key; a null spec switches one off."""
    from kpd6d.config import ConfigError
    from kpd6d.workflow import yardstick_splits

    (tmp_path / "data" / "val").mkdir(parents=True)
    root = tmp_path / "data"
    cases = [("+evaluate.yardsticks.a={spit: val}", "unknown key\\(s\\) \\['spit'\\]; known: split, root"),
             ("+evaluate.yardsticks.a={num_images: 2, split: val}", "either num_images"),
             ("+evaluate.yardsticks.a={split: test}", "evaluate.yardsticks.a: split 'test' not found"),
             ("+evaluate.yardsticks.a={seed: 3}", "seed and options need num_images"),
             ("+evaluate.yardsticks.a={num_images: 0}", "num_images must be > 0"),
             ("+evaluate.yardsticks.a=7", "must be a mapping")]
    for override, message in cases:
        with pytest.raises(ConfigError, match=message):
            yardstick_splits(_cfg([override]), tmp_path, root)
    assert yardstick_splits(_cfg(["+evaluate.yardsticks.a=null", "+evaluate.yardsticks.b.split=val"]), tmp_path,
                            root) == {"b": (root, "val")}


LMO_TINY = [
    "experiment=lmo", "objects.obj_ids=[1,5]", "designator.num_keypoints=8", "data.num_train=6", "data.num_val=2",
    "data.workers=1", "+data.options.width=160", "+data.options.height=120", "data.options.objects_per_image=[1,2]",
    "evaluate.max_frames=2", "evaluate.overlays=1", "progress=false",
    "detector.input_size=[128,96]", "detector_stage.trainer.max_time=null",
    "detector_recipe@detector_stage=fast", "detector_stage.trainer.max_epochs=1", "detector_stage.batch_size=4",
    "detector_stage.trainer.precision=32-true",
    "backbone@kpd_stage.backbone=tiny", "kpd_stage.kpd.codec.input_size=32", "kpd_stage.kpd.num_workers=0",
    "kpd_stage.kpd.batch_size=4", "kpd_stage.kpd.trainer.max_time=null", "kpd_stage.kpd.trainer.max_epochs=1",
    "kpd_stage.kpd.scheduler=null", "evaluate.yardsticks.heldout_style.num_images=2",
]


@pytest.mark.slow
@pytest.mark.lmo
def test_lmo_recipe_composes_and_runs_end_to_end_on_tiny_sizes(tmp_path, lmo_dir):
    """experiment=lmo: SIFT keypoints on the real meshes, table-top training scenes, the pretrained
    detector, evaluation on the real frames with the own detector and with ground-truth boxes."""
    from kpd6d.workflow import run_experiment

    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        full = compose("run", overrides=["experiment=lmo", f"objects.models_dir={lmo_dir / 'models'}",
                                         f"evaluate.data_root={lmo_dir}"])
        cfg = compose("run", overrides=[*LMO_TINY, f"objects.models_dir={lmo_dir / 'models'}",
                                        f"evaluate.data_root={lmo_dir}", "evaluate.detector_overrides.score_threshold=0.05",
                                        "evaluate.detector_overrides.test_scales=[1,1.5]"])
    # the recipe itself: 8 objects, 50 SIFT keypoints (17 on the eggbox), table-top scenes, pretrained backbones
    assert full.objects.obj_ids == [1, 5, 6, 8, 9, 10, 11, 12] and full.designator.name == "sift"
    assert full.designator.num_keypoints == 50 and full.designator_per_object[10].symmetry_aware
    assert full.data.options.layout == "tabletop" and full.data.num_test == 0
    assert full.detector.backbone == "efficientnet_lite0" and full.detector.backbone_pretrained == "imagenet"
    assert full.kpd_stage.backbone.name == "efficientnet_lite2" and full.evaluate.oracle
    # inference settings chosen on synthetic validation: RANSAC + SQPnP refit on all keypoints, depth calibration
    assert full.pnp.name == "sqpnp_ransac" and full.pnp.relative_error == 0.2
    assert full.select.top_l is None and full.evaluate.depth_calibration == "auto"
    assert full.evaluate.candidates == {"per_object": 5, "verify_crops": 1} and full.detector.one_per_object
    assert full.evaluate.detector_overrides.test_scales is None
    assert full.data.options.palette == "natural" and full.data.options.distractor_refresh == 100
    assert full.data.options.photometric == {"exposure": [0.7, 2.5], "saturation": [0.8, 1.5]}
    assert full.kpd_stage.kpd.finetune.freeze_stages == 2 and not full.kpd_stage.kpd.finetune.freeze_bn
    assert full.evaluate.refiner.name == "region" and full.evaluate.refiner.prior_rotation == 0.02
    # the synthetic yardsticks: the run's val split and the held-out-style split (appearance training never sees)
    assert full.evaluate.yardsticks.val == {"split": "val"} and full.evaluate.yardsticks.heldout_style.seed == 7
    shift = full.evaluate.yardsticks.heldout_style.options
    assert shift.lighting != full.data.options.lighting and shift.palette != full.data.options.palette

    run = tmp_path / "run"
    m = run_experiment(cfg, run)
    info = json.loads((run / "data" / "dataset_info.json").read_text())
    assert info["splits"]["train"]["config"]["layout"] == "tabletop"
    assert info["splits"]["train"]["config"]["photometric"]["exposure"] == [0.7, 2.5]  # the camera reached the generator
    for f in ("eval/results.csv", "eval/report.md", "eval_oracle/results.csv", "eval_oracle/report.md"):
        assert (run / f).is_file(), f
    assert m["mean"]["n"] > 0 and m["oracle_boxes"]["mean"]["n"] > 0
    # the detector's inference override reaches the evaluation with the own detector (not the oracle's)
    assert json.loads((run / "eval" / "settings.json").read_text())["detector_overrides"] == {
        "score_threshold": 0.05, "test_scales": [1.0, 1.5]}
    assert "detector_overrides" not in json.loads((run / "eval_oracle" / "settings.json").read_text())
    assert 0.0 <= m["mean"]["ar_mspd"] <= 1.0
    # the detector's own AP on the real frames, per object, in metrics.json and the report
    assert set(m["detector"]["ap50_per_object"]) <= {1, 5} and m["detector"]["images"] == 2
    assert "Detector on the same frames (2 images" in (run / "eval" / "report.md").read_text()
    assert "detector" not in json.loads((run / "eval_oracle" / "metrics.json").read_text())
    assert json.loads((run / "eval" / "metrics.json").read_text())["run"]["dataset"] == str(lmo_dir)
    # evaluate.depth_calibration=auto: fitted on the generated val split (with the own detector), then
    # applied to both real-frame evaluations; the record says whether pairs were found (a tiny
    # untrained KPD may have none: then it keeps 1.0 and gives the reason)
    cal = run / "calibration" / "depth_calibration.json"
    rec = json.loads(cal.read_text())
    assert rec["global"] > 0 and (rec["fitted"] or "could be paired" in rec["reason"])
    assert json.loads((run / "calibration" / "metrics.json").read_text())["run"]["split"] == "val"
    for ev in ("eval", "eval_oracle"):
        assert json.loads((run / ev / "metrics.json").read_text())["run"]["depth_calibration"] == str(cal)
        # both real-frame evaluations refine with the region refiner on the dataset's meshes; the depth
        # calibration is fitted on the PnP poses (no refiner there)
        assert json.loads((run / ev / "settings.json").read_text())["refiner"]["name"] == "region"
        assert "- refiner: `{'name': 'region'" in (run / ev / "report.md").read_text()
    assert "refiner" not in json.loads((run / "calibration" / "settings.json").read_text())
    # the yardsticks, evaluated as the real frames are (refiner, depth calibration), with both box sources
    assert set(m["yardsticks"]) == {"val", "heldout_style"}
    held = json.loads((run / "yardsticks" / "heldout_style" / "data" / "dataset_info.json").read_text())["splits"]["val"]
    assert held["config"]["lighting"] == "random" and held["config"]["layout"] == "tabletop"
    for name in ("val", "heldout_style"):
        for ev in ("eval", "eval_oracle"):
            rec = json.loads((run / "yardsticks" / name / ev / "settings.json").read_text())
            assert rec["refiner"]["name"] == "region" and rec["depth_calibration"] == str(cal)


@pytest.mark.slow
def test_per_object_kpd_networks_train_evaluate_and_resume(tmp_path):
    """kpd_networks=per_object: one KPD per object (each covering only its object), a manifest the
    pipeline loads as one KPD, each box answered by its own object's network."""
    import numpy as np
    import torch

    from kpd6d.kpd.ensemble import KPDEnsemble, load_kpd, read_manifest
    from kpd6d.kpd.module import KPDModule
    from kpd6d.workflow import _split_max_time, run_experiment

    run = tmp_path / "run"
    cfg = _cfg(["objects.obj_ids=[1,2]", "kpd_networks=per_object", "detector_ckpt=oracle"])
    m = run_experiment(cfg, run)
    manifest = run / "kpd" / "networks.json"
    members = read_manifest(manifest)
    assert sorted(members) == [1, 2]
    for o, ck in members.items():
        assert ck == (run / "kpd" / f"obj_{o:06d}" / "checkpoints" / "best.ckpt").resolve()
        assert KPDModule.load_checkpoint(ck).obj_ids == [o]
    assert m["mean"]["n"] == 3 and json.loads((run / "eval" / "metrics.json").read_text())["run"]["kpd"] == str(manifest)

    ens = load_kpd(manifest)
    assert isinstance(ens, KPDEnsemble) and sorted(ens.keypoints_3d) == [1, 2]
    g = torch.Generator().manual_seed(0)
    images = torch.rand(2, 3, 120, 160, generator=g)
    boxes = torch.tensor([[10.0, 20, 50, 40], [60, 30, 40, 50], [30, 10, 60, 60]])
    idx, obj = torch.tensor([0, 1, 1]), torch.tensor([2, 1, 2])
    kp, conf = ens.predict_keypoints(images, boxes, idx, obj)
    for i in range(3):  # the same as the object's own network on that box alone (batching: ~1e-3 px)
        own = KPDModule.load_checkpoint(members[int(obj[i])])
        kp_i, c_i = own.predict_keypoints(images, boxes[i:i + 1], idx[i:i + 1], obj[i:i + 1])
        torch.testing.assert_close(kp[i], kp_i[0].float(), atol=1e-2, rtol=0)
        torch.testing.assert_close(conf[i], c_i[0].float(), atol=1e-3, rtol=0)
    from kpd6d.predict import corners_from_kpd  # kpd6d-predict's drawn boxes: each object's surface points

    for o, corners in corners_from_kpd(ens).items():
        pts = KPDModule.load_checkpoint(members[o]).surface_points(o)
        np.testing.assert_allclose(corners.min(0), pts.min(0))
        np.testing.assert_allclose(corners.max(0), pts.max(0))
        assert corners.shape == (8, 3)
    with pytest.raises(KeyError, match=r"do not cover object 3; they cover \[1, 2\]"):
        ens.predict_keypoints(images, boxes[:1], idx[:1], torch.tensor([3]))

    # a rerun reuses the networks; the time budget is split between the objects
    stamp = manifest.stat().st_mtime_ns
    run_experiment(cfg, run)
    assert manifest.stat().st_mtime_ns == stamp
    assert _split_max_time("00:01:00:00", 8) == "00:00:07:30" and _split_max_time(None, 8) is None


def test_kpd_networks_manifest_errors(tmp_path):
    from kpd6d.config import ConfigError
    from kpd6d.kpd.ensemble import load_kpd, read_manifest, write_manifest
    from kpd6d.workflow import train_kpd_stage

    bad = tmp_path / "networks.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match=r"networks\.json.*not valid JSON"):
        read_manifest(bad)
    bad.write_text(json.dumps({"members": {"1": "a.ckpt"}}))
    with pytest.raises(ValueError, match="not a KPD networks manifest"):
        read_manifest(bad)
    write_manifest(bad, {1: tmp_path / "obj_000001" / "best.ckpt"})
    assert json.loads(bad.read_text())["members"] == {"1": "obj_000001/best.ckpt"}
    with pytest.raises(FileNotFoundError, match=r"networks.json', object 1: KPD checkpoint .*obj_000001/best.ckpt"):
        load_kpd(bad)
    from kpd6d.deploy.export import export_models

    with pytest.raises(ValueError, match=r"is a networks manifest .*export takes one KPD checkpoint"):
        export_models(bad, "oracle", tmp_path / "export")
    with pytest.raises(ConfigError, match="kpd_networks='each' unknown; known: shared, per_object"):
        train_kpd_stage(_cfg(["kpd_networks=each"]), tmp_path / "kpd", tmp_path, tmp_path / "k.json")


def test_kpd_checkpoint_picks_best_or_last_and_names_bad_values(tmp_path):
    """kpd_checkpoint: the run evaluates the KPD's best.ckpt (default) or last.ckpt; when the chosen one is
    missing, the other; an unknown name stops kpd6d-run before anything is made, listing the known ones."""
    from kpd6d.config import ConfigError
    from kpd6d.workflow import _train_one_kpd, run_experiment

    kpd = tmp_path / "kpd"
    (kpd / "checkpoints").mkdir(parents=True)
    (kpd / "metrics.json").write_text("{}")  # a finished KPD stage: nothing is trained again
    for name in ("best", "last"):
        (kpd / "checkpoints" / f"{name}.ckpt").write_text(name)
    args = (tmp_path, tmp_path / "k.json", [1])
    assert _train_one_kpd(_cfg(), kpd, *args) == str(kpd / "checkpoints" / "best.ckpt")
    assert _train_one_kpd(_cfg(["kpd_checkpoint=last"]), kpd, *args) == str(kpd / "checkpoints" / "last.ckpt")
    (kpd / "checkpoints" / "last.ckpt").unlink()
    assert _train_one_kpd(_cfg(["kpd_checkpoint=last"]), kpd, *args) == str(kpd / "checkpoints" / "best.ckpt")
    with pytest.raises(ConfigError, match="kpd_checkpoint='final' unknown; known: best, last"):
        run_experiment(_cfg(["kpd_checkpoint=final"]), tmp_path / "run")
    assert not (tmp_path / "run").exists()
