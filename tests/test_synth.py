"""Synthetic data engine: ground-truth consistency, determinism, resume, options and errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from kpd6d.data import BopDataset, load_scene_gt
from kpd6d.geometry import project_points, view_from_pose
from kpd6d.synth import SynthConfig, default_K, generate_dataset
from synth_helpers import SMALL, tree_bytes, write_models

# ---------------------------------------------------------------------------------------------
# fixtures
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def models_dir(tmp_path_factory) -> Path:
    return write_models(tmp_path_factory.mktemp("models"))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, models_dir) -> Path:
    """14 images in scenes of 5, 1-2 objects and 0-2 occluders each, with depth."""
    root = tmp_path_factory.mktemp("synth")
    generate_dataset(root, models_dir, num_images=14, seed=7, progress=False, objects_per_image=(1, 2),
                     distractors=(0, 2), scene_size=5, depth=True, visib_fract_range=(0.2, 1.0), **SMALL)
    return root


def _rasterize(model, K, R, t, width, height, pad=0):
    """Independent silhouette: pixel centres (integer coordinates) inside any projected triangle
    (edge-function test per triangle), on a canvas enlarged by ``pad`` px on each side."""
    uv = project_points(model.vertices, K, R, t) + pad
    canvas = np.zeros((height + 2 * pad, width + 2 * pad), bool)
    for a, b, c in uv[model.faces]:
        lo = np.maximum(np.ceil(np.minimum(np.minimum(a, b), c)), 0).astype(int)
        hi = np.minimum(np.floor(np.maximum(np.maximum(a, b), c)), [canvas.shape[1] - 1, canvas.shape[0] - 1]).astype(int)
        if (hi < lo).any():
            continue
        ys, xs = np.mgrid[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1]
        p = np.stack([xs, ys], -1).astype(float)

        def edge(p0, p1, p=p):
            return (p1[0] - p0[0]) * (p[..., 1] - p0[1]) - (p1[1] - p0[1]) * (p[..., 0] - p0[0])

        e = np.stack([edge(a, b), edge(b, c), edge(c, a)])
        inside = (e >= 0).all(0) | (e <= 0).all(0)
        canvas[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1] |= inside
    return canvas


# ---------------------------------------------------------------------------------------------
# ground-truth consistency on generated data
# ---------------------------------------------------------------------------------------------
def test_layout_and_files(dataset):
    scenes = sorted(p.name for p in (dataset / "train").iterdir())
    assert scenes == ["000000", "000001", "000002"]  # 14 images, scenes of 5
    gt = load_scene_gt(dataset / "train" / "000002" / "scene_gt.json")
    assert sorted(gt) == [0, 1, 2, 3]
    for name in ("camera.json", "dataset_info.json", "models/models_info.json", "models/obj_000001.ply",
                 "models/obj_000002.ply", "train/000000/rgb/000004.jpg", "train/000000/depth/000004.png",
                 "train/000000/mask_visib/000004_000000.png"):
        assert (dataset / name).is_file(), name
    assert not list(dataset.rglob("*.tmp"))
    cam = json.loads((dataset / "camera.json").read_text())
    assert (cam["width"], cam["height"]) == (160, 120)
    np.testing.assert_allclose(cam["fx"], 572.4114 / 4)


def test_unoccluded_silhouette_matches_mask_visib(dataset):
    ds = BopDataset(dataset, "train")
    models = {m.obj_id: m for m in ds.load_models()}
    checked = 0
    for f in ds:
        for inst in f.instances:
            if inst.px_count_visib != inst.px_count_all or inst.px_count_all < 30:
                continue
            mask = f.load_mask_visib(inst.gt_index)
            sil = _rasterize(models[inst.obj_id], f.K, inst.R, inst.t, 160, 120)
            iou = (mask & sil).sum() / (mask | sil).sum()
            assert iou >= 0.95, (f.scene_id, f.im_id, inst.gt_index, iou)
            checked += 1
    assert checked >= 5


def test_bbox_obj_matches_projected_vertices(dataset):
    ds = BopDataset(dataset, "train")
    models = {m.obj_id: m for m in ds.load_models()}
    n = 0
    for f in ds:
        for inst in f.instances:
            uv = project_points(models[inst.obj_id].vertices, f.K, inst.R, inst.t)
            x, y, w, h = inst.bbox_obj
            lo, hi = uv.min(0), uv.max(0)
            assert abs(x - lo[0]) <= 1 and abs(y - lo[1]) <= 1
            assert abs(x + w - hi[0]) <= 1 and abs(y + h - hi[1]) <= 1
            n += 1
    assert n >= 14


def test_counts_and_visible_fraction_agree_with_masks(dataset):
    ds = BopDataset(dataset, "train")
    models = {m.obj_id: m for m in ds.load_models()}
    occluded = 0
    for f in ds:
        for inst in f.instances:
            mask = f.load_mask_visib(inst.gt_index)
            assert inst.px_count_visib == mask.sum()
            ys, xs = np.nonzero(mask)
            assert list(inst.bbox_visib) == [xs.min(), ys.min(), xs.max() - xs.min(), ys.max() - ys.min()]
            assert inst.visib_fract == pytest.approx(inst.px_count_visib / inst.px_count_all)
            assert 0.2 - 1e-9 <= inst.visib_fract <= 1.0
            # px_count_all against an independent rasterization (whole silhouette, also off-image)
            sil = _rasterize(models[inst.obj_id], f.K, inst.R, inst.t, 160, 120, pad=100)
            assert abs(int(sil.sum()) - inst.px_count_all) <= 0.01 * inst.px_count_all + 2
            inside = sil[100:-100, 100:-100].sum()
            assert abs(int(inside) - inst.px_count_valid) <= 0.01 * inst.px_count_valid + 2
            # visible pixels lie in the silhouette
            assert (mask & ~sil[100:-100, 100:-100]).sum() <= 0.01 * mask.sum() + 2
            occluded += inst.visib_fract < 0.98
    assert occluded >= 2  # the occluders did occlude


def test_depth_matches_pose(dataset):
    ds = BopDataset(dataset, "train")
    models = {m.obj_id: m for m in ds.load_models()}
    for f in ds[:5]:
        depth = f.load_depth()
        assert f.depth_scale == pytest.approx(0.1)
        for inst in f.instances:
            mask = f.load_mask_visib(inst.gt_index)
            z = depth[mask]
            pts_c = models[inst.obj_id].vertices @ inst.R.T + inst.t
            assert (z > 0).all()
            assert z.min() >= pts_c[:, 2].min() - 1.0 and z.max() <= pts_c[:, 2].max() + 1.0


def test_poses_within_ranges(dataset):
    ds = BopDataset(dataset, "train")
    for f in ds:
        for inst in f.instances:
            assert 180.0 - 40 <= inst.t[2] <= 400.0 + 40  # box centre at the sampled distance (+- object size)
            np.testing.assert_allclose(inst.R @ inst.R.T, np.eye(3), atol=1e-9)
            assert np.linalg.det(inst.R) == pytest.approx(1.0)


def test_view_sampler_respects_ranges():
    from kpd6d.synth.poses import ViewRanges, sample_view_rotation

    rng = np.random.default_rng(0)
    ranges = ViewRanges((500, 600), (10.0, 40.0), (30.0, 90.0), (0.0, 0.0))
    for _ in range(200):
        R = sample_view_rotation(rng, ranges)
        az, el, _ = view_from_pose(R, np.array([0.0, 0.0, 1000.0]))
        assert 10.0 - 1e-6 <= math.degrees(el) <= 40.0 + 1e-6
        assert 30.0 - 1e-6 <= math.degrees(az) % 360 <= 90.0 + 1e-6


def test_objects_kept_in_view():
    from kpd6d.synth.poses import ModelGeometry, ViewRanges, projected_box, sample_object_pose

    class M:
        vertices = np.array([[x, y, z] for x in (-40, 40) for y in (-30, 30) for z in (-20, 20)], float)

    g = ModelGeometry(M())
    K = default_K(160, 120)
    rng = np.random.default_rng(1)
    for _ in range(100):
        R, t = sample_object_pose(rng, g, K, 160, 120, ViewRanges(distance=(300, 500)), view_margin=0.0)
        x, y, w, h = projected_box(g, K, R, t)[0]
        assert x >= 0 and y >= 0 and x + w <= 159 and y + h <= 119


def test_symmetric_poses_are_canonical(dataset):
    from kpd6d.symmetry import handler_for_model

    ds = BopDataset(dataset, "train", obj_ids=[2])
    handler = handler_for_model(ds.load_models()[0])
    assert len(ds) >= 2
    for f in ds:
        for inst in f.instances:
            R2, t2 = handler.canonicalize(inst.R, inst.t)
            np.testing.assert_allclose(R2, inst.R, atol=1e-6)
            np.testing.assert_allclose(t2, inst.t, atol=1e-4)


def test_default_K_scales_linemod():
    K = default_K(640, 480)
    from kpd6d.geometry import LINEMOD_K

    np.testing.assert_allclose(K, LINEMOD_K)
    # a point seen at pixel (u, v) at 640x480 is seen at ((u + .5) / 4 - .5, ...) at 160x120
    X = np.array([[30.0, -20.0, 700.0]])
    uv_big = project_points(X, LINEMOD_K)
    uv_small = project_points(X, default_K(160, 120))
    np.testing.assert_allclose(uv_small, (uv_big + 0.5) / 4 - 0.5)


# ---------------------------------------------------------------------------------------------
# determinism and resume
# ---------------------------------------------------------------------------------------------
_RUN = dict(num_images=6, seed=3, progress=False, distractors=(1, 1), scene_size=4, **SMALL)


@pytest.fixture(scope="module")
def reference(tmp_path_factory, models_dir) -> dict[str, bytes]:
    root = tmp_path_factory.mktemp("ref")
    generate_dataset(root, models_dir, **_RUN)
    return tree_bytes(root)


def test_same_seed_same_bytes_other_seed_differs(tmp_path, models_dir, reference):
    generate_dataset(tmp_path / "a", models_dir, **_RUN)
    assert tree_bytes(tmp_path / "a") == reference
    generate_dataset(tmp_path / "b", models_dir, **{**_RUN, "seed": 4})
    other = tree_bytes(tmp_path / "b")
    assert other["train/000000/rgb/000000.jpg"] != reference["train/000000/rgb/000000.jpg"]
    assert other["train/000000/scene_gt.json"] != reference["train/000000/scene_gt.json"]


def test_resume_after_lost_files_and_unrecorded_images(tmp_path, models_dir, reference):
    root = tmp_path / "r"
    generate_dataset(root, models_dir, **_RUN)
    sd = root / "train" / "000000"
    (sd / "rgb" / "000001.jpg").unlink()  # an image file lost
    (sd / "mask_visib" / "000002_000000.png").unlink()
    gt = json.loads((sd / "scene_gt.json").read_text())  # an image not yet recorded
    del gt["3"]
    (sd / "scene_gt.json").write_text(json.dumps(gt))
    (sd / "rgb" / ".000003.jpg.abc.tmp").write_bytes(b"half-written")  # debris of a killed writer
    generate_dataset(root, models_dir, **_RUN)
    assert tree_bytes(root) == reference


def test_resume_after_interruption(tmp_path, models_dir, reference, monkeypatch):
    import kpd6d.synth.generate as gen

    real = gen._make_image
    calls = {"n": 0}

    def flaky(index):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        return real(index)

    monkeypatch.setattr(gen, "_make_image", flaky)
    root = tmp_path / "i"
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(root, models_dir, **_RUN)
    done = load_scene_gt(root / "train" / "000000" / "scene_gt.json")
    assert sorted(done) == [0, 1, 2]  # the finished images were recorded before stopping
    monkeypatch.setattr(gen, "_make_image", real)
    generate_dataset(root, models_dir, **_RUN)
    assert tree_bytes(root) == reference


@pytest.mark.slow
def test_killed_run_resumes_and_workers_do_not_change_result(tmp_path, models_dir, reference):
    """A run with 2 worker processes is SIGKILLed mid-way; the rerun finishes it, and the result is
    the bytes of the single-process reference."""
    import signal
    import subprocess
    import sys
    import time

    root = tmp_path / "k"
    code = (
        f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        "from synth_helpers import SMALL\n"
        "from kpd6d.synth import generate_dataset\n"
        "if __name__ == '__main__':\n"
        f"    generate_dataset({str(root)!r}, {str(models_dir)!r}, workers=2, num_images=120, seed=3, progress=False,"
        " distractors=(1, 1), scene_size=4, **SMALL)\n"
    )
    script = tmp_path / "run.py"
    script.write_text(code)
    proc = subprocess.Popen([sys.executable, str(script)], start_new_session=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(list(root.glob("train/*/scene_gt.json"))) < 3:
        time.sleep(0.2)
    import os

    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    n_done = sum(len(load_scene_gt(p)) for p in root.glob("train/*/scene_gt.json"))
    assert 0 < n_done < 120
    generate_dataset(root, models_dir, workers=2, **{**_RUN, "num_images": 120})
    got = tree_bytes(root)
    # the first 6 images are the single-process reference's, byte for byte (scene 0 whole, JSON included)
    compared = [n for n in reference if n.startswith(("train/000000/", "train/000001/rgb/", "train/000001/mask_visib/"))]
    assert len(compared) > 12
    for name in compared:
        assert got[name] == reference[name], name
    ds = BopDataset(root, "train")
    assert len(ds) == 120
    assert not list(root.rglob("*.tmp"))


def test_resume_refuses_other_settings(tmp_path, models_dir):
    generate_dataset(tmp_path, models_dir, **{**_RUN, "num_images": 1})
    with pytest.raises(ValueError, match=r"different settings \(config\)"):
        generate_dataset(tmp_path, models_dir, **{**_RUN, "num_images": 1, "feather_sigma": 0.0})
    with pytest.raises(ValueError, match="seed"):
        generate_dataset(tmp_path, models_dir, **{**_RUN, "num_images": 1, "seed": 5})
    # more images with the same settings extend the split
    generate_dataset(tmp_path, models_dir, **{**_RUN, "num_images": 2})
    assert len(BopDataset(tmp_path, "train")) == 2


# ---------------------------------------------------------------------------------------------
# options
# ---------------------------------------------------------------------------------------------
def test_all_objects_png_no_photometric(tmp_path, models_dir):
    generate_dataset(tmp_path, models_dir, num_images=2, progress=False, objects_per_image="all", distractors=(0, 0),
                     rgb_format="png", photometric={"prob": 0.0}, **SMALL)
    ds = BopDataset(tmp_path, "train")
    assert [sorted(i.obj_id for i in f.instances) for f in ds] == [[1, 2], [1, 2]]
    assert ds[0].rgb_path.suffix == ".png"
    assert ds[0].load_rgb().shape == (120, 160, 3)


def test_backgrounds_folder_is_used(tmp_path, models_dir):
    import cv2

    bgs = tmp_path / "bgs"
    (bgs / "sub").mkdir(parents=True)
    cv2.imwrite(str(bgs / "sub" / "red.png"), np.full((50, 90, 3), (0, 0, 255), np.uint8))  # BGR red
    generate_dataset(tmp_path / "d", models_dir, num_images=2, progress=False, distractors=(0, 0),
                     backgrounds_dir=str(bgs), photometric={"prob": 0.0}, feather_sigma=0.0, rgb_format="png", **SMALL)
    f = BopDataset(tmp_path / "d", "train")[0]
    rgb = f.load_rgb()
    bg = ~f.load_mask_visib(0)
    assert (rgb[bg] == [255, 0, 0]).all()
    obj = rgb[~bg]
    assert not (obj == [255, 0, 0]).all(axis=1).all()


def test_procedural_objects_are_the_default(tmp_path):
    generate_dataset(tmp_path, None, obj_ids=[1, 2], num_images=2, progress=False, distractors=(0, 0),
                     **{**SMALL, "distance_range": (300.0, 500.0)})
    ds = BopDataset(tmp_path, "train")
    assert sorted(p.name for p in (tmp_path / "models").glob("*.ply")) == ["obj_000001.ply", "obj_000002.ply"]
    assert {i.obj_id for f in ds for i in f.instances} <= {1, 2}
    models = ds.load_models()
    from kpd6d.objects import procedural_objects

    ref = {m.obj_id: m for m in procedural_objects(obj_ids=[1, 2])}
    for m in models:
        np.testing.assert_allclose(m.vertices, ref[m.obj_id].vertices, atol=1e-3)  # PLY stores float32


def test_photometric_effects():
    from kpd6d.synth.photometric import PhotometricConfig, apply_photometric

    img = np.random.default_rng(0).integers(0, 256, (40, 50, 3), dtype=np.uint8)
    assert apply_photometric(img, np.random.default_rng(0), PhotometricConfig(prob=0.0)) is img
    out = apply_photometric(img, np.random.default_rng(0), PhotometricConfig(prob=1.0))
    assert out.shape == img.shape and out.dtype == np.uint8 and not np.array_equal(out, img)
    with pytest.raises(ValueError, match="unknown option"):
        PhotometricConfig.from_mapping({"blurr": 1})


def test_camera_exposure_and_saturation_against_direct_formulas():
    from kpd6d.synth.photometric import (
        PhotometricConfig,
        _log_uniform,
        apply_photometric,
        camera_exposure_saturation,
    )

    img = np.random.default_rng(1).integers(0, 256, (30, 40, 3), dtype=np.uint8)
    assert camera_exposure_saturation(img) is img
    # exposure: linear light x e, through the 2.2 power curve both ways, clipped at white
    x = img.astype(np.float64) / 255
    want = np.clip((x ** 2.2 * 2.0) ** (1 / 2.2), 0, 1) * 255
    got = camera_exposure_saturation(img, exposure=2.0)
    assert np.abs(got - want).max() <= 0.5 + 1e-6 and (got[img >= 200] == 255).all()
    # saturation: grey stays grey; 0 gives the luma; 2 doubles the chroma (a pixel by hand)
    grey = np.full((2, 2, 3), 90, np.uint8)
    assert np.array_equal(camera_exposure_saturation(grey, saturation=1.7), grey)
    px = np.array([[[200, 100, 50]]], np.uint8)
    luma = 0.299 * 200 + 0.587 * 100 + 0.114 * 50  # 124.2
    assert camera_exposure_saturation(px, saturation=0.0).ravel().tolist() == [round(luma)] * 3
    assert camera_exposure_saturation(px, saturation=2.0).ravel().tolist() == [
        min(255, max(0, round(luma + 2 * (c - luma)))) for c in (200, 100, 50)]
    # a degenerate range draws nothing, so the default settings keep every earlier dataset's random stream
    rng = np.random.default_rng(3)
    state = rng.bit_generator.state
    assert _log_uniform(rng, (1.0, 1.0)) == 1.0 and rng.bit_generator.state == state
    draws = [_log_uniform(rng, (0.5, 2.0)) for _ in range(200)]
    assert 0.5 <= min(draws) and max(draws) <= 2.0 and 0.7 < float(np.exp(np.mean(np.log(draws)))) < 1.4
    cfg = PhotometricConfig.from_mapping({"prob": 0.0001, "exposure": [3.0, 3.0]})  # no blur / colour / noise
    assert np.array_equal(apply_photometric(img, np.random.default_rng(0), cfg), camera_exposure_saturation(img, 3.0))
    for bad in ({"exposure": [0, 2]}, {"saturation": [1.5, 1.0]}, {"exposure": 2.0}, {"saturation": ["a", 1]}):
        with pytest.raises(ValueError, match=r"photometric\.(exposure|saturation) must be \[low, high\] with 0 < low <= high"):
            PhotometricConfig.from_mapping(bad)


def test_procedural_backgrounds_vary_and_are_deterministic():
    from kpd6d.synth.backgrounds import procedural_background

    a = procedural_background(np.random.default_rng(5), 64, 48)
    b = procedural_background(np.random.default_rng(5), 64, 48)
    c = procedural_background(np.random.default_rng(6), 64, 48)
    assert a.shape == (48, 64, 3) and a.dtype == np.uint8
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert a.std() > 1.0  # not a flat colour


# ---------------------------------------------------------------------------------------------
# errors
# ---------------------------------------------------------------------------------------------
def test_bad_options_are_named(tmp_path, models_dir):
    with pytest.raises(TypeError, match=r"unknown option\(s\) colour.*known options:.*width"):
        generate_dataset(tmp_path, models_dir, num_images=1, colour=1)
    with pytest.raises(ValueError, match="distance_range"):
        SynthConfig.from_options({"distance_range": (500, 100)})
    with pytest.raises(ValueError, match="visib_fract_range"):
        SynthConfig.from_options({"visib_fract_range": (0.5, 1.5)})
    with pytest.raises(ValueError, match="objects_per_image"):
        SynthConfig.from_options({"objects_per_image": "some"})
    with pytest.raises(ValueError, match="rgb_format"):
        SynthConfig.from_options({"rgb_format": "gif"})
    with pytest.raises(FileNotFoundError, match="models_dir"):
        generate_dataset(tmp_path, tmp_path / "nope", num_images=1)


def test_bad_backgrounds_are_named(tmp_path, models_dir):
    from kpd6d.synth.backgrounds import FolderBackgrounds

    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="no image files"):
        FolderBackgrounds(empty)
    (empty / "broken.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(OSError, match=r"broken\.jpg"):
        FolderBackgrounds(empty).sample(np.random.default_rng(0), 32, 24)


def test_renderer_antialias_only_changes_colour_edges():
    import cv2

    from kpd6d.render import Lighting, Renderer
    from kpd6d.synth.distractors import make_distractor

    mesh = make_distractor(np.random.default_rng(0), 80.0)
    K = default_K(160, 120)
    R, t = np.eye(3), np.array([5.0, -3.0, 300.0])
    out = {}
    for aa in (True, False):
        r = Renderer(160, 120, K, antialias=aa)
        out[aa] = r.render([(mesh, R, t)], lighting=Lighting())
        r.close()
    a, b = out[True], out[False]
    np.testing.assert_array_equal(a.masks_visib[0], b.masks_visib[0])  # masks / depth: pixel-centre samples
    np.testing.assert_allclose(a.depth, b.depth, atol=0.01)  # (24-bit depth resolved differently)
    m = a.masks_visib[0].astype(np.uint8)
    edge = (cv2.dilate(m, np.ones((3, 3))) - cv2.erode(m, np.ones((3, 3)))) > 0
    diff = np.abs(a.rgb.astype(int) - b.rgb.astype(int)).sum(-1)
    assert diff[edge].mean() > 2 * diff[~edge].mean() + 1  # multisampling smooths the silhouette


def test_keypoints_written_for_the_shipped_meshes(tmp_path, models_dir):
    import trimesh

    root = generate_dataset(tmp_path, models_dir, num_images=1, progress=False,
                            **{**SMALL, "designator": {"name": "fps", "num_keypoints": 8}})
    ds = BopDataset(root, "train")
    kps = ds.load_keypoints()
    assert sorted(kps) == [1, 2]
    for m in ds.load_models():
        assert kps[m.obj_id].shape == (8, 3)
        _, dist, _ = trimesh.proximity.closest_point(m.mesh, kps[m.obj_id])
        assert dist.max() < 1e-3 * m.diameter  # on the surface
        assert np.linalg.norm(kps[m.obj_id][:, None] - kps[m.obj_id][None], axis=-1)[~np.eye(8, dtype=bool)].min() > 5
    info = json.loads((root / "models" / "keypoints.json").read_text())
    assert info["designator"] == "fps" and set(info["objects"]["1"]) >= {"points", "fingerprint"}


def test_interrupted_keypoint_designation_resumes_and_never_leaves_a_partial_keypoints_json(tmp_path, models_dir,
                                                                                          monkeypatch):
    from kpd6d.keypoints import designators

    real = designators.FpsDesignator.__call__
    calls = []

    def flaky(self, m):
        calls.append(m.obj_id)
        if m.obj_id == 2:
            raise KeyboardInterrupt
        return real(self, m)

    monkeypatch.setattr(designators.FpsDesignator, "__call__", flaky)
    opts = {**SMALL, "designator": {"name": "fps", "num_keypoints": 8}}
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(tmp_path, models_dir, num_images=1, progress=False, **opts)
    assert not (tmp_path / "models" / "keypoints.json").exists()  # not a file that lacks object 2
    monkeypatch.setattr(designators.FpsDesignator, "__call__", lambda self, m: calls.append(m.obj_id) or real(self, m))
    generate_dataset(tmp_path, models_dir, num_images=1, progress=False, **opts)
    assert calls == [1, 2, 2]  # object 1 is not designated again
    assert sorted(BopDataset(tmp_path, "train").load_keypoints()) == [1, 2]
    assert not list((tmp_path / "models").glob(".*"))


def test_cli_composes_and_generates(tmp_path, models_dir):
    from hydra import compose, initialize_config_dir

    from kpd6d.cli.generate import run
    from kpd6d.config import config_dir

    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("generate", overrides=[
            f"out_dir={tmp_path}", f"models_dir={models_dir}", "num_images=2", "workers=1", "progress=false",
            "options.width=160", "options.height=120", "options.designator=null", "options.distractors=[0,0]",
            "options.distance_range=[200,400]", "options.rgb_format=png",
        ])
    assert run(cfg) == str(tmp_path)
    ds = BopDataset(tmp_path, "train")
    assert len(ds) == 2 and ds[0].rgb_path.suffix == ".png"
    settings = json.loads((tmp_path / "dataset_info.json").read_text())["splits"]["train"]["config"]
    assert settings["distance_range"] == [200.0, 400.0] and settings["photometric"]["prob"] == 0.5


def test_generate_yaml_defaults_match_the_python_api():
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from kpd6d.config import config_dir
    from kpd6d.synth.photometric import PhotometricConfig

    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("generate", overrides=["out_dir=x"])
    opts = OmegaConf.to_container(cfg.options, resolve=True)
    yaml_cfg, api_cfg = SynthConfig.from_options(opts), SynthConfig.from_options({})
    a, b = yaml_cfg.to_dict(), api_cfg.to_dict()
    assert yaml_cfg.photometric_config() == api_cfg.photometric_config() == PhotometricConfig()
    assert a == b  # photometric included: both spell the defaults out
    assert (cfg.num_images, cfg.split, cfg.seed) == (1000, "train", 0)


def test_a_dataset_started_from_python_resumes_from_the_cli(tmp_path, models_dir):
    """The API and kpd6d-generate record the same settings, so either resumes the other's dataset;
    a dataset_info.json written before session 9 (photometric recorded as {}) resumes too."""
    from hydra import compose, initialize_config_dir

    from kpd6d.cli.generate import run
    from kpd6d.config import config_dir

    small = {"width": 160, "height": 120, "designator": None, "distractors": [0, 0], "rgb_format": "png"}
    root = tmp_path / "ds"
    generate_dataset(root, models_dir=models_dir, num_images=2, workers=1, progress=False, **small)
    info_path = root / "dataset_info.json"
    assert json.loads(info_path.read_text())["splits"]["train"]["config"]["photometric"]["prob"] == 0.5
    overrides = [f"out_dir={root}", f"models_dir={models_dir}", "num_images=3", "workers=1", "progress=false",
                 "options.width=160", "options.height=120", "options.designator=null", "options.distractors=[0,0]",
                 "options.rgb_format=png"]
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("generate", overrides=overrides)
    run(cfg)
    assert len(BopDataset(root, "train")) == 3
    # the old record of the defaults
    info = json.loads(info_path.read_text())
    info["splits"]["train"]["config"]["photometric"] = {}
    info_path.write_text(json.dumps(info))
    generate_dataset(root, models_dir=models_dir, num_images=4, workers=1, progress=False, **small)
    assert len(BopDataset(root, "train")) == 4
    # a real difference is still refused, naming the field
    with pytest.raises(ValueError, match="different settings \\(config\\)"):
        generate_dataset(root, models_dir=models_dir, num_images=5, workers=1, progress=False,
                         **{**small, "photometric": {"prob": 0.0}})


def test_renderer_keeps_cached_meshes_uploaded(monkeypatch):
    """Alternating meshes are uploaded to the GL context once each (a generator speed feature)."""
    import pyrender
    import trimesh

    from kpd6d.render import Renderer

    calls = []
    orig = pyrender.primitive.Primitive._add_to_context
    monkeypatch.setattr(pyrender.primitive.Primitive, "_add_to_context", lambda self: calls.append(1) or orig(self))
    r = Renderer(160, 120, default_K(160, 120), antialias=False)
    a, b = trimesh.creation.box((50.0, 50.0, 50.0)), trimesh.creation.icosphere(radius=30.0)
    R, t = np.eye(3), np.array([0.0, 0.0, 500.0])
    px = [int(r.render([(m, R, t)]).masks_visib[0].sum()) for m in (a, b, a, b, a)]
    r.close()
    assert len(calls) == 2
    assert px[0] == px[2] == px[4] > 0 and px[1] == px[3] > 0 and px[0] != px[1]


def test_two_pass_and_full_segmentation_paths_agree(tmp_path, models_dir):
    """antialias=False derives visibility from the colour pass's depth and an objects-only
    segmentation; antialias=True segments the whole scene. The ground truth must be identical."""
    run = dict(num_images=6, seed=11, progress=False, objects_per_image=(1, 2), distractors=(1, 2), depth=True,
               visib_fract_range=(0.0, 1.0), **SMALL)
    generate_dataset(tmp_path / "fast", models_dir, antialias=False, **run)
    generate_dataset(tmp_path / "aa", models_dir, antialias=True, **run)
    fast, aa = tree_bytes(tmp_path / "fast"), tree_bytes(tmp_path / "aa")
    names = [n for n in fast if "mask_visib" in n or n.endswith(("scene_gt.json", "scene_gt_info.json"))]
    assert len(names) > 8
    for n in names:
        assert fast[n] == aa[n], n
    info = BopDataset(tmp_path / "fast", "train")
    assert any(i.visib_fract < 0.95 for f in info for i in f.instances)  # occluders did occlude
    for f_fast, f_aa in zip(info, BopDataset(tmp_path / "aa", "train")):
        np.testing.assert_allclose(f_fast.load_depth(), f_aa.load_depth(), atol=0.1)  # stored in 0.1 mm


def test_object_alone_passes_are_shared_by_objects_with_disjoint_boxes():
    """silhouette_counts_many gives each instance the counts of a pass drawing it alone (and those of an
    independent rasterization, off-image parts included), in fewer passes: instances whose boxes are
    disjoint share one."""
    import trimesh

    from kpd6d.render import Renderer
    from kpd6d.synth.scene import bbox_obj_from_uv, silhouette_counts, silhouette_counts_many

    W, H = 160, 120
    K = default_K(W, H)
    r = Renderer(W, H, K, antialias=False)
    box, ball = trimesh.creation.box((60.0, 40.0, 50.0)), trimesh.creation.icosphere(subdivisions=2, radius=30.0)
    R = trimesh.transformations.rotation_matrix(0.4, [1.0, 1.0, 0.0])[:3, :3]
    items = [(box, R, np.array([-20.0, 0.0, 600.0])), (ball, np.eye(3), np.array([5.0, 10.0, 580.0])),  # overlap
             (ball, np.eye(3), np.array([-150.0, -100.0, 700.0])),  # apart, top left
             (box, R, np.array([340.0, 40.0, 650.0]))]  # leaves the image on the right
    boxes = [bbox_obj_from_uv(project_points(m.vertices, K, Ri, ti)) for m, Ri, ti in items]
    assert boxes[3][0] + boxes[3][2] > W  # the last one is partly outside the image
    calls = []
    render = r.render
    r.render = lambda *a, **k: calls.append(1) or render(*a, **k)
    many = silhouette_counts_many(r, items, K, W, H, boxes)
    n_many = len(calls)
    calls.clear()
    single = [silhouette_counts(r, m, Ri, ti, K, W, H, b) for (m, Ri, ti), b in zip(items, boxes)]
    n_single = len(calls)
    r.close()
    assert many == single
    assert n_many == 3 and n_single == 5  # {0, 2, 3} + {1} + the off-image tile of 3, against 1 + 1 + 1 + 2
    pad = 120
    for (m, Ri, ti), (total, inside) in zip(items, many):

        class _M:  # what _rasterize reads
            vertices, faces = np.asarray(m.vertices), np.asarray(m.faces)

        sil = _rasterize(_M, K, Ri, ti, W, H, pad=pad)
        ref_inside = int(sil[pad:pad + H, pad:pad + W].sum())
        assert abs(total - int(sil.sum())) <= 0.01 * total + 2 and abs(inside - ref_inside) <= 0.01 * inside + 2
        assert inside > 0


def test_palettes():
    """The natural palette: colours in [0, 255], mostly far less saturated than uniform RGB; its HSV
    conversion agrees with colorsys; unknown palettes name the known ones."""
    import colorsys

    from kpd6d.synth.palette import _hsv_to_rgb, random_colors

    rng = np.random.default_rng(0)
    h, s, v = rng.random(50), rng.random(50), rng.random(50)
    ours = _hsv_to_rgb(h, s, v)
    ref = np.array([colorsys.hsv_to_rgb(*x) for x in zip(h, s, v, strict=True)])
    np.testing.assert_allclose(ours, ref, atol=1e-12)

    def sat(c):
        return (c.max(1) - c.min(1)) / np.maximum(c.max(1), 1e-9)

    nat, uni = random_colors(np.random.default_rng(1), 4000, "natural"), random_colors(np.random.default_rng(1), 4000)
    assert nat.min() >= 0 and nat.max() <= 255 and uni.min() >= 0 and uni.max() <= 255
    assert np.median(sat(nat)) < 0.3 < np.median(sat(uni))
    assert 0.05 < (sat(nat) > 0.6).mean() < 0.2  # a tail of vivid colours remains
    with pytest.raises(ValueError, match=r"palette must be one of \['uniform', 'natural'\], got 'pastel'"):
        random_colors(rng, 2, "pastel")
    from kpd6d.synth.config import SynthConfig

    with pytest.raises(ValueError, match="palette must be one of"):
        SynthConfig.from_options({"palette": "pastel"})
    with pytest.raises(ValueError, match="distractor_refresh must be >= 0"):
        SynthConfig.from_options({"distractor_refresh": -1})
    # options at their defaults stay out of dataset_info.json (old datasets resume unchanged)
    assert "palette" not in SynthConfig().to_dict() and "distractor_refresh" not in SynthConfig().to_dict()
    assert SynthConfig.from_options({"palette": "natural"}).to_dict()["palette"] == "natural"


def test_natural_palette_backgrounds_are_muted():
    from kpd6d.synth.backgrounds import ProceduralBackgrounds

    def mean_sat(src):
        imgs = [src.sample(np.random.default_rng(i), 64, 48).astype(np.float64) for i in range(20)]
        return np.mean([np.median((im.max(2) - im.min(2)) / np.maximum(im.max(2), 1)) for im in imgs])

    assert mean_sat(ProceduralBackgrounds("natural")) < 0.7 * mean_sat(ProceduralBackgrounds())
    with pytest.raises(ValueError, match="palette must be one of"):
        ProceduralBackgrounds("vivid")


def test_object_coloured_distractors_carry_the_objects_colour_layout():
    """``distractor_object_colors``: each primitive vertex takes the colour of the nearest vertex of the
    turned object (checked against a brute-force nearest neighbour with the same rotation), so the
    object's colour regions stay regions on the primitive; the fraction of the pool, its determinism,
    and the errors."""
    import trimesh
    from scipy.spatial.transform import Rotation

    from kpd6d.synth.distractors import color_source, distractor_pool, transfer_colors

    obj = trimesh.creation.icosphere(subdivisions=3, radius=40.0)
    v = np.asarray(obj.vertices)
    rgba = np.where(v[:, :1] > 0, [[200, 30, 30, 255]], [[20, 40, 220, 255]]).astype(np.uint8)  # red / blue halves
    obj.visual = trimesh.visual.ColorVisuals(mesh=obj, vertex_colors=rgba)
    src = color_source(obj)
    assert src[0].min() == 0.0 and src[0].max() == 1.0 and src[1].shape == (len(v), 3)

    box = trimesh.creation.box(extents=(1.0, 0.5, 0.8)).subdivide().subdivide().subdivide()
    got = transfer_colors(np.random.default_rng(3), box.vertices, src)
    R = Rotation.random(random_state=np.random.default_rng(3)).as_matrix()
    sv = (src[0] - 0.5) @ R.T
    sv = (sv - sv.min(0)) / np.ptp(sv, axis=0)
    bv = (box.vertices - box.vertices.min(0)) / np.ptp(box.vertices, axis=0)
    nearest = np.argmin(((bv[:, None] - sv[None]) ** 2).sum(-1), axis=1)
    np.testing.assert_array_equal(got, src[1][nearest])
    red = (got == [200, 30, 30]).all(1)
    assert 0.1 < red.mean() < 0.9  # both halves show
    e = box.edges_unique
    assert (red[e[:, 0]] == red[e[:, 1]]).mean() > 0.85  # regions, not noise (random colours: ~0.5)

    pool = distractor_pool(5, 8, object_colors=0.5, color_sources=[src])
    coloured = [bool(np.isin(np.asarray(m.visual.vertex_colors)[:, 0], [200, 20]).all()) for m in pool]
    assert coloured == [True] * 4 + [False] * 4
    again = distractor_pool(5, 8, object_colors=0.5, color_sources=[src])
    assert all(np.array_equal(a.visual.vertex_colors, b.visual.vertex_colors) for a, b in zip(pool, again, strict=True))
    # at 0 the pool is the one made before the option existed (same random draws)
    plain = distractor_pool(5, 8)
    assert all(np.array_equal(a.vertices, b.vertices) for a, b in zip(plain, distractor_pool(5, 8, color_sources=[src]),
                                                                      strict=True))
    with pytest.raises(ValueError, match="object_colors > 0 needs color_sources"):
        distractor_pool(5, 8, object_colors=0.5)
    with pytest.raises(ValueError, match=r"distractor_object_colors must be a number in \[0, 1\], got 1.5"):
        SynthConfig.from_options({"distractor_object_colors": 1.5})
    assert "distractor_object_colors" not in SynthConfig().to_dict()


def test_generated_occluders_wear_the_target_objects_colours(tmp_path, models_dir):
    """End to end: with ``distractor_object_colors: 1`` the run's occluder pool wears only colours of
    the shipped objects' vertices, and the setting is recorded for resuming."""
    from kpd6d.objects import load_bop_models
    from kpd6d.synth import generate as gen
    from kpd6d.synth.distractors import color_source

    opts = {**SMALL, "distractors": (2, 2), "distractor_object_colors": 1.0}
    root = generate_dataset(tmp_path, models_dir, num_images=1, progress=False, **opts)
    info = json.loads((root / "dataset_info.json").read_text())["splits"]["train"]["config"]
    assert info["distractor_object_colors"] == 1.0
    models = load_bop_models(root / "models")
    cfg = SynthConfig.from_options(opts)
    pool = gen._distractors(0, cfg, 0, gen._color_sources(models, cfg))
    allowed = np.unique(np.concatenate([color_source(m.mesh)[1] for m in models]), axis=0)
    assert len(allowed) > 1 and len(pool) == cfg.distractor_pool_size
    for m in pool:
        cols = np.unique(np.asarray(m.visual.vertex_colors)[:, :3].astype(float), axis=0)
        assert (np.abs(cols[:, None] - allowed[None]).sum(-1).min(1) == 0).all()


