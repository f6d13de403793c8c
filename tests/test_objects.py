"""ObjectModel loading (PLY / OBJ / GLB, units, errors), models_info reading and BOP model folders."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from kpd6d.objects import ModelError, ObjectModel, load_bop_models, load_models_info, procedural_objects


@pytest.fixture(scope="module")
def coloured_box():
    m = trimesh.creation.box((100.0, 60.0, 40.0))
    m = trimesh.Trimesh(*trimesh.remesh.subdivide(m.vertices, m.faces), process=False)
    rng = np.random.default_rng(0)
    m.visual = trimesh.visual.ColorVisuals(m, vertex_colors=np.c_[rng.integers(0, 255, (len(m.vertices), 3)),
                                                                   np.full(len(m.vertices), 255)].astype(np.uint8))
    return m


def test_load_ply_keeps_colours_and_id(tmp_path, coloured_box):
    p = tmp_path / "obj_000042.ply"
    coloured_box.export(p)
    m = ObjectModel.load(p)
    assert m.obj_id == 42 and m.source == str(p)
    assert np.allclose(m.vertices, coloured_box.vertices)
    assert np.array_equal(np.asarray(m.mesh.visual.vertex_colors), np.asarray(coloured_box.visual.vertex_colors))
    assert m.diameter == pytest.approx(np.sqrt(100**2 + 60**2 + 40**2))
    assert np.allclose(m.bbox_min, [-50, -30, -20]) and np.allclose(m.bbox_size, [100, 60, 40])
    assert m.bbox_corners.shape == (8, 3) and m.info()["size_x"] == pytest.approx(100.0)


def test_units_m_scales_by_1000(tmp_path, coloured_box):
    metres = coloured_box.copy()
    metres.apply_scale(0.001)
    p = tmp_path / "box_m.ply"
    metres.export(p)
    m = ObjectModel.load(p, units="m", obj_id=3)
    assert np.allclose(m.vertices, coloured_box.vertices, atol=1e-6)
    assert m.diameter == pytest.approx(ObjectModel(obj_id=0, mesh=coloured_box).diameter, rel=1e-6)
    mm = ObjectModel.load(p, units="mm")  # read as millimetres (stated: the default would reject it): 1000x smaller
    assert mm.diameter == pytest.approx(m.diameter / 1000, rel=1e-6)


@pytest.mark.parametrize("ext", ["obj", "glb"])
def test_load_obj_and_glb(tmp_path, coloured_box, ext):
    p = tmp_path / f"model_7.{ext}"
    coloured_box.export(p)
    m = ObjectModel.load(p)
    assert m.obj_id == 7
    assert len(m.faces) == len(coloured_box.faces)
    assert np.allclose(np.sort(m.vertices, axis=0), np.sort(coloured_box.vertices, axis=0), atol=1e-4)
    assert m.diameter == pytest.approx(np.sqrt(100**2 + 60**2 + 40**2), rel=1e-5)


def test_load_errors_name_file_and_problem(tmp_path):
    with pytest.raises(ModelError, match="does not exist") as ei:
        ObjectModel.load(tmp_path / "missing.ply")
    assert "missing.ply" in str(ei.value)
    empty = tmp_path / "empty.ply"
    empty.write_bytes(b"")
    with pytest.raises(ModelError, match=r"empty.ply: mesh file is empty"):
        ObjectModel.load(empty)
    corrupt = tmp_path / "corrupt.ply"
    corrupt.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nend_header\n\x00\x01")
    with pytest.raises(ModelError, match=r"corrupt.ply: cannot be read as a mesh \(ValueError"):
        ObjectModel.load(corrupt)
    whole = tmp_path / "whole.ply"
    procedural_objects(obj_ids=[3])[0].mesh.export(whole)
    trunc = tmp_path / "truncated.ply"
    trunc.write_bytes(whole.read_bytes()[:5000])
    with pytest.raises(ModelError, match=r"truncated.ply: (mesh has \d+ vertices and 0 faces|cannot be read)"):
        ObjectModel.load(trunc)
    garbage = tmp_path / "garbage.obj"
    garbage.write_text("this is not a mesh\n")
    with pytest.raises(ModelError, match=r"garbage.obj: file holds no triangle mesh"):
        ObjectModel.load(garbage)
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(50, 3))).export(cloud)
    with pytest.raises(ModelError, match=r"cloud.ply: file holds a PointCloud, not a triangle mesh"):
        ObjectModel.load(cloud)
    with pytest.raises(ModelError, match="is a directory"):
        ObjectModel.load(tmp_path)
    with pytest.raises(ModelError, match=r"unknown units 'inch'"):
        ObjectModel.load(cloud, units="inch")


def test_models_info_reader_errors(tmp_path):
    p = tmp_path / "models_info.json"
    with pytest.raises(ModelError, match="does not exist"):
        load_models_info(p)
    p.write_text("{bad")
    with pytest.raises(ModelError, match="invalid JSON"):
        load_models_info(p)
    p.write_text(json.dumps({"x": {"diameter": 1}}))
    with pytest.raises(ModelError, match="object id 'x' is not an integer"):
        load_models_info(p)
    p.write_text(json.dumps({"1": {"size_x": 1}}))
    with pytest.raises(ModelError, match="entry '1' has no 'diameter'"):
        load_models_info(p)
    p.write_text(json.dumps({"1": {"diameter": 1, "symmetries_discrete": [[1, 0, 0]]}}))
    with pytest.raises(ModelError, match=r"symmetries_discrete\[0\] has 3 values, expected 16"):
        load_models_info(p)


def test_bop_folder_round_trip_with_procedural(tmp_path):
    objs = procedural_objects(obj_ids=[5, 6])
    info = {}
    for m in objs:
        m.mesh.export(tmp_path / f"obj_{m.obj_id:06d}.ply")
        info[str(m.obj_id)] = m.info()
    (tmp_path / "models_info.json").write_text(json.dumps(info))
    loaded = load_bop_models(tmp_path)
    assert [m.obj_id for m in loaded] == [5, 6]
    for a, b in zip(objs, loaded):
        assert np.allclose(a.vertices, b.vertices, atol=1e-4)
        assert a.info()["symmetries_discrete" if a.obj_id == 5 else "symmetries_continuous"] == \
            b.info()["symmetries_discrete" if a.obj_id == 5 else "symmetries_continuous"]
    with pytest.raises(ModelError, match=r"no entry for object id\(s\) \[9\]; known: \[5, 6\]"):
        load_bop_models(tmp_path, obj_ids=[9])


@pytest.mark.lmo
def test_lmo_models_match_models_info(lmo_dir, lmo_models):
    info = load_models_info(lmo_dir / "models" / "models_info.json")
    assert [m.obj_id for m in lmo_models] == sorted(info)
    for m in lmo_models:
        e = info[m.obj_id]
        # geometry computed from the mesh agrees with BOP's metadata
        assert np.allclose(m.bbox_min, [e["min_x"], e["min_y"], e["min_z"]], atol=0.01)
        assert np.allclose(m.bbox_size, [e["size_x"], e["size_y"], e["size_z"]], atol=0.01)
        raw = ObjectModel(obj_id=m.obj_id, mesh=m.mesh)  # diameter from the vertices, not the file
        assert raw.diameter == pytest.approx(e["diameter"], rel=2e-3)
        assert len(m.symmetries_discrete) == len(e.get("symmetries_discrete", []))
        assert np.asarray(m.mesh.visual.vertex_colors).shape[0] == len(m.vertices)  # LM-O meshes are coloured
