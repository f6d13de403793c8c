"""KPD crop dataset on the real LM-O frames (evaluation data, used here only to check the geometry):
crop / keypoint mapping against independent computations, symmetric-pose canonicalisation,
visibility flags and detector-box matching."""

import json

import cv2
import numpy as np
import pytest
import torch

from kpd6d.kpd.crops import KPDCropDataset


@pytest.fixture(scope="module")
def lmo_crops(lmo_dir, lmo_model_by_id):
    models = [lmo_model_by_id[1], lmo_model_by_id[10]]  # ape, eggbox (symmetric)
    kps = {m.obj_id: np.vstack([m.bbox_corners, m.bbox_min + m.bbox_size / 2]) for m in models}
    ds = KPDCropDataset(lmo_dir, split="test", obj_ids=[1, 10], keypoints=kps, models=models, input_size=128,
                        out_stride=4, sigma=2.0, crop_scale=1.5, box_source="visib", min_visib_fract=0.3)
    return ds, kps


def _bilinear(img, x, y):
    x0, y0 = int(np.floor(x)), int(np.floor(y))
    ax, ay = x - x0, y - y0
    p = img.astype(np.float64)
    return ((1 - ax) * (1 - ay) * p[y0, x0] + ax * (1 - ay) * p[y0, x0 + 1]
            + (1 - ax) * ay * p[y0 + 1, x0] + ax * ay * p[y0 + 1, x0 + 1])


