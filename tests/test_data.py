"""BOP I/O (kpd6d.data): writer -> reader round trip, the real LM-O frames, error messages."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from kpd6d.data import (
    BopDataset,
    BopFormatError,
    atomic_write_bytes,
    bbox_from_mask,
    load_camera,
    load_scene_camera,
    load_scene_gt,
    load_scene_gt_info,
    save_camera,
    save_scene_camera,
    save_scene_gt,
    save_scene_gt_info,
)
from kpd6d.geometry import LINEMOD_K, project_points, random_rotation
from synth_helpers import SMALL, write_models


def _write_scene(sd: Path, rng, n_images=3, with_info=True):
    gt, cam, info = {}, {}, {}
    for im in range(n_images):
        gt[im] = [{"obj_id": int(o), "R": random_rotation(rng), "t": rng.uniform(-100, 900, 3)} for o in (1, 5, 1)]
        cam[im] = {"K": LINEMOD_K * (1 + im), "depth_scale": 0.1}
        info[im] = [{"bbox_obj": [1, 2, 3, 4], "bbox_visib": [1, 2, 3, 3], "px_count_all": 12, "px_count_valid": 11,
                     "px_count_visib": 9, "visib_fract": 0.75} for _ in gt[im]]
    save_scene_gt(sd / "scene_gt.json", gt)
    save_scene_camera(sd / "scene_camera.json", cam)
    if with_info:
        save_scene_gt_info(sd / "scene_gt_info.json", info)
    return gt, cam, info


def test_json_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    sd = tmp_path / "train" / "000003"
    gt, cam, _ = _write_scene(sd, rng)
    gt2 = load_scene_gt(sd / "scene_gt.json")
    cam2 = load_scene_camera(sd / "scene_camera.json")
    info2 = load_scene_gt_info(sd / "scene_gt_info.json")
    assert sorted(gt2) == [0, 1, 2]
    for im in gt:
        for a, b in zip(gt[im], gt2[im]):
            assert a["obj_id"] == b["obj_id"]
            np.testing.assert_array_equal(a["R"], b["R"])  # floats survive JSON exactly
            np.testing.assert_array_equal(a["t"], b["t"])
        np.testing.assert_array_equal(cam2[im]["K"], cam[im]["K"])
        assert cam2[im]["depth_scale"] == 0.1
        assert info2[im][0]["px_count_valid"] == 11 and info2[im][0]["visib_fract"] == 0.75
    # BOP's on-disk form: row-major 9 floats, string image keys
    raw = json.loads((sd / "scene_gt.json").read_text())
    np.testing.assert_array_equal(np.reshape(raw["1"][0]["cam_R_m2c"], (3, 3)), gt[1][0]["R"])
    save_camera(tmp_path / "camera.json", LINEMOD_K, 640, 480, 0.1)
    c = load_camera(tmp_path / "camera.json")
    np.testing.assert_array_equal(c["K"], LINEMOD_K)
    assert (c["width"], c["height"], c["depth_scale"]) == (640, 480, 0.1)


def test_dataset_reader_on_written_files(tmp_path):
    rng = np.random.default_rng(1)
    gt, cam, _ = _write_scene(tmp_path / "val" / "000000", rng, n_images=2)
    _write_scene(tmp_path / "val" / "000001", rng, n_images=1, with_info=False)
    ds = BopDataset(tmp_path, "val")
    assert len(ds) == 3 and ds.scene_ids == [0, 1]
    f = ds[1]
    assert (f.scene_id, f.im_id) == (0, 1)
    np.testing.assert_array_equal(f.K, cam[1]["K"])
    assert [i.gt_index for i in f.instances] == [0, 1, 2]
    np.testing.assert_array_equal(f.instances[2].R, gt[1][2]["R"])
    assert f.instances[0].visib_fract == 0.75 and list(f.instances[0].bbox_visib) == [1, 2, 3, 3]
    assert ds[2].instances[0].bbox_obj is None  # no scene_gt_info.json in scene 1
    only5 = BopDataset(tmp_path, "val", obj_ids=[5])
    assert [[i.gt_index for i in f.instances] for f in only5] == [[1], [1], [1]]
    assert BopDataset(tmp_path, "val", obj_ids=[7]).frames == []


def test_targets_restrict_frames_and_instances(tmp_path):
    rng = np.random.default_rng(2)
    _write_scene(tmp_path / "test" / "000002", rng, n_images=3)
    targets = [{"scene_id": 2, "im_id": 1, "obj_id": 1, "inst_count": 2},
               {"scene_id": 2, "im_id": 2, "obj_id": 5, "inst_count": 1}]
    (tmp_path / "test_targets_bop19.json").write_text(json.dumps(targets))
    ds = BopDataset(tmp_path, "test", targets="test_targets_bop19.json")
    assert [(f.im_id, f.targets) for f in ds] == [(1, {1: 2}), (2, {5: 1})]
    assert [i.gt_index for i in ds[0].instances] == [0, 2]
    (tmp_path / "bad.json").write_text(json.dumps([*targets, {"scene_id": 2, "im_id": 9, "obj_id": 1, "inst_count": 1}]))
    with pytest.raises(BopFormatError, match=r"bad.json.*\(2, 9\)"):
        BopDataset(tmp_path, "test", targets=tmp_path / "bad.json")


def test_round_trip_generated_dataset(tmp_path, monkeypatch):
    from kpd6d.synth import generate_dataset

    models = write_models(tmp_path / "m")
    root = generate_dataset(tmp_path / "d", models, num_images=3, progress=False, **SMALL)
    ds = BopDataset(root, "train")
    assert len(ds) == 3
    f = ds[2]
    assert f.load_rgb().shape == (120, 160, 3) and f.load_rgb().dtype == np.uint8
    m = f.load_mask_visib(0)
    assert m.dtype == bool and m.sum() == f.instances[0].px_count_visib
    assert {mm.obj_id for mm in ds.load_models()} == {1, 2}
    assert ds.camera["width"] == 160
    # meshes are read once per dataset (the evaluation's metrics and the refiner share them), and not pickled
    import pickle

    import kpd6d.objects as objects

    calls = []
    real = objects.load_bop_models
    monkeypatch.setattr(objects, "load_bop_models", lambda *a, **k: calls.append(a) or real(*a, **k))
    first = ds.load_models([2])
    assert [m.obj_id for m in first] == [2] and ds.load_models([2])[0] is first[0] and len(calls) == 1
    assert pickle.loads(pickle.dumps(ds))._models == {} and ds._models


def test_bbox_from_mask():
    m = np.zeros((10, 12), bool)
    assert bbox_from_mask(m) == [-1, -1, -1, -1]
    m[2:5, 3:9] = True
    assert bbox_from_mask(m) == [3, 2, 5, 2]  # bop_toolkit: w = x_max - x_min


def test_atomic_write_leaves_no_partial_file(tmp_path, monkeypatch):
    import os

    atomic_write_bytes(tmp_path / "perm.bin", b"x")
    mask = os.umask(0)
    os.umask(mask)
    assert (tmp_path / "perm.bin").stat().st_mode & 0o777 == 0o666 & ~mask  # not mkstemp's 0600
    (tmp_path / "perm.bin").unlink()

    target = tmp_path / "x.json"
    target.write_text("old")

    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        atomic_write_bytes(target, b"new")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["x.json"]


# ---------------------------------------------------------------------------------------------
# the real LM-O data
# ---------------------------------------------------------------------------------------------
@pytest.mark.lmo
def test_reads_lmo_test_frames(lmo_dir):
    ds = BopDataset(lmo_dir, "test", targets="test_targets_bop19.json")
    assert len(ds) == 40
    assert sum(sum(f.targets.values()) for f in ds) == 285
    assert sum(len(f.instances) for f in ds) == 285
    f = ds[0]
    np.testing.assert_allclose(f.K, LINEMOD_K)
    img = f.load_rgb()
    assert img.shape == (480, 640, 3) and img.dtype == np.uint8 and img.std() > 10
    with pytest.raises(FileNotFoundError, match=r"mask_visib/000003_000000.png"):
        f.load_mask_visib(0)  # this copy ships no masks


@pytest.mark.lmo
def test_lmo_bbox_obj_agrees_with_projected_models(lmo_dir, lmo_model_by_id):
    """BOP's published bbox_obj (bop_toolkit's renderer) is the pixel box of the projected model with
    pixel centres at +0.5 (ceil(u_min - 0.5) .. floor(u_max - 0.5)), within 1 px: a real-data check
    of the box convention (ours puts pixel centres at integers -- see docs/data.md)."""
    ds = BopDataset(lmo_dir, "test")
    n, exact = 0, 0
    for f in ds:
        for inst in f.instances:
            if inst.px_count_visib == 0:
                assert list(inst.bbox_obj) == [-1, -1, -1, -1]
                continue
            uv = project_points(lmo_model_by_id[inst.obj_id].vertices, f.K, inst.R, inst.t) - 0.5
            lo, hi = np.ceil(uv.min(0)), np.floor(uv.max(0))
            x, y, w, h = inst.bbox_obj
            d = np.abs(np.array([x - lo[0], y - lo[1], x + w - hi[0], y + h - hi[1]]))
            assert d.max() <= 1, (f.im_id, inst.obj_id, d)
            n += 1
            exact += d.max() == 0
    assert exact >= 0.8 * n
    assert n > 250


@pytest.mark.lmo
def test_reads_annotation_only_copy(shared_data):
    root = shared_data / "bop_reference" / "lmo_full"
    ds = BopDataset(root, "test", targets=root / "test_targets_bop19.json", models_dir=root / "models_eval")
    assert len(ds) == 200
    assert sum(len(f.instances) for f in ds) == sum(sum(f.targets.values()) for f in ds)
    with pytest.raises(FileNotFoundError, match=r"rgb/\d{6}\.png: image file does not exist"):
        ds[0].load_rgb()
    assert {m.obj_id for m in ds.load_models([1, 5])} == {1, 5}


# ---------------------------------------------------------------------------------------------
# errors name the file and the field
# ---------------------------------------------------------------------------------------------
def test_malformed_files_are_named(tmp_path):
    sd = tmp_path / "test" / "000000"
    sd.mkdir(parents=True)
    (sd / "scene_gt.json").write_text("{not json")
    with pytest.raises(BopFormatError, match=r"scene_gt.json: invalid JSON"):
        BopDataset(tmp_path)
    (sd / "scene_gt.json").write_text(json.dumps({"0": [{"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "obj_id": 1}]}))
    with pytest.raises(BopFormatError, match=r"scene_gt.json: image 0 instance 0 has no field 'cam_t_m2c'"):
        BopDataset(tmp_path)
    (sd / "scene_gt.json").write_text(json.dumps({"0": [{"cam_R_m2c": [1, 0, 0], "cam_t_m2c": [0, 0, 1], "obj_id": 1}]}))
    with pytest.raises(BopFormatError, match=r"'cam_R_m2c' has 3 values, expected 9"):
        BopDataset(tmp_path)
    (sd / "scene_gt.json").write_text(json.dumps({"0": [{"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1],
                                                         "cam_t_m2c": [0, 0, 1], "obj_id": 1}]}))
    with pytest.raises(BopFormatError, match=r"scene_camera.json: scene_camera.json does not exist"):
        BopDataset(tmp_path)
    (sd / "scene_camera.json").write_text(json.dumps({"0": {"depth_scale": 1.0}}))
    with pytest.raises(BopFormatError, match=r"scene_camera.json: image 0 has no field 'cam_K'"):
        BopDataset(tmp_path)
    (sd / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": LINEMOD_K.ravel().tolist()}}))
    (sd / "scene_gt_info.json").write_text(json.dumps({"0": [{"bbox_obj": [0, 0, 1, 1]}]}))
    with pytest.raises(BopFormatError, match=r"scene_gt_info.json: image 0 instance 0 has no field 'bbox_visib'"):
        BopDataset(tmp_path)
    (sd / "scene_gt_info.json").unlink()
    ds = BopDataset(tmp_path)
    (sd / "rgb").mkdir()
    (sd / "rgb" / "000000.png").write_bytes(b"garbage")
    ds = BopDataset(tmp_path)
    with pytest.raises(OSError, match=r"rgb/000000.png: cannot be read as an image"):
        ds[0].load_rgb()
    with pytest.raises(FileNotFoundError, match=r"split 'train' does not exist; splits found: \['test'\]"):
        BopDataset(tmp_path, "train")
    with pytest.raises(FileNotFoundError, match="targets file does not exist"):
        BopDataset(tmp_path, targets="nope.json")


def test_keypoints_missing_is_named(tmp_path):
    rng = np.random.default_rng(3)
    _write_scene(tmp_path / "test" / "000000", rng, n_images=1)
    with pytest.raises(FileNotFoundError, match=r"models/keypoints.json: keypoints file does not exist"):
        BopDataset(tmp_path).load_keypoints()
