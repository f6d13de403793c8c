"""Renderer: silhouettes agree with geometry.project_points, depth with the pose, masks are consistent."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from matplotlib.path import Path
from scipy.spatial import ConvexHull

from kpd6d.geometry import LINEMOD_K, pose_from_view, project_points, transform_points
from kpd6d.objects import procedural_objects
from kpd6d.render import Renderer


@pytest.fixture(scope="module")
def renderer():
    r = Renderer(320, 240, LINEMOD_K * np.array([[0.5], [0.5], [1.0]]))
    yield r
    r.close()


@pytest.fixture(scope="module")
def objs():
    return procedural_objects(obj_ids=[1, 3, 4, 5])


def _mask_bbox(mask):
    ys, xs = np.nonzero(mask)
    return np.array([xs.min(), ys.min(), xs.max(), ys.max()], dtype=float)


@pytest.mark.parametrize("view", [(0.3, 0.5, 700.0, 0.0), (2.1, -0.4, 600.0, 0.6), (4.4, 1.1, 800.0, -1.2)])
def test_silhouette_matches_projected_vertices(renderer, objs, view):
    K = renderer.K
    R, t = pose_from_view(*view)
    t = t + np.array([25.0, -15.0, 0.0])  # off-centre as well
    for m in objs:
        res = renderer.render([(m, R, t)])
        uv = project_points(m.vertices, K, R, t)
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        box = _mask_bbox(res.masks_visib[0])
        # no silhouette pixel centre outside the projection's extent (pixel centres at integers)
        assert (box[:2] >= lo - 1e-6).all() and (box[2:] <= hi + 1e-6).all(), (m.name, box, lo, hi)
        # the box of pixel centres inside the projected convex hull (independent rasterisation)
        hull = Path(uv[ConvexHull(uv).vertices])
        xs, ys = np.meshgrid(np.arange(np.floor(lo[0]) - 1, np.ceil(hi[0]) + 2),
                             np.arange(np.floor(lo[1]) - 1, np.ceil(hi[1]) + 2))
        centres = np.c_[xs.ravel(), ys.ravel()]
        inside = centres[hull.contains_points(centres)]
        expected = np.r_[inside.min(0), inside.max(0)]
        assert np.abs(box - expected).max() <= 1.0, (m.name, box, expected)
        # every vertex projecting well inside the image lands on (or within 1 px of) the mask
        inside = (uv > 2).all(1) & (uv[:, 0] < renderer.width - 3) & (uv[:, 1] < renderer.height - 3)
        ij = np.rint(uv[inside]).astype(int)
        dil = cv2.dilate(res.masks_visib[0].astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        assert dil[ij[:, 1], ij[:, 0]].all()


def test_depth_matches_ray_casting(renderer, objs):
    """Depth at pixel centres equals the first hit of the ray through that pixel centre (trimesh)."""
    m = objs[1]
    R, t = pose_from_view(1.0, 0.7, 650.0, inplane=0.3)
    res = renderer.render([(m, R, t)])
    ys, xs = np.nonzero(res.masks_visib[0])
    pick = np.random.default_rng(0).choice(len(xs), 60, replace=False)
    uv = np.c_[xs[pick], ys[pick]].astype(float)
    rays_cam = np.c_[(uv - renderer.K[:2, 2]) / np.diag(renderer.K)[:2], np.ones(len(uv))]
    eye = -R.T @ t
    dirs = rays_cam @ R  # camera -> model frame directions (R^T d)
    locs, idx, _ = m.mesh.ray.intersects_location(np.repeat(eye[None], len(uv), 0), dirs, multiple_hits=False)
    assert len(idx) >= 0.95 * len(uv)  # (a few grazing rays may miss the tessellated surface)
    z_hit = transform_points(locs, R, t)[:, 2]
    z_ren = res.depth[ys[pick][idx], xs[pick][idx]]
    err = np.abs(z_hit - z_ren)
    assert np.median(err) < 0.2 and (err < 2.0).mean() > 0.95, err.max()
    # background pixels have no depth, and the lit texture shows
    assert (res.depth[~res.masks_visib[0]] == 0).all()
    assert res.rgb.dtype == np.uint8 and res.rgb[res.masks_visib[0]].mean() > 20


def test_masks_visib_subset_of_full_with_occlusion(renderer, objs):
    R, t = pose_from_view(0.8, 0.5, 700.0)
    insts = [(m, R, t + np.array([dx, dy, dz])) for m, (dx, dy, dz) in
             zip(objs, [(-60, 0, 0), (60, 20, 250), (200, -60, 500), (-30, 30, -250)])]
    res = renderer.render(insts, full_masks=True)
    union = np.zeros_like(res.depth, dtype=bool)
    for i, (v, f) in enumerate(zip(res.masks_visib, res.masks_full)):
        assert v.sum() > 0
        assert not (v & ~f).any(), f"instance {i}: visib pixels outside full"
        assert not (union & v).any(), "visible masks overlap"
        union |= v
        solo = renderer.render([insts[i]])
        assert np.array_equal(f, solo.depth > 0)  # full mask = silhouette of the instance alone
    # the visible masks cover the rendered object pixels except anti-aliased boundaries
    assert (res.depth > 0).sum() - union.sum() < 0.03 * union.sum()
    assert (union <= (res.depth > 0)).all()
    # occlusion: the nearest instance (last one, 250 mm closer) is fully visible
    assert res.masks_visib[3].sum() >= 0.97 * res.masks_full[3].sum()
    assert any(0 < v.sum() < 0.9 * f.sum() for v, f in zip(res.masks_visib, res.masks_full))  # real occlusion


def test_masks_without_full_are_consistent(renderer, objs):
    R, t = pose_from_view(2.5, 0.3, 700.0)
    insts = [(objs[0], R, t), (objs[1], R, t + np.array([30.0, 0.0, 80.0]))]
    res = renderer.render(insts)
    assert res.masks_full == []
    a, b = res.masks_visib
    assert not (a & b).any() and a.sum() > 0 and b.sum() > 0
    one = renderer.render([insts[0]], full_masks=True)
    assert np.array_equal(one.masks_visib[0], one.depth > 0)
    assert np.array_equal(one.masks_full[0], one.masks_visib[0])


def test_torchvision_ops_import_after_a_render_does_not_crash(tmp_path):
    """Mesa's llvmpipe and triton both bundle LLVM: importing triton (via torchvision.ops) after the
    first render used to kill the process with a segmentation fault. Run it in a fresh process."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        from kpd6d.objects import procedural_objects
        from kpd6d.render import Renderer
        from kpd6d.geometry import LINEMOD_K, pose_from_view
        m = procedural_objects(obj_ids=[1])[0]
        R, t = pose_from_view(0.3, 0.4, 500.0)
        K = LINEMOD_K * [[0.25], [0.25], [1.0]]
        assert Renderer(160, 120, K).render([(m, R, t)]).masks_visib[0].any()
        import torchvision.ops  # noqa: F401
        print("survived")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and "survived" in out.stdout, out.stderr[-2000:]


