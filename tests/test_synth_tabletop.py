"""Synthetic data engine, ``layout: tabletop``: objects resting on a textured table seen from above.

The annotations are checked against independent computations (object-alone renders by a separate
renderer, a numpy rasterizer, projected vertices, the table frame), as tests/test_synth.py does for
the free layout; plus resting poses, camera ranges, determinism, and that the free layout is unchanged.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from kpd6d.data import BopDataset
from kpd6d.geometry import project_points
from kpd6d.synth import SynthConfig, generate_dataset
from synth_helpers import SMALL, tree_bytes, write_models

#: 160x120, objects ~20-50 px; tabletop, 1-3 objects (the two test models, repeated), 0-2 occluders
TT = dict(SMALL, distance_range=(300.0, 600.0), layout="tabletop")


@pytest.fixture(scope="module")
def models_dir(tmp_path_factory) -> Path:
    return write_models(tmp_path_factory.mktemp("models"))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, models_dir) -> Path:
    """10 table-top images; half the occluder pool printed cards and boxes, sheets on half the tables."""
    root = tmp_path_factory.mktemp("tabletop")
    generate_dataset(root, models_dir, num_images=10, seed=5, progress=False, objects_per_image=(1, 3),
                     distractors=(0, 2), depth=True, visib_fract_range=(0.0, 1.0), printed_matter=0.5, **TT)
    return root


def _composer(models_dir, width=160, height=120, seed=0, **options):
    """A SceneComposer as the generator's workers build it (its samples expose the table pose)."""
    from kpd6d.objects import load_bop_models
    from kpd6d.render import Renderer
    from kpd6d.symmetry import handler_for_model
    from kpd6d.synth.backgrounds import ProceduralBackgrounds
    from kpd6d.synth.distractors import distractor_pool
    from kpd6d.synth.scene import SceneComposer

    opts = {**TT, "width": width, "height": height, **options}
    cfg = SynthConfig.from_options(opts)
    models = load_bop_models(models_dir)
    renderer = Renderer(cfg.width, cfg.height, cfg.camera_K(), antialias=cfg.antialias)
    pool = distractor_pool(seed, 8) if cfg.distractors[1] > 0 else []
    return SceneComposer(renderer, models, cfg, ProceduralBackgrounds(), pool, [handler_for_model(m) for m in models])


@pytest.fixture(scope="module")
def samples(models_dir):
    """12 composed table-top images with 2-3 objects and 1-3 occluders (half of them resting)."""
    comp = _composer(models_dir, objects_per_image=(2, 3), distractors=(1, 3), visib_fract_range=(0.0, 1.0))
    out = [comp.compose(np.random.default_rng([21, i])) for i in range(12)]
    comp.renderer.close()
    return comp.models, comp.cfg, out


def _to_table(sample, points, R, t):
    """Model points at camera pose (R, t) in the table frame."""
    Rw, tw = sample.table.R_w2c, sample.table.t_w2c
    return (points @ R.T + t - tw) @ Rw


def _rasterize(model, K, R, t, width, height, pad=0):
    """Independent silhouette (as in tests/test_synth.py): pixel centres inside any projected triangle."""
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
        canvas[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1] |= (e >= 0).all(0) | (e <= 0).all(0)
    return canvas


def _convex_polygons_disjoint(P: np.ndarray, Q: np.ndarray, gap: float = 0.0) -> bool:
    """Separating-axis test for the convex hulls of 2-D point sets P and Q."""
    from scipy.spatial import ConvexHull

    polys = [X[ConvexHull(X).vertices] for X in (P, Q)]
    for poly in polys:
        edges = np.roll(poly, -1, axis=0) - poly
        for nx, ny in np.stack([edges[:, 1], -edges[:, 0]], 1):
            n = np.array([nx, ny]) / math.hypot(nx, ny)
            a, b = polys[0] @ n, polys[1] @ n
            if a.max() + gap <= b.min() or b.max() + gap <= a.min():
                return True
    return False


