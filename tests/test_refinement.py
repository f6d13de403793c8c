"""Region-based pose refinement (kpd6d.refinement): poses pulled onto rendered objects' silhouettes,
checked against the ground-truth poses the images were rendered at."""

from __future__ import annotations

import numpy as np
import pytest

from kpd6d.geometry import LINEMOD_K, pose_from_view, rotation_about_axis, rotation_error_deg
from kpd6d.objects import procedural_objects
from kpd6d.refinement import RegionRefineConfig, RegionRefiner, build_refiner, cover_box
from kpd6d.registry import REFINERS, UnknownNameError


@pytest.fixture(scope="module")
def scene_renderer():
    from kpd6d.render import Renderer

    r = Renderer(640, 480, LINEMOD_K, antialias=False)
    yield r
    r.close()


@pytest.fixture(scope="module")
def refiner():
    ref = RegionRefiner()
    yield ref
    ref.close()


def _scene(renderer, model, seed=0):
    """The object rendered at a known pose over a dark, unsaturated noise background."""
    import cv2

    rng = np.random.default_rng(seed)
    R, t = pose_from_view(0.7, 0.5, 650.0, 0.3)
    t = t + np.array([30.0, -20.0, 0.0])
    res = renderer.render([(model, R, t)])
    grey = cv2.resize(rng.uniform(30, 90, (30, 40)).astype(np.float32), (640, 480))
    bg = np.repeat(grey[..., None], 3, axis=2) + rng.uniform(-6, 6, (1, 1, 3))
    image = np.where((res.depth > 0)[..., None], res.rgb, np.clip(bg, 0, 255)).astype(np.uint8)
    return image, R, t


def _perturbed(R, t, seed=1, deg=6.0, dt=(4.0, -3.0, 35.0)):
    axis = np.random.default_rng(seed).normal(size=3)
    return rotation_about_axis(axis / np.linalg.norm(axis), np.radians(deg)) @ R, t + np.asarray(dt)


@pytest.mark.parametrize("obj_id", [1, 3, 5])
def test_refinement_recovers_a_perturbed_pose(scene_renderer, refiner, obj_id):
    model = procedural_objects(obj_ids=[obj_id])[0]
    image, R, t = _scene(scene_renderer, model)
    Rp, tp = _perturbed(R, t)
    out = refiner.refine(image, model, Rp, tp, LINEMOD_K)
    assert out.ok and out.lines >= 100 and len(out.history) == len(refiner.config.scales)
    err_t, err_r = np.linalg.norm(out.t - t), rotation_error_deg(out.R, R)
    # from 35 mm / 6 degrees off to a few mm / about a degree (depth comes from the silhouette's size)
    assert err_t < 8.0 and err_r < 3.0, (err_t, err_r)
    assert abs(out.t[2] - t[2]) < 6.0
    # each step a proper rotation
    assert np.allclose(out.R @ out.R.T, np.eye(3), atol=1e-9) and np.linalg.det(out.R) == pytest.approx(1.0)


def test_refinement_keeps_the_true_pose(scene_renderer, refiner):
    model = procedural_objects(obj_ids=[1])[0]
    image, R, t = _scene(scene_renderer, model, seed=3)
    out = refiner.refine(image, model, R, t, LINEMOD_K)
    assert out.ok
    assert np.linalg.norm(out.t - t) < 3.0 and rotation_error_deg(out.R, R) < 1.5


def test_edge_offset_sets_where_the_silhouette_edge_is_taken(scene_renderer):
    """From the true pose on an aliased render: the default half viewport pixel keeps the depth within
    0.5 %; taking the edge at the contour pixels' centres (0) pulls the object nearer (its contour
    looks a little too small), a whole pixel out (1) pushes it away; a value outside [0, 1] is refused."""
    model = procedural_objects(obj_ids=[1])[0]
    image, R, t = _scene(scene_renderer, model, seed=3)
    z = {}
    for e in (0.0, 0.5, 1.0):
        ref = RegionRefiner(RegionRefineConfig(edge_offset=e))
        out = ref.refine(image, model, R, t, LINEMOD_K)
        ref.close()
        assert out.ok
        z[e] = out.t[2] / t[2]
    assert abs(z[0.5] - 1) < 0.005 and z[0.0] < z[0.5] < z[1.0], z
    assert z[1.0] - z[0.0] > 0.005, z
    with pytest.raises(ValueError, match=r"edge_offset must lie in \[0, 1\]"):
        RegionRefineConfig(edge_offset=1.5)


