"""The procedural room around the table (``table_room_prob``): geometry, ground truth, emissive screens.

The masks of a table-top scene in a room are checked against an independent segmentation pass that
draws the objects, the occluders and every room surface (the room may hide object pixels only where
it is truly in front); the room's surfaces are checked to face the inside and to leave every
camera the layout samples inside the walls.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from kpd6d.synth import SynthConfig, generate_dataset
from kpd6d.synth.backgrounds import ProceduralBackgrounds
from kpd6d.synth.room import make_room, textured_box, textured_quad
from synth_helpers import SMALL, write_models
from test_synth_tabletop import TT, _composer


@pytest.fixture(scope="module")
def models_dir(tmp_path_factory):
    return write_models(tmp_path_factory.mktemp("models"))


def _face_normals(mesh):
    v = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    return v.mean(axis=1), n / np.linalg.norm(n, axis=1, keepdims=True)


def test_room_surfaces_face_inside_and_cameras_stay_inside():
    bg = ProceduralBackgrounds()
    ext, reach = (-400.0, 700.0, -300.0, 500.0), 1400.0
    for seed in range(6):
        room = make_room(np.random.default_rng(seed), bg, ext, reach, texture_px=32)
        wx0, wx1, wy0, wy1 = room.walls
        # every camera within `reach` of the look-at point (horizontally), and the table, is inside
        assert wx0 < -reach and wx1 > reach and wy0 < -reach and wy1 > reach
        assert wx0 < ext[0] and wx1 > ext[1] and wy0 < ext[2] and wy1 > ext[3]
        assert room.floor_z < -600.0 and room.height > 2000.0
        inside = np.array([0.0, 0.0, room.floor_z + 1000.0])
        assert len(room.meshes) >= 5  # floor and four walls at least
        for mesh in room.meshes[:5]:  # floor, walls: front faces towards the room's inside
            c, n = _face_normals(mesh)
            assert np.all(np.einsum("ij,ij->i", n, inside - c) > 0)
        for mesh in room.meshes[5:]:
            v = np.asarray(mesh.vertices)
            assert np.all(v[:, 0] >= wx0 - 1e-6) and np.all(v[:, 0] <= wx1 + 1e-6)
            assert np.all(v[:, 1] >= wy0 - 1e-6) and np.all(v[:, 1] <= wy1 + 1e-6)
            assert np.all(v[:, 2] >= room.floor_z - 1e-6) and np.all(v[:, 2] <= room.floor_z + room.height + 1e-6)
            if len(mesh.faces) == 10:  # a piece of furniture: clear of the table and of the camera region
                lo, hi = v.min(0), v.max(0)
                assert not (lo[0] < ext[1] and hi[0] > ext[0] and lo[1] < ext[3] and hi[1] > ext[2])
                assert np.any(np.abs(np.clip([0.0, 0.0], lo[:2], hi[:2])) >= reach)


def test_textured_box_faces_point_outwards_and_quad_faces_the_given_point():
    box = textured_box([0, 0, 0], [100, 50, 30], np.zeros((4, 4, 3), np.uint8))
    c, n = _face_normals(box)
    assert len(box.faces) == 10  # five faces, no bottom
    assert np.all(np.einsum("ij,ij->i", n, c - np.array([50.0, 25.0, 15.0])) > 0)
    assert not np.any(n[:, 2] < -0.5)
    for towards in ([0, 0, 100], [0, 0, -100]):
        q = textured_quad([-1, -1, 0], [2, 0, 0], [0, 2, 0], np.zeros((4, 4, 3), np.uint8), towards)
        _, n = _face_normals(q)
        assert np.all(np.sign(n[:, 2]) == np.sign(towards[2]))


def test_screens_emit_and_posters_do_not():
    """A screen shows its picture in the dark (no ambient, no light); a poster of the same picture is black."""
    from kpd6d.render import Lighting, Renderer

    img = np.full((16, 16, 3), 200, np.uint8)
    r = Renderer(64, 48, np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]]), antialias=False)
    dark = Lighting(ambient=(0.0, 0.0, 0.0), lights=[])
    R, t = np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, 500.0])  # table frame +z towards the camera
    means = {}
    for emissive in (False, True):
        q = textured_quad([-400, -400, 0], [800, 0, 0], [0, 800, 0], img, [0, 0, 100], emissive=emissive)
        res = r.render([(q, R, t)], lighting=dark, K=r.K, masks=False)
        assert np.all(res.depth > 0)  # it faces the camera and fills the view
        means[emissive] = float(res.rgb.mean())
    r.close()
    assert means[False] < 5 and means[True] > 150


def test_room_masks_equal_an_independent_segmentation(models_dir):
    """Objects' visible masks with the room = a segmentation pass of objects, occluders and every room
    surface (no table): the room hides object pixels only where it is in front; the room fills the
    frame behind the table (the pasted backdrop is hardly seen)."""
    from kpd6d.render import Renderer

    comp = _composer(models_dir, objects_per_image=(2, 3), distractors=(1, 2), visib_fract_range=(0.0, 1.0),
                     table_room_prob=1.0)
    samples = [comp.compose(np.random.default_rng([31, i])) for i in range(6)]
    comp.renderer.close()  # one GL context at a time
    r = Renderer(comp.W, comp.H, comp.K, antialias=False)
    by_id = {m.obj_id: m for m in comp.models}
    compared, coverage = 0, []
    for s in samples:
        assert len(s.table.room) >= 5
        objs = [(by_id[inst.obj_id], inst.R, inst.t) for inst in s.instances]
        room = [(m, s.table.R_w2c, s.table.t_w2c) for m in s.table.room]
        ref = r.render(objs + s.distractor_items + room, K=s.K, depth_only=True)
        for inst, m in zip(s.instances, ref.masks_visib):
            np.testing.assert_array_equal(inst.mask_visib, m)
            compared += int(m.sum())
        coverage.append(float((s.depth > 0).mean()))
    r.close()
    assert compared > 1000
    assert np.median(coverage) > 0.97  # the room is behind everything the table does not cover


def test_room_meshes_do_not_accumulate(models_dir):
    comp = _composer(models_dir, distractors=(1, 1), max_retries=0, table_room_prob=1.0)
    sizes = []
    for i in range(4):
        comp.compose(np.random.default_rng([5, i]))
        sizes.append(len(comp.renderer._cache))
    comp.renderer.close()
    assert max(sizes) <= 2 + 8  # the models and the occluder pool: no tables, no rooms


def test_room_option_is_recorded_validated_and_off_by_default(tmp_path, models_dir):
    assert SynthConfig().table_room_prob == 0.0
    with pytest.raises(ValueError, match="table_room_prob must lie in"):
        SynthConfig.from_options({"layout": "tabletop", "table_room_prob": 1.5})
    comp = _composer(models_dir, distractors=(0, 0))
    assert all(comp.compose(np.random.default_rng(i)).table.room == () for i in range(2))
    comp.renderer.close()
    root = generate_dataset(tmp_path / "d", models_dir, num_images=2, seed=2, progress=False,
                            table_room_prob=0.5, **{**TT, "distractors": (0, 0)})
    info = json.loads((root / "dataset_info.json").read_text())
    assert info["splits"]["train"]["config"]["table_room_prob"] == 0.5
    free = SynthConfig.from_options(dict(SMALL)).to_dict()
    assert "table_room_prob" not in free  # the free layout's recorded options are unchanged