# ---------------------------------------------------------------------------------------------
# ground truth against independent computation (generated dataset)
# ---------------------------------------------------------------------------------------------
def test_unoccluded_masks_match_object_alone_renders(dataset):
    """(a) an unoccluded object's visible mask is its object-alone silhouette: the table took nothing."""
    from kpd6d.render import Renderer

    ds = BopDataset(dataset, "train")
    models = {m.obj_id: m for m in ds.load_models()}
    r = Renderer(160, 120, ds[0].K, antialias=False)  # an independent renderer
    checked = 0
    for f in ds:
        for inst in f.instances:
            if inst.px_count_visib != inst.px_count_all or inst.px_count_all < 30:
                continue
            mask = f.load_mask_visib(inst.gt_index)
            alone = r.render([(models[inst.obj_id], inst.R, inst.t)], K=f.K, depth_only=True).masks_visib[0]
            iou = (mask & alone).sum() / (mask | alone).sum()
            assert iou > 0.98, (f.im_id, inst.gt_index, iou)
            sil = _rasterize(models[inst.obj_id], f.K, inst.R, inst.t, 160, 120)  # GL-free
            assert (mask & sil).sum() / (mask | sil).sum() >= 0.95
            checked += 1
    r.close()
    assert checked >= 8


def test_bbox_obj_matches_projected_vertices(dataset):
    """(b)"""
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
    assert n >= 15


def test_counts_and_visible_fraction_agree_with_masks(dataset):
    """(c) px counts / visib_fract vs the masks and an independent rasterization (also off-image)."""
    ds = BopDataset(dataset, "train")
    models = {m.obj_id: m for m in ds.load_models()}
    occluded = 0
    for f in ds:
        for inst in f.instances:
            mask = f.load_mask_visib(inst.gt_index)
            assert inst.px_count_visib == mask.sum()
            if mask.any():
                ys, xs = np.nonzero(mask)
                assert list(inst.bbox_visib) == [xs.min(), ys.min(), xs.max() - xs.min(), ys.max() - ys.min()]
            assert inst.visib_fract == pytest.approx(inst.px_count_visib / inst.px_count_all)
            sil = _rasterize(models[inst.obj_id], f.K, inst.R, inst.t, 160, 120, pad=100)
            assert abs(int(sil.sum()) - inst.px_count_all) <= 0.01 * inst.px_count_all + 2
            assert abs(int(sil[100:-100, 100:-100].sum()) - inst.px_count_valid) <= 0.01 * inst.px_count_valid + 2
            assert (mask & ~sil[100:-100, 100:-100]).sum() <= 0.01 * mask.sum() + 2
            occluded += inst.visib_fract < 0.98
    assert occluded >= 2  # objects and occluders do cover objects


def test_depth_holds_the_table_and_matches_poses(dataset):
    ds = BopDataset(dataset, "train")
    models = {m.obj_id: m for m in ds.load_models()}
    for f in ds[:5]:
        depth = f.load_depth()
        union = np.zeros(depth.shape, bool)
        for inst in f.instances:
            mask = f.load_mask_visib(inst.gt_index)
            union |= mask
            z = depth[mask]
            pts = models[inst.obj_id].vertices @ inst.R.T + inst.t
            assert (z > 0).all() and z.min() >= pts[:, 2].min() - 1.0 and z.max() <= pts[:, 2].max() + 1.0
        assert (depth[~union] > 0).mean() > 0.3  # the table is in the depth image


def test_symmetric_poses_are_canonical(dataset):
    """(5) the cylinder (continuous symmetry about z) gets canonical ground truth."""
    from kpd6d.symmetry import handler_for_model

    ds = BopDataset(dataset, "train", obj_ids=[2])
    handler = handler_for_model(ds.load_models()[0])
    assert len(ds) >= 2
    for f in ds:
        for inst in f.instances:
            R2, t2 = handler.canonicalize(inst.R, inst.t)
            np.testing.assert_allclose(R2, inst.R, atol=1e-6)
            np.testing.assert_allclose(t2, inst.t, atol=1e-4)


# ---------------------------------------------------------------------------------------------
# the table: never an occluder, objects rest on it, camera ranges (composed samples)
# ---------------------------------------------------------------------------------------------
def test_table_never_removes_object_pixels(samples, models_dir):
    """(a) the masks equal an independent segmentation of the objects and occluders *without* the
    table; and, numerically, with the table in the scene its depth is never nearer than an object's
    at the object's pixels beyond the tolerance used at contact points."""
    from kpd6d.render import Renderer
    from kpd6d.synth.tabletop import depth_tolerance

    models, cfg, out = samples
    r = Renderer(cfg.width, cfg.height, cfg.camera_K(), antialias=False)
    by_id = {m.obj_id: m for m in models}
    worst, compared = -np.inf, 0
    for s in out:
        objs = [(by_id[i.obj_id], i.R, i.t) for i in s.instances]
        ref = r.render(objs + s.distractor_items, K=s.K, depth_only=True)  # no table
        for inst, m in zip(s.instances, ref.masks_visib):
            np.testing.assert_array_equal(inst.mask_visib, m)
            compared += int(m.sum())
        for obj in objs:
            alone = r.render([obj], K=s.K, depth_only=True)
            with_table = r.render([obj, (s.table.mesh, s.table.R_w2c, s.table.t_w2c)], K=s.K, masks=False)
            px = alone.masks_visib[0]
            z_obj, z_all = alone.depth[px].astype(np.float64), with_table.depth[px].astype(np.float64)
            worst = max(worst, float((z_obj - z_all - depth_tolerance(z_obj, r.znear)).max()))
    r.close()
    assert compared > 2000
    assert worst <= 0.0  # the table is behind every object pixel (up to depth-buffer ties at the contact)