def test_keypoints_and_pixels_match_independent_mapping(lmo_crops):
    ds, kps = lmo_crops
    asym = [i for i, (fi, ii) in enumerate(ds.items) if ds.ds.frames[fi].instances[ii].obj_id == 1][:5]
    assert asym
    for i in asym:
        item = ds[i]
        fi, ii = ds.items[i]
        frame, inst = ds.ds.frames[fi], ds.ds.frames[fi].instances[ii]
        # independent projection (OpenCV) and crop mapping (scale about the box centre)
        rvec, _ = cv2.Rodrigues(np.asarray(inst.R, dtype=np.float64))
        uv, _ = cv2.projectPoints(kps[1], rvec, np.asarray(inst.t, dtype=np.float64), frame.K, None)
        uv = uv[:, 0]
        x, y, w, h = np.asarray(inst.bbox_visib, dtype=np.float64)
        s = 128 / (1.5 * max(w, h))
        want = np.column_stack([(uv[:, 0] - (x + w / 2)) * s + 63.5, (uv[:, 1] - (y + h / 2)) * s + 63.5])
        # (cv2.Rodrigues re-orthonormalises BOP's 8-digit R: differences of a few 1e-3 px)
        np.testing.assert_allclose(item["keypoints_image"].numpy(), uv, atol=0.01)
        np.testing.assert_allclose(item["keypoints"].numpy(), want, atol=0.01)
        # crop pixels are the image bilinearly sampled at the inverse-mapped positions
        rgb = frame.load_rgb()
        crop = (item["image"].numpy().transpose(1, 2, 0) * 255).round()
        for cu, cv in [(10, 20), (64, 64), (100, 37), (127, 127)]:
            u, v = (cu - 63.5) / s + x + w / 2, (cv - 63.5) / s + y + h / 2
            if 0 <= u < rgb.shape[1] - 1 and 0 <= v < rgb.shape[0] - 1:
                np.testing.assert_allclose(crop[cv, cu], _bilinear(rgb, u, v), atol=1.01)
        # target heatmaps peak at the keypoints mapped to heatmap px: (crop + 0.5) / 4 - 0.5
        hm = item["heatmaps"]
        assert hm.shape == (9, 32, 32)
        inside = (want >= 0).all(1) & (want < 127).all(1)
        peak = hm.flatten(1).argmax(1)
        hm_xy = np.column_stack([peak % 32, peak // 32])
        np.testing.assert_allclose(hm_xy[inside], np.round((want[inside] + 0.5) / 4 - 0.5), atol=1)
        np.testing.assert_array_equal(item["visibility"].numpy().astype(bool), inside)


def test_symmetric_object_pose_is_canonicalised(lmo_crops, lmo_model_by_id):
    from kpd6d.evaluation.errors import adds_error
    from kpd6d.geometry import project_points
    from kpd6d.symmetry import handler_for_model

    ds, kps = lmo_crops
    egg = lmo_model_by_id[10]
    handler = handler_for_model(egg)
    idx = [i for i, (fi, ii) in enumerate(ds.items) if ds.ds.frames[fi].instances[ii].obj_id == 10][:4]
    assert idx
    pts = egg.sample_points(500, seed=0)
    for i in idx:
        item = ds[i]
        fi, ii = ds.items[i]
        inst = ds.ds.frames[fi].instances[ii]
        Rc, tc = handler.canonicalize(np.asarray(inst.R, dtype=np.float64), np.asarray(inst.t, dtype=np.float64))
        np.testing.assert_allclose(item["R"].numpy(), Rc, atol=1e-9)
        # an equivalent pose: the GT pose composed with one of the model's symmetry transforms S
        R, t = np.asarray(inst.R, dtype=np.float64), np.asarray(inst.t, dtype=np.float64)
        syms = [np.eye(4)] + [np.asarray(S, dtype=np.float64).reshape(4, 4) for S in egg.symmetries_discrete]
        dist = [np.abs(Rc - R @ S[:3, :3]).max() + np.abs(tc - (R @ S[:3, 3] + t)).max() / 1000 for S in syms]
        assert min(dist) < 0.01  # the handler may re-orthonormalise the 8-digit BOP matrices
        assert adds_error(Rc, tc, R, t, pts) < 0.05 * egg.diameter  # eggbox is only nearly symmetric
        np.testing.assert_allclose(item["keypoints_image"].numpy(),
                                   project_points(kps[10], ds.ds.frames[fi].K, Rc, tc), atol=1e-3)


def test_visibility_in_crop_and_box_sources(lmo_dir, lmo_model_by_id, tmp_path):
    m = lmo_model_by_id[1]
    kps = {1: np.vstack([m.bbox_corners, m.bbox_min + m.bbox_size / 2])}
    tight = KPDCropDataset(lmo_dir, split="test", obj_ids=[1], keypoints=kps, models=[m], input_size=64,
                           crop_scale=0.5, visibility="crop", max_instances=3)
    for i in range(len(tight)):
        it = tight[i]
        k = it["keypoints"].numpy()
        want = (k >= -0.5).all(1) & (k < 63.5).all(1)
        np.testing.assert_array_equal(it["visibility"].numpy().astype(bool), want)
    assert any(not tight[i]["visibility"].all() for i in range(len(tight)))  # the half-size crop cuts some off

    # box sources: bbox_obj, and detections matched to the GT instance by class and IoU
    by_obj = KPDCropDataset(lmo_dir, split="test", obj_ids=[1], keypoints=kps, models=[m], input_size=64,
                            box_source="obj", max_instances=2)
    fi, ii = by_obj.items[0]
    frame = by_obj.ds.frames[fi]
    inst = frame.instances[ii]
    np.testing.assert_allclose(by_obj[0]["box"].numpy(), inst.bbox_obj)
    det_box = np.asarray(inst.bbox_visib, dtype=np.float64) + np.array([3.0, -2.0, 4.0, 1.0])
    dets = [{"scene_id": frame.scene_id, "image_id": frame.im_id, "category_id": 1, "bbox": det_box.tolist(), "score": 0.9},
            {"scene_id": frame.scene_id, "image_id": frame.im_id, "category_id": 5, "bbox": [0, 0, 50, 50], "score": 0.8}]
    path = tmp_path / "dets.json"
    path.write_text(json.dumps(dets))
    by_det = KPDCropDataset(lmo_dir, split="test", obj_ids=[1], keypoints=kps, models=[m], input_size=64,
                            box_source="detections", detections=path, max_instances=2)
    by_det.items = [(fi, ii)]
    np.testing.assert_allclose(by_det[0]["box"].numpy(), det_box)
    with pytest.raises(ValueError, match="box_source 'gt'"):
        KPDCropDataset(lmo_dir, split="test", obj_ids=[1], keypoints=kps, models=[m], box_source="gt")
    with pytest.raises(KeyError, match=r"no keypoints for object\(s\) \[1\]"):
        KPDCropDataset(lmo_dir, split="test", obj_ids=[1], keypoints={5: kps[1]}, models=[m])


def test_box_jitter_changes_the_crop_not_the_geometry(lmo_dir, lmo_model_by_id):
    from kpd6d.geometry import affine_apply
    from kpd6d.kpd.box_augment import BoxJitter

    m = lmo_model_by_id[1]
    kps = {1: m.bbox_corners}
    ds = KPDCropDataset(lmo_dir, split="test", obj_ids=[1], keypoints=kps, models=[m], input_size=64,
                        box_augment=BoxJitter(0.2, 0.2), max_instances=1)
    torch.manual_seed(0)
    a, b = ds[0], ds[0]
    assert not torch.allclose(a["box"], b["box"])
    for it in (a, b):  # whatever the box, the crop keypoints are the image keypoints through the crop affine
        np.testing.assert_allclose(it["keypoints"].numpy(),
                                   affine_apply(it["affine"].numpy(), it["keypoints_image"].numpy()), atol=1e-4)


def test_image_cache_gives_identical_items_within_its_budget(lmo_dir, lmo_model_by_id):
    models = [lmo_model_by_id[1]]
    kps = {1: lmo_model_by_id[1].bbox_corners}
    common = dict(split="test", obj_ids=[1], keypoints=kps, models=models, input_size=64, min_visib_fract=0.3)
    plain = KPDCropDataset(lmo_dir, **common)
    one_image_mb = 640 * 480 * 3 / 2**20
    cached = KPDCropDataset(lmo_dir, image_cache_mb=2.5 * one_image_mb, **common)  # room for two images
    for _ in range(2):  # the second pass reads from the cache
        for i in range(4):
            a, b = plain[i], cached[i]
            for key in ("image", "keypoints", "visibility", "heatmaps"):
                torch.testing.assert_close(a[key], b[key])
    assert len(cached._cache) == 2 and cached._cache_bytes <= 2.5 * one_image_mb * 2**20
    assert not plain._cache


def test_negative_crops_avoid_their_object_and_have_empty_targets(lmo_dir, lmo_model_by_id):
    """negative_fraction: the negative items' crops touch no visible box of their object (read from
    scene_gt_info.json here), their targets and visibility are all zero, the positives are the plain
    dataset's items; a fraction outside [0, 1) is refused."""
    models = [lmo_model_by_id[1], lmo_model_by_id[5]]
    kps = {m.obj_id: m.bbox_corners for m in models}
    common = dict(split="test", obj_ids=[1, 5], keypoints=kps, models=models, input_size=64, min_visib_fract=0.3)
    plain = KPDCropDataset(lmo_dir, **common)
    mixed = KPDCropDataset(lmo_dir, negative_fraction=0.5, **common)
    scene = plain.ds.frames[0].scene_dir
    gt = json.loads((scene / "scene_gt.json").read_text())
    info = json.loads((scene / "scene_gt_info.json").read_text())
    torch.manual_seed(0)
    n_neg = 0
    for i in range(len(mixed)):
        a = mixed[i]
        frame = mixed.ds.frames[mixed.items[i][0]]
        if not a["negative"]:
            b = plain[i]
            for key in ("image", "keypoints", "visibility", "heatmaps", "box"):
                torch.testing.assert_close(a[key], b[key])
            continue
        n_neg += 1
        assert a["heatmaps"].abs().max() == 0 and a["visibility"].sum() == 0
        # the crop square in image px, from the item's affine (crop px -> image px)
        A = np.vstack([a["affine"].numpy(), [0, 0, 1]])
        corners = np.linalg.inv(A)[:2] @ np.array([[-0.5, 63.5, 63.5, -0.5], [-0.5, -0.5, 63.5, 63.5], [1, 1, 1, 1]])
        x0, y0, x1, y1 = corners[0].min(), corners[1].min(), corners[0].max(), corners[1].max()
        own = [inf["bbox_visib"] for g, inf in zip(gt[str(frame.im_id)], info[str(frame.im_id)])
               if g["obj_id"] == a["obj_id"] and inf["bbox_visib"][2] > 0]
        assert own
        for bx, by, bw, bh in own:
            assert x1 <= bx + 1 or bx + bw <= x0 + 1 or y1 <= by + 1 or by + bh <= y0 + 1, (i, (x0, y0, x1, y1), own)
        # the box keeps the instance's size: same crop scale as its positive crop
        np.testing.assert_allclose(a["box"][2:].numpy(), plain[i]["box"][2:].numpy())
    assert 0.25 * len(mixed) <= n_neg <= 0.75 * len(mixed)
    with pytest.raises(ValueError, match="negative_fraction must be in"):
        KPDCropDataset(lmo_dir, negative_fraction=1.0, **common)


def test_full_box_crops_cover_the_whole_projected_object(lmo_dir, lmo_model_by_id):
    """full_box_p: a full-box item is cropped on the box of the whole object — checked against the model's
    vertices projected independently (OpenCV) with the GT pose and clipped to the image — and holds the
    keypoints a visible-box crop leaves out on occluded instances; the other items are the plain dataset's;
    a share outside [0, 1] is refused."""
    models = [lmo_model_by_id[1], lmo_model_by_id[5], lmo_model_by_id[6]]
    kps = {m.obj_id: m.bbox_corners for m in models}
    common = dict(split="test", obj_ids=[1, 5, 6], keypoints=kps, models=models, input_size=64, crop_scale=1.25,
                  min_visib_fract=0.1)
    plain = KPDCropDataset(lmo_dir, **common)
    full = KPDCropDataset(lmo_dir, full_box_p=1.0, **common)
    occluded = 0
    for i in range(len(full)):
        a, b = full[i], plain[i]
        fi, ii = full.items[i]
        frame, inst = full.ds.frames[fi], full.ds.frames[fi].instances[ii]
        rvec, _ = cv2.Rodrigues(np.asarray(inst.R, dtype=np.float64))
        m = full.models[inst.obj_id]
        uv = cv2.projectPoints(m.vertices, rvec, np.asarray(inst.t, dtype=np.float64), frame.K, None)[0][:, 0]
        lo, hi = np.clip(uv.min(0), 0, [640, 480]), np.clip(uv.max(0), 0, [640, 480])
        np.testing.assert_allclose(a["box"].numpy(), np.r_[lo, hi - lo], atol=2.0)  # BOP boxes are whole px
        torch.testing.assert_close(a["keypoints_image"], b["keypoints_image"])  # same instance, same pose
        if inst.visib_fract < 0.7:
            occluded += 1
            inside = lambda it: ((it["keypoints"] >= 0) & (it["keypoints"] < 64)).all(1).sum()  # noqa: E731
            assert inside(a) >= inside(b), i
            assert a["box"][2:].prod() >= b["box"][2:].prod()
    assert occluded >= 3
    half = KPDCropDataset(lmo_dir, full_box_p=0.5, **common)
    torch.manual_seed(0)
    n_full = 0
    for i in range(len(half)):
        box = half[i]["box"]
        is_full = torch.allclose(box, full[i]["box"])
        is_plain = torch.allclose(box, plain[i]["box"])
        assert is_full or is_plain, i
        n_full += is_full and not is_plain
    assert 0.2 * len(half) <= n_full <= 0.8 * len(half)
    with pytest.raises(ValueError, match="full_box_p must be in"):
        KPDCropDataset(lmo_dir, full_box_p=1.5, **common)


def test_symmetry_boundary_option(lmo_dir, lmo_model_by_id):
    from kpd6d.symmetry import handler_for_model

    glue = lmo_model_by_id[11]
    kps = {11: np.vstack([glue.bbox_corners, glue.bbox_min + glue.bbox_size / 2])}
    common = dict(split="test", obj_ids=[11], keypoints=kps, models=[glue], input_size=64, out_stride=4, sigma=2.0,
                  min_visib_fract=0.3, return_heatmaps=False)
    ds = KPDCropDataset(lmo_dir, symmetry_boundary="least_motion", **common)
    hl, hx = handler_for_model(glue, boundary="least_motion"), handler_for_model(glue)
    moved = 0
    for i in range(len(ds)):
        inst = ds.ds.frames[ds.items[i][0]].instances[ds.items[i][1]]
        R, t = np.asarray(inst.R, dtype=np.float64), np.asarray(inst.t, dtype=np.float64)
        Rl = hl.canonicalize(R, t)[0]
        np.testing.assert_allclose(ds[i]["R"].numpy(), Rl, atol=1e-9)
        moved += not np.allclose(Rl, hx.canonicalize(R, t)[0])
    assert len(ds) and moved  # the glue's labels differ from the model_x range's for some views
    with pytest.raises(ValueError, match="symmetry boundary 'widest' unknown; known: model_x, least_motion"):
        KPDCropDataset(lmo_dir, symmetry_boundary="widest", **common)