def test_no_evidence_keeps_the_input_pose(refiner):
    model = procedural_objects(obj_ids=[1])[0]
    R, t = pose_from_view(0.7, 0.5, 650.0, 0.3)
    flat = np.full((480, 640, 3), 128, np.uint8)  # object and background the same colour: nothing to align to
    out = refiner.refine(flat, model, R, t, LINEMOD_K)
    assert not out.ok and out.history == []
    assert np.array_equal(out.R, R) and np.array_equal(out.t, t)


def test_refine_poses_updates_ok_poses_and_names_missing_meshes(scene_renderer):
    model = procedural_objects(obj_ids=[3])[0]
    image, R, t = _scene(scene_renderer, model)
    Rp, tp = _perturbed(R, t)
    ref = RegionRefiner(models={3: model})
    poses = [[{"obj_id": 3, "R": Rp, "t": tp, "ok": True}, {"obj_id": 3, "R": Rp, "t": tp, "ok": False}]]
    out = ref.refine_poses([image], LINEMOD_K[None], poses)
    good, failed = out[0]
    assert good["refined"] and np.linalg.norm(good["t"] - t) < 8.0
    assert not failed["refined"] and failed["t"] is tp  # not ok: left as it was
    with pytest.raises(KeyError, match=r"no mesh for object 7 .*\[3\]"):
        ref.refine_poses([image], LINEMOD_K[None], [[{"obj_id": 7, "R": R, "t": t, "ok": True}]])
    with pytest.raises(ValueError, match="uint8 RGB"):
        ref.refine_poses([image.astype(np.float32)], LINEMOD_K[None], poses)
    ref.close()


def test_registry_configs_and_errors(tmp_path):
    assert REFINERS.names() == ["none", "region"]
    assert build_refiner(None) is None and build_refiner({"name": "none"}) is None
    with pytest.raises(ValueError, match=r"refiner\.models_dir is required"):
        build_refiner({"name": "region"})
    models = procedural_objects(obj_ids=[1, 2])
    ref = build_refiner({"name": "region", "num_lines": 50}, lambda: models, source="the dataset")
    assert sorted(ref.models) == [1, 2] and ref.config.num_lines == 50
    assert ref.settings()["name"] == "region" and ref.settings()["scales"] == list(RegionRefineConfig().scales)
    with pytest.raises(TypeError, match=r"got unknown parameter.*lines_per_step.*it accepts: models_dir"):
        build_refiner({"name": "region", "lines_per_step": 3}, models)
    with pytest.raises(UnknownNameError, match="known pose refiners: none, region"):
        build_refiner({"name": "icp"}, models)
    with pytest.raises(ValueError, match="amplitude must lie in"):
        RegionRefineConfig(amplitude=0.6)
    with pytest.raises(ValueError, match="scales must be positive"):
        RegionRefineConfig(scales=())


def test_occlusion_masks_the_lines_another_object_hides(scene_renderer):
    """Object 1 with 30 % of it hidden behind object 3: with ``occlusion`` the lines the front object
    covers carry no evidence, and the refined pose is closer to the truth than without."""
    import cv2

    back, front = procedural_objects(obj_ids=[1, 3])
    R, t = pose_from_view(0.7, 0.5, 650.0, 0.3)
    t = t + np.array([30.0, -20.0, 0.0])
    Rf, tf = pose_from_view(2.0, 0.3, 450.0, 1.0)
    tf = tf + np.array([75.0, -5.0, 0.0])
    res = scene_renderer.render([(back, R, t), (front, Rf, tf)])
    alone = scene_renderer.render([(back, R, t)]).masks_visib[0]
    assert 0.6 < res.masks_visib[0].sum() / alone.sum() < 0.8
    grey = cv2.resize(np.random.default_rng(0).uniform(30, 90, (30, 40)).astype(np.float32), (640, 480))
    image = np.where((res.depth > 0)[..., None], res.rgb, np.repeat(grey[..., None], 3, axis=2)).astype(np.uint8)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    Rp, tp = rotation_about_axis(axis, np.radians(6.0)) @ R, t + np.array([4.0, -3.0, 35.0])
    errors = {}
    for occlusion in (False, True):
        ref = RegionRefiner(RegionRefineConfig(occlusion=occlusion), models={1: back, 3: front})
        poses = [[{"obj_id": 1, "R": Rp, "t": tp, "ok": True}, {"obj_id": 3, "R": Rf, "t": tf, "ok": True}]]
        p = ref.refine_poses([image], LINEMOD_K[None], poses)[0][0]
        errors[occlusion] = (rotation_error_deg(p["R"], R), np.linalg.norm(p["t"] - t))
        ref.close()
    assert errors[True][0] < 0.8 and errors[True][1] < 3.0, errors
    assert errors[True][0] < errors[False][0], errors