def test_contact_ties_with_the_table_keep_object_pixels():
    """The worst case of contact: a two-sided sheet lying flat on the table, i.e. coplanar with it, so
    the colour pass z-fights. Comparing depths alone (the free layout's rule) would hide a good part of
    it; the table-plane test keeps every pixel: the masks equal a segmentation without the table."""
    import trimesh

    from kpd6d.objects import ObjectModel
    from kpd6d.render import Renderer
    from kpd6d.synth.backgrounds import ProceduralBackgrounds
    from kpd6d.synth.distractors import distractor_pool
    from kpd6d.synth.scene import SceneComposer

    v = np.array([[-50.0, -50.0, 0.0], [50.0, -50.0, 0.0], [50.0, 50.0, 0.0], [-50.0, 50.0, 0.0]])
    sheet = trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]], process=False)
    sheet.visual = trimesh.visual.ColorVisuals(sheet, vertex_colors=np.tile([200, 120, 60, 255], (4, 1)).astype(np.uint8))
    model = ObjectModel(7, sheet)
    cfg = SynthConfig.from_options({**TT, "distance_range": (700.0, 1000.0), "distractors": (1, 1),
                                    "table_distractor_rest_prob": 0.0, "visib_fract_range": (0.0, 1.0),
                                    "max_retries": 0})
    r = Renderer(cfg.width, cfg.height, cfg.camera_K(), antialias=False)
    comp = SceneComposer(r, [model], cfg, ProceduralBackgrounds(), distractor_pool(0, 4))
    fights = kept = 0
    for i in range(6):
        s = comp.compose(np.random.default_rng([5, i]))
        inst = s.instances[0]
        assert abs(_to_table(s, v, inst.R, inst.t)[:, 2]).max() < 1e-6  # coplanar with the table
        alone = r.render([(model, inst.R, inst.t)], K=s.K, depth_only=True)
        with_table = r.render([(model, inst.R, inst.t), (s.table.mesh, s.table.R_w2c, s.table.t_w2c)], K=s.K,
                              masks=False)
        naive = alone.masks_visib[0] & (with_table.depth < alone.depth * (1.0 - 1e-6) - 1e-3)
        ref = r.render([(model, inst.R, inst.t), *s.distractor_items], K=s.K, depth_only=True).masks_visib[0]
        np.testing.assert_array_equal(inst.mask_visib, ref)
        fights += int(naive.sum())
        kept += int((naive & inst.mask_visib).sum())
    r.close()
    assert fights > 50 and kept > 0.5 * fights  # the scenario does tie, and the ties stay in the masks


def test_objects_rest_on_the_table_without_interpenetrating(samples):
    """(d) in the table frame every object's lowest vertex is at height 0 (< 0.5 mm), its footprint
    lies on the table top, footprints of objects (and of resting occluders) are disjoint, and
    floating occluders are above the table."""
    models, _, out = samples
    by_id = {m.obj_id: m for m in models}
    pairs = resting_d = 0
    for s in out:
        x0, x1, y0, y1 = s.table.extent
        feet = []
        for inst in s.instances:
            v = _to_table(s, by_id[inst.obj_id].vertices, inst.R, inst.t)
            assert abs(v[:, 2].min()) < 0.5, v[:, 2].min()
            assert v[:, 0].min() >= x0 and v[:, 0].max() <= x1 and v[:, 1].min() >= y0 and v[:, 1].max() <= y1
            feet.append(v[:, :2])
        for mesh, R, t in s.distractor_items:
            v = _to_table(s, np.asarray(mesh.vertices), R, t)
            assert v[:, 2].min() > -0.5
            if v[:, 2].min() < 0.5:  # resting on the table
                feet.append(v[:, :2])
                resting_d += 1
        for i in range(len(feet)):
            for j in range(i):
                assert _convex_polygons_disjoint(feet[i], feet[j]), (i, j)
                pairs += 1
    assert pairs >= 20 and resting_d >= 3