@pytest.mark.parametrize("kind", ["vertex", "face"])
def test_mesh_colours_render_as_stored_under_unit_light(renderer, kind):
    """Colours in meshes are sRGB-encoded: under unit ambient light (no other light) a flat patch
    renders as its stored colour, and under ambient ``a`` as that colour times ``a ** (1 / 2.2)``
    (the shader works in linear light and encodes with 1/2.2). Before the fix a stored 30 rendered as 96."""
    from kpd6d.render import Lighting

    rng = np.random.default_rng(0)
    R, t = np.eye(3), np.array([0.0, 0.0, 900.0])
    for _ in range(4):
        c = rng.integers(5, 250, 3)
        quad = trimesh_quad(c, kind)
        for a in (1.0, 0.25):
            rgb = renderer.render([(quad, R, t)], lighting=Lighting(ambient=(a, a, a), lights=[])).rgb
            want = np.clip(c / 255.0 * a ** (1 / 2.2), 0, 1) * 255
            np.testing.assert_allclose(rgb[120, 160].astype(float), want, atol=1.5, err_msg=f"{kind} {c} {a}")


def trimesh_quad(color, kind: str):
    import trimesh

    quad = trimesh.Trimesh(vertices=[[-80, -80, 0], [80, -80, 0], [80, 80, 0], [-80, 80, 0]],
                           faces=[[0, 2, 1], [0, 3, 2]], process=False)
    rgba = np.array([*color, 255], dtype=np.uint8)
    if kind == "vertex":
        quad.visual.vertex_colors = np.tile(rgba, (4, 1))
    else:
        quad.visual.face_colors = np.tile(rgba, (2, 1))
    return quad