def test_evidence_is_high_on_the_object_and_low_on_background(scene_renderer, refiner):
    """``evidence``: the share of the contour the image confirms. At the true pose most of it; the same
    object placed on the background (120 px away) little."""
    model = procedural_objects(obj_ids=[1])[0]
    image, R, t = _scene(scene_renderer, model, seed=3)
    on = refiner.refine(image, model, R, t, LINEMOD_K)
    off = refiner.refine(image, model, R, t + np.array([-160.0, 90.0, 0.0]), LINEMOD_K)
    assert 0.0 <= off.evidence < 0.5 * on.evidence and on.evidence > 0.5, (on.evidence, off.evidence)


def test_contour_jacobian_matches_finite_differences_of_the_pose_step():
    """The Gauss-Newton Jacobian against central differences of projecting model points after
    apply_pose_step (an independent computation: project_points on the stepped pose)."""
    from kpd6d.geometry import project_points
    from kpd6d.refinement import apply_pose_step, contour_jacobian

    rng = np.random.default_rng(0)
    R, t = pose_from_view(0.4, 0.6, 700.0, 0.2)
    t = t + np.array([40.0, -25.0, 0.0])
    pts_m = rng.uniform(-60, 60, (12, 3))
    X = pts_m @ R.T + t
    centre = R @ np.array([5.0, -3.0, 2.0]) + t
    normals = rng.normal(size=(12, 2))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    J = contour_jacobian(X, normals, centre, LINEMOD_K)
    eps = 1e-6
    for k in range(6):
        step = np.zeros(6)
        step[k] = eps
        plus = project_points(pts_m, LINEMOD_K, *apply_pose_step(R, t, centre, step))
        minus = project_points(pts_m, LINEMOD_K, *apply_pose_step(R, t, centre, -step))
        numeric = np.sum((plus - minus) / (2 * eps) * normals, axis=1)
        np.testing.assert_allclose(J[:, k], numeric, rtol=1e-5, atol=1e-6)
    # a finite step: rotation about the centre leaves the centre where it is
    R2, t2 = apply_pose_step(R, t, centre, np.array([0.1, -0.2, 0.3, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(R2 @ np.array([5.0, -3.0, 2.0]) + t2, centre, atol=1e-9)


@pytest.mark.parametrize("fg_margin,bg_margin", [(0, 0), (1, 2), (2, 0), (0, 3), (2, 3)])
def test_histogram_margins_leave_the_bands_beside_the_edge_out(fg_margin, bg_margin):
    """A square silhouette; a 2-px band of one colour just inside its edge and a 2-px band of another just
    outside: each band's colour counts for its side unless that side's margin leaves the band out."""
    ref = RegionRefiner(config=RegionRefineConfig(fg_margin=fg_margin, bg_margin=bg_margin))
    H = W = 120
    sil = np.zeros((60, 60), np.uint8)
    sil[10:50, 10:50] = 1
    A = np.array([[1.0, 0.0, 30.0], [0.0, 1.0, 30.0]])  # viewport px -> image px: the square is image [40, 80)
    img = np.zeros((H, W, 3), np.uint8)
    img[:] = (200, 200, 200)                   # background
    img[38:82, 38:82] = (0, 0, 200)            # outer band: image px 38-39 and 80-81 ...
    img[40:80, 40:80] = (200, 0, 0)            # ... inner band 40-41 and 78-79
    img[42:78, 42:78] = (0, 200, 0)            # object
    pf, sil_img, origin = ref._posterior(img, sil, A, diameter_px=40.0)
    assert origin == (0, 0) and pf.shape == (H, W)  # no reach: the whole image
    assert sil_img[40:80, 40:80].all() and not sil_img[39, 50] and not sil_img[80, 50]
    inner, outer, obj = pf[41, 60], pf[38, 60], pf[60, 60]
    assert obj > 0.99 and pf[5, 5] < 0.01
    assert (inner > 0.99) if fg_margin < 2 else (inner == pytest.approx(0.5, abs=1e-3))  # seen by neither histogram: 0.5
    assert (outer < 0.01) if bg_margin < 2 else (outer == pytest.approx(0.5, abs=1e-3))
    with pytest.raises(ValueError, match="fg_margin"):
        RegionRefineConfig(fg_margin=-1)


def test_local_histograms_separate_what_the_whole_silhouettes_cannot():
    """An object red on its left half and blue on its right, on a background blue beside the left half and red
    beside the right: one histogram pair sees both colours on both sides (posterior 0.5 everywhere); one pair
    per angular sector tells object from background on each side."""
    H = W = 120
    sil = np.zeros((60, 60), np.uint8)
    sil[10:50, 10:50] = 1
    A = np.array([[1.0, 0.0, 30.0], [0.0, 1.0, 30.0]])  # viewport px -> image px: the square is image [40, 80)
    img = np.zeros((H, W, 3), np.uint8)
    img[:, :60] = (0, 0, 200)
    img[:, 60:] = (200, 0, 0)
    img[40:80, 40:60] = (200, 0, 0)
    img[40:80, 60:80] = (0, 0, 200)
    whole, _, _ = RegionRefiner(config=RegionRefineConfig(fg_margin=0, bg_margin=0))._posterior(img, sil, A, 40.0)
    np.testing.assert_allclose(whole[[60, 60, 60, 60], [45, 75, 30, 90]], 0.5, atol=0.02)
    for prior in (0.0, 100.0):
        ref = RegionRefiner(config=RegionRefineConfig(fg_margin=0, bg_margin=0, local_regions=4, local_prior=prior))
        local, _, _ = ref._posterior(img, sil, A, 40.0)
        # inside left / right half, outside left / right (the sectors of +-45 degrees about the x axis); the
        # prior (0.5 for both colours) pulls toward 0.5 by its weight against the sector's ~400 / ~280 px
        lo, hi = (0.01, 0.99) if prior == 0 else (0.2, 0.8)
        assert local[60, 45] > hi and local[60, 75] > hi, (local[60, 45], local[60, 75])
        assert local[60, 30] < lo and local[60, 90] < lo, (local[60, 30], local[60, 90])
    # many sectors without a prior: sectors with no pixel of a side fall back on the whole pair (no 0 / 0)
    many, _, _ = RegionRefiner(config=RegionRefineConfig(local_regions=720, local_prior=0.0))._posterior(img, sil, A, 40.0)
    assert np.isfinite(many).all() and many.min() >= 0.0 and many.max() <= 1.0
    same, _, _ = RegionRefiner(config=RegionRefineConfig(fg_margin=0, bg_margin=0, local_regions=1))._posterior(img, sil, A, 40.0)
    np.testing.assert_array_equal(same, whole)  # one sector: the whole silhouette's pair
    for bad in ({"local_regions": -1}, {"local_regions": 2.5}, {"local_prior": -1.0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            RegionRefineConfig(**bad)


def test_local_histograms_recover_a_pose_where_the_background_has_the_objects_colours(scene_renderer):
    """The background beside the object's left half is made of the object's own pixels (drawn at random), the
    rest stays dark: one histogram pair sees the object's colours as background and the pose runs off;
    per-sector pairs judge the right side by its own surroundings and bring the perturbed pose back."""
    model = procedural_objects(obj_ids=[3])[0]
    image, R, t = _scene(scene_renderer, model)
    inside = scene_renderer.render([(model, R, t)]).depth > 0
    left = np.zeros_like(inside)
    left[:, : int(np.median(np.nonzero(inside)[1]))] = True
    where = left & ~inside
    image = image.copy()
    image[where] = image[inside][np.random.default_rng(0).integers(0, int(inside.sum()), int(where.sum()))]
    start = _perturbed(R, t)
    outs = {}
    for S in (0, 8):
        ref = RegionRefiner(config=RegionRefineConfig(local_regions=S))
        outs[S] = ref.refine(image, model, *start, LINEMOD_K)
        ref.close()
    assert np.linalg.norm(outs[0].t - t) > 50.0  # one pair: lost (a control, so the scene is a hard one)
    assert outs[8].ok and np.linalg.norm(outs[8].t - t) < 10.0 and rotation_error_deg(outs[8].R, R) < 3.0
    assert outs[8].evidence > outs[0].evidence + 0.2


@pytest.mark.parametrize("local_regions", [0, 8])
def test_posterior_window_holds_the_whole_images_values(scene_renderer, local_regions):
    """The posterior on a window around the silhouette (``reach`` px past its box besides the ring) equals the
    whole image's there, hidden pixels and all, with one histogram pair or one per sector; and refinement on
    windows gives the whole image's poses, bit for bit."""
    model = procedural_objects(obj_ids=[3])[0]
    image, R, t = _scene(scene_renderer, model)
    ref = RegionRefiner(config=RegionRefineConfig(local_regions=local_regions))
    s = ref.config.viewport
    sil = np.zeros((s, s), np.uint8)
    sil[60:130, 50:120] = 1
    hidden = np.zeros_like(sil, bool)
    hidden[60:80, 50:120] = True
    A = np.array([[0.6, 0.0, 250.0], [0.0, 0.6, 180.0]])  # viewport px -> image px
    full, sil_full, o_full = ref._posterior(image, sil, A, 45.0, hidden)
    win, sil_win, (x0, y0) = ref._posterior(image, sil, A, 45.0, hidden, reach=20.0)
    assert o_full == (0, 0) and win.shape[0] < 480 / 2 and win.shape[1] < 640 / 2
    # the window: the silhouette's image box [280, 322) x [216, 258) grown by the reach and 3 px
    assert (x0, y0) == (280 - 23, 216 - 23)
    np.testing.assert_array_equal(win, full[y0:y0 + win.shape[0], x0:x0 + win.shape[1]])
    np.testing.assert_array_equal(sil_win, sil_full[y0:y0 + win.shape[0], x0:x0 + win.shape[1]])
    assert sil_full.sum() == sil_win.sum() > 0
    R0, t0 = _perturbed(R, t)
    windowed = ref.refine(image, model, R0, t0, LINEMOD_K)
    ref._full_frame = True
    whole = ref.refine(image, model, R0, t0, LINEMOD_K)
    assert windowed.ok and np.array_equal(windowed.R, whole.R) and np.array_equal(windowed.t, whole.t)
    assert windowed.evidence == whole.evidence and rotation_error_deg(windowed.R, R) < 2.0
    ref.close()


def test_cover_box_brings_a_too_far_pose_up_to_the_rendered_silhouettes_box(scene_renderer):
    """The box is the rendered mask's (not a projection of the same points): a pose 15 % too far comes back
    to the true depth within the mask's pixel quantisation; one too near, or at the truth, stays."""
    model = procedural_objects(obj_ids=[3])[0]
    R, t = pose_from_view(0.7, 0.5, 650.0, 0.3)
    t = t + np.array([30.0, -20.0, 0.0])
    mask = scene_renderer.render([(model, R, t)]).depth > 0
    ys, xs = np.nonzero(mask)
    box = np.array([xs.min(), ys.min(), xs.max() + 1 - xs.min(), ys.max() + 1 - ys.min()], np.float64)
    t_far, f = cover_box(model.vertices, R, t * 1.15, LINEMOD_K, box, mask.shape)
    assert f < 1 and abs(t_far[2] / t[2] - 1) < 0.01
    assert np.allclose(np.cross(t_far, t), 0, atol=1e-6 * t[2] ** 2)  # along the estimate's ray
    for near in (0.9, 1.0 - 0.015):
        t_near, f = cover_box(model.vertices, R, t * near, LINEMOD_K, box, mask.shape)
        assert f == 1.0 and np.array_equal(t_near, t * near)
    assert cover_box(model.vertices, R, t * 1.15, LINEMOD_K, [10, 10, 0, 5], mask.shape)[1] == 1.0  # empty box
    assert cover_box(model.vertices, R, -t, LINEMOD_K, box, mask.shape)[1] == 1.0  # behind the camera


@pytest.mark.parametrize("when", ["before", "after"])
def test_refine_poses_covers_the_detection_box(when):
    """``cover_box``: a pose too small for its box moves closer (recorded in ``cover_factor``), one without a
    box stays; on an image with no evidence the region steps change nothing, so both orders give the same."""
    from kpd6d.geometry import project_points

    model = procedural_objects(obj_ids=[1])[0]
    R, t = pose_from_view(0.7, 0.5, 650.0, 0.3)
    uv = project_points(model.vertices, LINEMOD_K, R, t)
    box = np.concatenate([uv.min(0), uv.max(0) - uv.min(0)])
    flat = np.full((480, 640, 3), 128, np.uint8)
    ref = RegionRefiner(RegionRefineConfig(cover_box=when), models={1: model})
    poses = [[{"obj_id": 1, "R": R, "t": t * 1.2, "ok": True, "box": box},
              {"obj_id": 1, "R": R, "t": t * 1.2, "ok": True}]]
    boxed, unboxed = ref.refine_poses([flat], LINEMOD_K[None], poses)[0]
    assert boxed["refined"] and np.allclose(boxed["t"], t, rtol=1e-3) and boxed["cover_factor"] == pytest.approx(1 / 1.2, rel=1e-3)
    assert not unboxed["refined"] and np.array_equal(unboxed["t"], t * 1.2) and "cover_factor" not in unboxed
    with pytest.raises(ValueError, match="cover_box must be one of none, before, after, got 'always'"):
        RegionRefineConfig(cover_box="always")


def test_depth_hypotheses_keep_the_start_whose_refinement_the_image_confirms_most(scene_renderer):
    """From 40 % too far one start alone stays short of the truth; with a second start at the true depth the
    kept refinement is that one (the most evidence), and the first factor alone equals plain refinement."""
    model = procedural_objects(obj_ids=[3])[0]
    image, R, t = _scene(scene_renderer, model)
    far = t * 1.4
    single = RegionRefiner(models={3: model})
    both = RegionRefiner(RegionRefineConfig(depth_hypotheses=(1.0, 1 / 1.4)), models={3: model})
    one = single.refine_poses([image], LINEMOD_K[None], [[{"obj_id": 3, "R": R, "t": far, "ok": True}]])[0][0]
    two = both.refine_poses([image], LINEMOD_K[None], [[{"obj_id": 3, "R": R, "t": far, "ok": True}]])[0][0]
    err_one, err_two = np.linalg.norm(one["t"] - t), np.linalg.norm(two["t"] - t)
    assert err_two < 5.0 < err_one and two["evidence"] > one["evidence"]
    plain = single.refine(image, model, R, far, LINEMOD_K)
    assert np.allclose(one["t"], plain.t) and one["evidence"] == plain.evidence
    with pytest.raises(ValueError, match=r"depth_hypotheses must be factors in \[0.5, 2\]"):
        RegionRefineConfig(depth_hypotheses=(1.0, 3.0))
    single.close()
    both.close()


def test_roll_hypotheses_recover_an_in_plane_turn_the_prior_holds_back(scene_renderer):
    """A start turned 45 degrees about its line of sight: one refinement, held by the rotation prior, stays
    turned; with roll starts of -45 / +45 degrees the kept one is the unturned pose (the most evidence).
    A roll start turns the object about its own centre, which stays where it was."""
    from kpd6d.geometry import project_points

    model = procedural_objects(obj_ids=[3])[0]
    image, R, t = _scene(scene_renderer, model)
    centre = np.asarray(model.mesh.bounds).mean(0)
    c = R @ centre + t
    axis = c / np.linalg.norm(c)
    Q = rotation_about_axis(axis, np.radians(45.0))
    R0, t0 = Q @ R, Q @ (t - c) + c
    np.testing.assert_allclose(R0 @ centre + t0, c, atol=1e-9)
    np.testing.assert_allclose(project_points(centre[None], LINEMOD_K, R0, t0), project_points(centre[None], LINEMOD_K, R, t), atol=1e-9)
    single = RegionRefiner(models={3: model})
    rolled = RegionRefiner(RegionRefineConfig(roll_hypotheses=(-45.0, 45.0)), models={3: model})
    one = single.refine_poses([image], LINEMOD_K[None], [[{"obj_id": 3, "R": R0, "t": t0, "ok": True}]])[0][0]
    best = rolled.refine_poses([image], LINEMOD_K[None], [[{"obj_id": 3, "R": R0, "t": t0, "ok": True}]])[0][0]
    assert rotation_error_deg(one["R"], R) > 10.0 > 2.0 > rotation_error_deg(best["R"], R)
    assert best["evidence"] > one["evidence"] and np.linalg.norm(best["t"] - t) < 5.0
    assert rolled.settings()["roll_hypotheses"] == [-45.0, 45.0]
    for bad in ((0.0,), (120.0,)):
        with pytest.raises(ValueError, match=r"roll_hypotheses must be non-zero angles in \[-90, 90\]"):
            RegionRefineConfig(roll_hypotheses=bad)
    single.close()
    rolled.close()