def test_objects_are_clustered_and_occlude_each_other(samples):
    _, cfg, out = samples
    mutual = 0
    for s in out:
        for inst in s.instances:
            p = _to_table(s, np.zeros((1, 3)), inst.R, inst.t)[0]
            assert math.hypot(p[0], p[1]) < 3 * cfg.table_cluster_radius * s.table.distance + 60
            x, y, w, h = inst.bbox_obj
            assert x >= -0.1 * w - 1 and y >= -0.1 * h - 1 and x + w <= 160 + 0.1 * w and y + h <= 120 + 0.1 * h
        masks = [i.mask_visib for i in s.instances]
        mutual += any(i.visib_fract < 0.95 for i in s.instances)
        assert not np.any(np.sum(masks, axis=0) > 1)  # a pixel belongs to one object at most
    assert mutual >= 2


def test_camera_elevation_roll_and_distance_within_ranges(models_dir):
    """(e) elevation of the optical axis above the table plane, roll, distance to the look-at point."""
    comp = _composer(models_dir, objects_per_image=(1, 2), distractors=(0, 0), table_elevation_range=(40.0, 50.0),
                     table_roll_range=(-10.0, 5.0), max_retries=0)
    els = []
    for i in range(10):
        s = comp.compose(np.random.default_rng([3, i]))
        R, t = s.table.R_w2c, s.table.t_w2c
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
        el = math.degrees(math.asin(-R[2, 2]))  # optical axis (row 2) against the table plane
        roll = math.degrees(math.asin(np.clip(R[0, 2] / math.cos(math.radians(el)), -1, 1)))
        centre = -R.T @ t
        assert 40.0 - 1e-6 <= el <= 50.0 + 1e-6 and -10.0 - 1e-6 <= roll <= 5.0 + 1e-6
        assert centre[2] > 0  # above the table
        assert 300.0 - 1e-6 <= np.linalg.norm(centre) <= 600.0 + 1e-6
        np.testing.assert_allclose(t[:2], 0.0, atol=1e-9)  # the look-at point is on the optical axis
        els.append(el)
    comp.renderer.close()
    assert max(els) - min(els) > 3


def test_table_meshes_do_not_accumulate(models_dir):
    """Each image has its own table mesh and texture; they leave the renderer's cache and GL context."""
    comp = _composer(models_dir, distractors=(1, 1), max_retries=0)
    sizes = []
    for i in range(5):
        comp.compose(np.random.default_rng([4, i]))
        gl_meshes = comp.renderer._renderer._renderer._meshes
        sizes.append((len(comp.renderer._cache), len(gl_meshes)))
    comp.renderer.close()
    assert max(c for c, _ in sizes) <= 2 + 8  # the models and the occluder pool, no tables
    assert max(g for _, g in sizes) <= 2 + 8 + 1


def test_stable_poses_are_stable():
    """A resting rotation puts a hull face down with the centre of mass above it; a box rests most
    often on its largest faces, a cylinder mostly on its side."""
    import trimesh
    from scipy.spatial import Delaunay

    from kpd6d.synth.tabletop import center_of_mass, stable_poses

    box = trimesh.creation.box((60.0, 40.0, 30.0))
    cyl = trimesh.creation.cylinder(radius=25.0, height=70.0, sections=32)
    cone = trimesh.creation.cone(radius=30.0, height=80.0, sections=32)
    for mesh in (box, cyl, cone):
        com = center_of_mass(mesh)
        rots, probs = stable_poses(np.asarray(mesh.vertices), com)
        assert probs.sum() == pytest.approx(1.0) and (np.diff(probs) <= 1e-12).all()
        for R in rots:
            v = np.asarray(mesh.vertices) @ R.T
            c = R @ com
            base = v[v[:, 2] < v[:, 2].min() + 1e-6][:, :2]
            assert len(base) >= 3  # a face, not an edge or a vertex
            assert Delaunay(base).find_simplex(c[:2]) >= 0
    rots, probs = stable_poses(np.asarray(box.vertices), center_of_mass(box))
    assert len(probs) == 6
    down = [np.round(R.T @ [0, 0, -1.0]).tolist() for R in rots[:2]]
    assert sorted(down) == [[0, 0, -1], [0, 0, 1]]  # the 60x40 faces first
    rots, probs = stable_poses(np.asarray(cyl.vertices), center_of_mass(cyl))
    caps = [p for R, p in zip(rots, probs) if abs((R.T @ [0, 0, 1.0])[2]) > 0.99]
    assert len(caps) == 2 and 0.1 < sum(caps) < 0.3  # standing ~19 % (solid angle of the caps)