def test_closing_one_renderer_leaves_the_others_working(objs):
    """pyrender's EGL teardown terminates the display all contexts share; Renderer.close must not, while
    another renderer of the process is open (a scene renderer beside a pose refiner's)."""
    from kpd6d.geometry import LINEMOD_K

    R, t = pose_from_view(0.3, 0.5, 700.0, 0.0)
    a, b = Renderer(160, 120, LINEMOD_K * np.array([[0.25], [0.25], [1.0]])), Renderer(96, 96)
    before = a.render([(objs[0], R, t)]).depth
    b.render([(objs[0], R, t)], depth_only=True)
    b.close()
    np.testing.assert_array_equal(a.render([(objs[0], R, t)]).depth, before)  # still renders, the same
    a.close()
    a.close()  # closing twice is harmless
    c = Renderer(160, 120, LINEMOD_K * np.array([[0.25], [0.25], [1.0]]))  # and a new one works after all closed
    np.testing.assert_array_equal(c.render([(objs[0], R, t)]).depth, before)
    c.close()


def test_pass_stats_count_the_passes_each_call_draws(renderer, objs):
    """render() draws one colour pass (unless depth_only), one segmentation pass (unless masks=False)
    and one more segmentation pass per instance asked for in full_masks (when there are several)."""
    R, t = pose_from_view(1.0, 0.4, 700.0)
    insts = [(objs[0], R, t), (objs[1], R, t + np.array([80.0, 0.0, 50.0])), (objs[2], R, t + np.array([-80.0, 0.0, 0.0]))]
    renderer.pass_stats.clear()
    renderer.render(insts)                                # colour + segmentation
    renderer.render(insts, depth_only=True)               # segmentation
    renderer.render(insts, masks=False)                   # colour
    renderer.render(insts, full_masks=[0, 2])             # colour + segmentation + 2 alone
    renderer.render(insts[:1], full_masks=True)           # colour + segmentation (one instance: its own mask)
    counts = {kind: n for kind, (n, _) in renderer.pass_stats.items()}
    assert counts == {"colour": 4, "segmentation": 6}
    assert all(secs > 0 for _, secs in renderer.pass_stats.values())


def test_smooth_models_shade_object_scans_smoothly_and_leave_bare_meshes_flat():
    """``smooth_models=True``: an ObjectModel's mesh (a coarse sphere, 80 facets, uniform colour, one
    directional light) is shaded with interpolated normals — the same silhouette and depth as flat
    shading, but no steps between facets (neighbouring pixels differ little, many grey levels instead of
    one per visible facet); a bare trimesh of the same sphere stays flat; ``forget`` drops both cache
    entries of a mesh."""
    import trimesh

    from kpd6d.objects import ObjectModel
    from kpd6d.render import Light, Lighting

    sphere = trimesh.creation.icosphere(subdivisions=1, radius=60.0)
    sphere.visual.vertex_colors = np.tile(np.array([200, 200, 200, 255], np.uint8), (len(sphere.vertices), 1))
    model = ObjectModel(obj_id=1, mesh=sphere)
    light = Lighting(ambient=(0.0, 0.0, 0.0), lights=[Light((0.3, 0.4, 1.0), (1.0, 1.0, 1.0), 3.0)])
    R, t = np.eye(3), np.array([0.0, 0.0, 500.0])
    flat_r = Renderer(160, 120, LINEMOD_K * np.array([[0.25], [0.25], [1.0]]), antialias=False)
    smooth_r = Renderer(160, 120, LINEMOD_K * np.array([[0.25], [0.25], [1.0]]), antialias=False, smooth_models=True)
    try:
        flat, smooth = (r.render([(model, R, t)], lighting=light) for r in (flat_r, smooth_r))
        assert np.array_equal(flat.masks_visib[0], smooth.masks_visib[0])
        np.testing.assert_allclose(flat.depth, smooth.depth, atol=1e-3)
        inner = cv2.erode(flat.masks_visib[0].astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        assert inner.sum() > 300

        def steps(rgb):  # largest grey-level jumps between horizontal neighbours inside the sphere
            g = rgb[..., 1].astype(float)
            both = inner[:, 1:] & inner[:, :-1]
            return np.percentile(np.abs(np.diff(g, axis=1))[both], 99)

        assert steps(flat.rgb) >= 2 * max(steps(smooth.rgb), 1.0)  # (measured: 35 against 11)
        assert len(np.unique(smooth.rgb[inner][:, 1])) > 2 * len(np.unique(flat.rgb[inner][:, 1]))
        bare = smooth_r.render([(sphere, R, t)], lighting=light)  # not an ObjectModel: flat
        assert np.array_equal(bare.rgb, flat.rgb)
        assert {(id(sphere), False), (id(sphere), True)} <= set(smooth_r._cache)
        smooth_r.forget(sphere)
        assert not {(id(sphere), False), (id(sphere), True)} & set(smooth_r._cache)
    finally:
        flat_r.close()
        smooth_r.close()