def test_printed_sheets_are_paper_with_sharp_ink():
    """``kpd6d.synth.prints``: every kind of sheet is an RGB uint8 image of the asked size, deterministic
    for a seed; marker, text and table sheets are mostly paper (bright) with dark ink and far sharper
    than a smooth procedural texture; marker sheets hold square codes (their black borders give
    closed dark squares); unknown kinds are named."""
    import cv2

    from kpd6d.synth.backgrounds import _gradient
    from kpd6d.synth.prints import SHEET_KINDS, printed_sheet

    def sharp_edges(img):  # the share of pixels at a sharp, high-contrast edge
        g = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY).astype(np.float32)
        return float((np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1)) > 150).mean())

    smooth = np.clip(_gradient(np.random.default_rng(0), 200, 150), 0, 255).astype(np.uint8)
    for kind in SHEET_KINDS:
        a = printed_sheet(np.random.default_rng(4), 200, 150, "natural", kind)
        assert a.shape == (150, 200, 3) and a.dtype == np.uint8
        assert np.array_equal(a, printed_sheet(np.random.default_rng(4), 200, 150, "natural", kind))
    for kind in ("markers", "text", "table"):
        for seed in range(5):
            img = printed_sheet(np.random.default_rng(seed), 240, 320, "natural", kind)
            lum = img.mean(2)
            assert np.median(lum) > 180, (kind, seed)  # paper
            assert sharp_edges(img) > 0.005 > 100 * sharp_edges(smooth), (kind, seed)
    # markers: each code has a closed black border, so dark square blobs with a solid outline
    img = printed_sheet(np.random.default_rng(1), 300, 300, "natural", "markers")
    dark = (img.max(2) < 60).astype(np.uint8)
    contours, _ = cv2.findContours(dark, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    squares = [c for c in contours if cv2.contourArea(c) > 50]
    assert len(squares) >= 2
    for c in squares:
        _, _, w, h = cv2.boundingRect(c)
        assert abs(w - h) <= 1 and cv2.contourArea(c) >= 0.9 * (w - 1) * (h - 1)  # square, outline closed
    with pytest.raises(ValueError, match=r"unknown kind 'poster'; known: \['markers', 'text', 'table', 'picture'\]"):
        printed_sheet(np.random.default_rng(0), 10, 10, kind="poster")


def test_printed_matter_on_backgrounds_and_occluders():
    """``printed_matter``: at 0 backgrounds and occluder pools are those made before the option (the same
    random draws); at 1 sheets lie on every background (paper-bright, sharp regions appear); a
    fraction of the pool are printed cards and boxes (textured, about their drawn diameter, centred);
    the setting is checked and recorded only when set."""
    from kpd6d.synth.backgrounds import ProceduralBackgrounds, procedural_background
    from kpd6d.synth.distractors import distractor_pool
    from kpd6d.synth.prints import paste_sheets

    r0, r1 = np.random.default_rng(3), np.random.default_rng(3)
    assert np.array_equal(procedural_background(r0, 96, 64, "natural"), procedural_background(r1, 96, 64, "natural", 0.0))
    assert r0.random() == r1.random()  # nothing more drawn at 0
    changed = 0
    for seed in range(6):
        plain = procedural_background(np.random.default_rng(seed), 160, 120, "natural")
        printed = procedural_background(np.random.default_rng(seed), 160, 120, "natural", 1.0)
        changed += not np.array_equal(plain, printed)
    assert changed == 6
    img = np.zeros((100, 120, 3), np.uint8)
    assert np.array_equal(paste_sheets(np.random.default_rng(0), img.copy(), 0), img)
    out = paste_sheets(np.random.default_rng(0), img.copy(), 3)
    assert 0.01 < (out.max(2) > 0).mean() and (out.max(2) > 150).any()  # paper on the black image

    pool = distractor_pool(7, 10, diameter_range=(40.0, 200.0), printed=0.5)
    textured = [m.visual.kind == "texture" for m in pool]
    assert textured == [True] * 5 + [False] * 5
    for m in pool[:5]:
        v = np.asarray(m.vertices)
        diag = float(np.sqrt(((v[:, None] - v[None]) ** 2).sum(-1).max()))  # the box's diagonal
        assert 40.0 - 1e-6 <= diag <= 200.0 + 1e-6
        np.testing.assert_allclose((v.min(0) + v.max(0)) / 2, 0.0, atol=1e-9)
        assert np.asarray(m.visual.material.baseColorTexture).ndim == 3
    plain = distractor_pool(7, 10)
    assert all(np.array_equal(a.vertices, b.vertices) for a, b in zip(plain, distractor_pool(7, 10, printed=0.0),
                                                                      strict=True))
    with pytest.raises(ValueError, match=r"printed_matter must be a number in \[0, 1\], got 2"):
        ProceduralBackgrounds(printed=2)
    with pytest.raises(ValueError, match=r"printed_matter must be a number in \[0, 1\], got -0.1"):
        SynthConfig.from_options({"printed_matter": -0.1})
    assert "printed_matter" not in SynthConfig().to_dict()
    assert SynthConfig.from_options({"printed_matter": 0.3}).to_dict()["printed_matter"] == 0.3


def test_surface_detail_changes_only_the_masked_pixels():
    """``surface_detail``: pixels outside the mask are untouched, those inside gain fine detail (their
    high-frequency energy rises on a smooth image) with their mean level kept; deterministic per seed;
    an empty mask changes nothing; ``object_detail`` is checked and recorded only when set."""
    import cv2

    from kpd6d.synth.photometric import surface_detail

    yy, xx = np.mgrid[0:80, 0:100]
    img = np.stack([60 + xx, 90 + yy, 120 + 0 * xx], -1).astype(np.uint8)  # a smooth ramp
    mask = (xx - 50) ** 2 + (yy - 40) ** 2 < 25 ** 2
    out = surface_detail(img, mask, np.random.default_rng(2))
    assert out.dtype == np.uint8 and out.shape == img.shape
    assert np.array_equal(out[~mask], img[~mask])
    assert np.array_equal(out, surface_detail(img, mask, np.random.default_rng(2)))
    inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # away from the ramp's filter margin

    def hf(a):
        g = a.mean(2).astype(np.float32)
        return float(np.abs(cv2.Laplacian(g, cv2.CV_32F))[inner].mean())

    assert hf(out) > 3 * hf(img) + 1.0
    assert abs(float(out[mask].mean()) - float(img[mask].mean())) < 3.0
    assert np.array_equal(surface_detail(img, np.zeros_like(mask), np.random.default_rng(0)), img)
    with pytest.raises(ValueError, match=r"object_detail must be a number in \[0, 1\], got True"):
        SynthConfig.from_options({"object_detail": True})
    assert "object_detail" not in SynthConfig().to_dict()