def test_table_camera_geometry():
    from kpd6d.synth.tabletop import table_camera

    for el, az, roll in ((30.0, 0.0, 0.0), (90.0, 45.0, 10.0), (15.0, 200.0, -15.0)):
        R, t = table_camera(math.radians(el), math.radians(az), 800.0, math.radians(roll))
        assert np.linalg.det(R) == pytest.approx(1.0)
        centre = -R.T @ t
        assert centre[2] == pytest.approx(800.0 * math.sin(math.radians(el)))
        np.testing.assert_allclose(t, [0.0, 0.0, 800.0], atol=1e-9)
        if roll == 0.0:
            up = R @ [0.0, 0.0, 1.0]
            assert abs(up[0]) < 1e-9 and up[1] < 0  # the table normal points up in the image


# ---------------------------------------------------------------------------------------------
# fast (two-pass) and full-segmentation paths, determinism, free layout unchanged
# ---------------------------------------------------------------------------------------------
def test_two_pass_and_full_segmentation_paths_agree(tmp_path, models_dir):
    """antialias=False hides object pixels where the colour pass (table included) is nearer, except
    at table-plane ties; antialias=True segments objects and occluders without the table. Same GT."""
    run = dict(num_images=5, seed=13, progress=False, objects_per_image=(2, 3), distractors=(1, 2), depth=True,
               visib_fract_range=(0.0, 1.0), **TT)
    generate_dataset(tmp_path / "fast", models_dir, antialias=False, **run)
    generate_dataset(tmp_path / "aa", models_dir, antialias=True, **run)
    fast, aa = tree_bytes(tmp_path / "fast"), tree_bytes(tmp_path / "aa")
    names = [n for n in fast if "mask_visib" in n or n.endswith(("scene_gt.json", "scene_gt_info.json"))]
    assert len(names) > 10
    for n in names:
        assert fast[n] == aa[n], n
    info = BopDataset(tmp_path / "fast", "train")
    assert any(i.visib_fract < 0.95 for f in info for i in f.instances)
    for f_fast, f_aa in zip(info, BopDataset(tmp_path / "aa", "train")):
        union = np.zeros((120, 160), bool)
        for i in f_fast.instances:
            union |= f_fast.load_mask_visib(i.gt_index)
        np.testing.assert_allclose(f_fast.load_depth()[union], f_aa.load_depth()[union], atol=0.1)


def test_same_seed_same_bytes_other_seed_differs(tmp_path, models_dir):
    """(f)"""
    run = dict(num_images=3, progress=False, objects_per_image=(1, 2), distractors=(1, 1), **TT)
    generate_dataset(tmp_path / "a", models_dir, seed=1, **run)
    generate_dataset(tmp_path / "b", models_dir, seed=1, **run)
    generate_dataset(tmp_path / "c", models_dir, seed=2, **run)
    a, b, c = (tree_bytes(tmp_path / x) for x in "abc")
    assert a == b
    assert a["train/000000/rgb/000000.jpg"] != c["train/000000/rgb/000000.jpg"]
    assert a["train/000000/scene_gt.json"] != c["train/000000/scene_gt.json"]
    settings = json.loads(a["dataset_info.json"])["splits"]["train"]["config"]
    assert settings["layout"] == "tabletop" and settings["table_elevation_range"] == [15.0, 75.0]


def test_free_layout_is_unchanged(tmp_path, models_dir):
    """(g) layout='free' given explicitly or not: the same bytes, dataset_info.json included (the
    table options are not recorded for the free layout, so datasets made before them resume)."""
    run = dict(num_images=3, seed=3, progress=False, distractors=(1, 1), **SMALL)
    generate_dataset(tmp_path / "implicit", models_dir, **run)
    generate_dataset(tmp_path / "explicit", models_dir, layout="free", table_roll_range=(-15, 15), **run)
    assert tree_bytes(tmp_path / "implicit") == tree_bytes(tmp_path / "explicit")
    settings = json.loads((tmp_path / "implicit" / "dataset_info.json").read_text())["splits"]["train"]["config"]
    assert not [k for k in settings if k == "layout" or k.startswith("table_")]
    assert "table_size_range" in SynthConfig.from_options({"layout": "free", "table_size_range": (500, 900)}).to_dict()


def test_bad_layout_options_are_named(tmp_path, models_dir):
    """(h)"""
    with pytest.raises(ValueError, match=r"layout must be one of 'free', 'tabletop', got 'table'"):
        SynthConfig.from_options({"layout": "table"})
    with pytest.raises(ValueError, match="layout"):
        generate_dataset(tmp_path, models_dir, num_images=1, progress=False, layout="Tabletop")
    bad = {
        "table_elevation_range": [(0.0, 45.0), (60.0, 20.0), (10.0, 95.0), "high"],
        "table_roll_range": [(-200.0, 0.0), (5.0, -5.0)],
        "table_size_range": [(0.0, 100.0), (900.0, 800.0)],
        "table_cluster_radius": [0.0, -1.0, float("nan"), "wide"],
        "table_distractor_rest_prob": [1.5, -0.1],
    }
    for name, values in bad.items():
        for value in values:
            with pytest.raises(ValueError, match=name):
                SynthConfig.from_options({"layout": "tabletop", name: value})


def test_upright_objects_stand_as_modelled_and_indoor_lighting(models_dir):
    """table_upright_prob=1: every object's model +z is the table normal (and it still rests on the
    table); lighting=indoor renders and stays deterministic."""
    comp = _composer(models_dir, objects_per_image=(2, 3), distractors=(0, 1), visib_fract_range=(0.0, 1.0),
                     table_upright_prob=1.0, lighting="indoor", canonicalize_symmetric=False)
    by_id = {m.obj_id: m for m in comp.models}
    for i in range(4):
        s = comp.compose(np.random.default_rng([31, i]))
        for inst in s.instances:
            R_mw = s.table.R_w2c.T @ inst.R  # model -> table frame
            np.testing.assert_allclose(R_mw[:, 2], [0.0, 0.0, 1.0], atol=1e-9)
            assert abs(_to_table(s, by_id[inst.obj_id].vertices, inst.R, inst.t)[:, 2].min()) < 0.5
        again = comp.compose(np.random.default_rng([31, i]))
        assert np.array_equal(again.rgb, s.rgb)
    with pytest.raises(ValueError, match="table_upright_prob must lie in"):
        SynthConfig.from_options({"table_upright_prob": 1.5})
    with pytest.raises(ValueError, match="lighting must be 'random', 'indoor', 'mixed' or 'fixed', got 'sunny'"):
        SynthConfig.from_options({"lighting": "sunny"})


def test_mixed_lighting_lights_each_image_one_way_or_the_other(models_dir, monkeypatch):
    """lighting=mixed: each image is lit by Lighting.random or Lighting.random_indoor (both occur, about half
    and half, one per image), and an image stays deterministic for its seed."""
    from kpd6d.render import Lighting

    calls = []
    for name in ("random", "random_indoor"):
        orig = getattr(Lighting, name).__func__

        def spy(cls, rng, *a, _orig=orig, _name=name, **kw):
            calls.append(_name)
            return _orig(cls, rng, *a, **kw)

        monkeypatch.setattr(Lighting, name, classmethod(spy))
    comp = _composer(models_dir, objects_per_image=(1, 1), distractors=(0, 0), visib_fract_range=(0.0, 1.0),
                     lighting="mixed")
    n = 16
    for i in range(n):
        comp.compose(np.random.default_rng([7, i]))
    assert len(calls) == n and 4 <= calls.count("random") <= n - 4
    first = calls[:]
    calls.clear()
    a = comp.compose(np.random.default_rng([7, 3]))
    b = comp.compose(np.random.default_rng([7, 3]))
    assert calls == [first[3]] * 2 and np.array_equal(a.rgb, b.rgb)


def test_indoor_lighting_is_dimmer_on_average_and_tinted():
    from kpd6d.render import Lighting

    rng = np.random.default_rng(0)
    indoor = [Lighting.random_indoor(rng) for _ in range(300)]
    rand = [Lighting.random(rng) for _ in range(300)]

    def energy(lights):
        return np.mean([np.mean(li.ambient) + sum(x.intensity for x in li.lights) / len(li.lights) for li in lights])

    assert energy(indoor) < energy(rand)
    assert min(min(x.intensity for x in li.lights) for li in indoor) < 1.0  # dim scenes occur
    # warm and cool tints both occur (red/blue gain ratio above and below 1)
    ratios = [li.ambient[0] / li.ambient[2] for li in indoor]
    assert min(ratios) < 0.95 and max(ratios) > 1.05
    assert all(x.direction[1] > 0 for li in indoor for x in li.lights)  # from above (OpenCV y down)


def test_contrast_lighting_is_dim_ambient_one_strong_key_light_and_glossy_half_the_time():
    from kpd6d.render import Lighting

    rng = np.random.default_rng(0)
    lit = [Lighting.random_contrast(rng) for _ in range(300)]
    indoor = [Lighting.random_indoor(rng) for _ in range(300)]
    for li in lit:
        assert max(li.ambient) <= 0.35 * 1.2 + 1e-9 and 1 <= len(li.lights) <= 2
        assert 2.0 <= li.lights[0].intensity <= 5.0 and all(x.intensity <= 1.0 for x in li.lights[1:])
        assert all(x.direction[1] > 0 and x.direction[2] > 0 for x in li.lights)  # down onto the table, into the scene
        np.testing.assert_allclose([np.linalg.norm(x.direction) for x in li.lights], 1.0)
        assert li.specular == 0.0 or 0.35 <= li.specular <= 0.7
    # the key light outweighs the ambient far more than indoor lighting's strongest light does
    ratio = np.median([li.lights[0].intensity / np.mean(li.ambient) for li in lit])
    assert ratio > 3 * np.median([max(x.intensity for x in li.lights) / np.mean(li.ambient) for li in indoor])
    glossy = np.mean([li.specular > 0 for li in lit])
    assert 0.4 < glossy < 0.6
    assert all(Lighting.random_contrast(rng, gloss_prob=0.0).specular == 0.0 for _ in range(20))
    a, b = (Lighting.random_contrast(np.random.default_rng(5)) for _ in range(2))
    assert a == b


def test_contrast_lighting_replaces_the_style_on_its_share_of_images(models_dir, monkeypatch):
    """contrast_lighting=p: that share of the images is lit by Lighting.random_contrast instead of the style's
    lighting (each image deterministic for its seed); at 0 it is never drawn. The options are checked and
    left out of the recorded settings while at their defaults (earlier datasets resume)."""
    from kpd6d.render import Lighting

    calls = []
    orig = Lighting.random_contrast.__func__

    def spy(cls, rng, *a, **kw):
        calls.append(1)
        return orig(cls, rng, *a, **kw)

    monkeypatch.setattr(Lighting, "random_contrast", classmethod(spy))
    comp = _composer(models_dir, objects_per_image=(1, 1), distractors=(0, 0), visib_fract_range=(0.0, 1.0),
                     lighting="indoor", contrast_lighting=0.5)
    n = 16
    for i in range(n):
        comp.compose(np.random.default_rng([9, i]))
    assert 4 <= len(calls) <= n - 4
    a, b = (comp.compose(np.random.default_rng([9, 2])) for _ in range(2))
    assert np.array_equal(a.rgb, b.rgb)
    calls.clear()
    off = _composer(models_dir, objects_per_image=(1, 1), distractors=(0, 0), visib_fract_range=(0.0, 1.0),
                    lighting="indoor")
    for i in range(4):
        off.compose(np.random.default_rng([9, i]))
    assert calls == []
    with pytest.raises(ValueError, match=r"contrast_lighting must be a number in \[0, 1\], got 1.5"):
        SynthConfig.from_options({"contrast_lighting": 1.5})
    with pytest.raises(ValueError, match="smooth_objects must be true or false, got 'yes'"):
        SynthConfig.from_options({"smooth_objects": "yes"})
    d = SynthConfig.from_options({}).to_dict()
    assert "contrast_lighting" not in d and "smooth_objects" not in d
    d = SynthConfig.from_options({"contrast_lighting": 0.5, "smooth_objects": True}).to_dict()
    assert d["contrast_lighting"] == 0.5 and d["smooth_objects"] is True


def test_smooth_objects_change_only_the_colours(tmp_path, models_dir):
    """smooth_objects shades the objects differently and changes nothing else: same poses, boxes, masks and
    visible fractions for the same seed (the option draws no random numbers)."""
    roots = {}
    for smooth in (False, True):
        roots[smooth] = generate_dataset(tmp_path / str(smooth), models_dir=models_dir, num_images=3, seed=4,
                                         progress=False, **{**TT, "objects_per_image": (2, 2), "distractors": (1, 1),
                                                            "contrast_lighting": 1.0, "smooth_objects": smooth})
    a, b = (BopDataset(roots[s], "train") for s in (False, True))
    assert len(a) == len(b) == 3
    differ = 0
    for i in range(3):
        x, y = a[i], b[i]
        assert [(g.obj_id, g.visib_fract) for g in x.instances] == [(g.obj_id, g.visib_fract) for g in y.instances]
        for g, h in zip(x.instances, y.instances):
            np.testing.assert_allclose(g.R, h.R)
            np.testing.assert_allclose(g.t, h.t)
            assert np.array_equal(g.bbox_visib, h.bbox_visib)
            assert np.array_equal(x.load_mask_visib(g.gt_index), y.load_mask_visib(h.gt_index))
        differ += int(not np.array_equal(x.load_rgb(), y.load_rgb()))
    assert differ == 3


def test_shadow_pose_flattens_along_the_light_onto_the_table():
    """Independent check: each flattened point is where the line through the posed point along the
    light direction meets the table plane (solved per point); grazing / upward light gives None."""
    from kpd6d.geometry import random_rotation
    from kpd6d.synth.tabletop import shadow_pose, table_camera

    rng = np.random.default_rng(3)
    R_w2c, t_w2c = table_camera(np.radians(40), np.radians(30), 900.0, np.radians(5))
    R = random_rotation(rng)
    t = np.array([20.0, -10.0, 850.0])
    d = np.array([0.3, 0.8, 0.5])  # camera frame: down in the image, away from the camera
    A, b = shadow_pose(R, t, R_w2c, t_w2c, d)
    pts = rng.normal(size=(20, 3)) * 50
    flat = pts @ A.T + b
    n, c = R_w2c[:, 2], float(R_w2c[:, 2] @ t_w2c)
    for p, q in zip(pts @ R.T + t, flat, strict=True):
        s = (c - n @ p) / (n @ d)  # p + s d on the plane
        np.testing.assert_allclose(q, p + s * d, atol=1e-9)
        assert abs(n @ q - c) < 1e-9
    up = R_w2c[:, 2]  # the table normal (up), in the camera frame
    assert shadow_pose(R, t, R_w2c, t_w2c, -up) is not None  # straight down: a shadow
    assert shadow_pose(R, t, R_w2c, t_w2c, up) is None  # from below the table
    graze = np.cross(R_w2c[:, 2], [1.0, 0.0, 0.0])
    assert shadow_pose(R, t, R_w2c, t_w2c, graze) is None  # parallel to the table


def test_cast_shadows_only_darken_the_table(models_dir):
    """table_shadow_prob: 1 against 0, same seeds: the same ground truth; pixels only get darker,
    never on an object's visible mask, and every image with a shadow is darker somewhere."""
    comp = _composer(models_dir, objects_per_image=(2, 3), distractors=(1, 3), photometric={"prob": 0},
                     table_shadow_prob=1.0)
    darker_images = 0
    for i in range(6):
        comp.cfg.table_shadow_prob = 0.0
        a = comp.compose(np.random.default_rng([4, i]))
        comp.cfg.table_shadow_prob = 1.0
        b = comp.compose(np.random.default_rng([4, i]))
        assert [x.obj_id for x in a.instances] == [x.obj_id for x in b.instances]
        for x, y in zip(a.instances, b.instances, strict=True):
            np.testing.assert_array_equal(x.R, y.R)
            np.testing.assert_array_equal(x.mask_visib, y.mask_visib)
        diff = a.rgb.astype(int) - b.rgb.astype(int)
        assert diff.min() >= -1  # never brighter (but for rounding)
        changed = (diff > 1).any(axis=2)
        objects = np.any([x.mask_visib for x in a.instances], axis=0)
        assert not (changed & objects).any()
        darker_images += bool(changed.sum() > 20)
    assert darker_images >= 4
    comp.renderer.close()
    from kpd6d.synth.config import SynthConfig

    with pytest.raises(ValueError, match="table_shadow_prob must lie in"):
        SynthConfig.from_options({"layout": "tabletop", "table_shadow_prob": 1.5})


def test_object_detail_touches_only_the_objects(models_dir):
    """``object_detail: 1``: the same scene as without it, but for the target objects' visible pixels (the
    camera effects off, so nothing else draws from the stream after it)."""
    opts = dict(objects_per_image=(2, 2), distractors=(1, 1), visib_fract_range=(0.0, 1.0), photometric={"prob": 0})
    plain = _composer(models_dir, **opts).compose(np.random.default_rng(4))
    detailed = _composer(models_dir, object_detail=1.0, **opts).compose(np.random.default_rng(4))
    objects = np.logical_or.reduce([inst.mask_visib for inst in plain.instances])
    assert objects.sum() > 100
    assert np.array_equal(plain.rgb[~objects], detailed.rgb[~objects])
    assert (plain.rgb[objects] != detailed.rgb[objects]).any(-1).mean() > 0.5
    assert all(np.array_equal(a.mask_visib, b.mask_visib) for a, b in zip(plain.instances, detailed.instances, strict=True))
