"""Automatic symmetry detection against BOP models_info.json and symmetries known by construction."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from kpd6d.geometry import rotation_about_axis, rotation_error_deg
from kpd6d.objects import ObjectModel, procedural_objects
from kpd6d.registry import SYMMETRIES
from kpd6d.symmetry import AutoSymmetry


def _nearest_rotation(M):
    U, _, Vt = np.linalg.svd(M)
    return U @ Vt


def _assert_matches(found: list, expected: list, diameter: float):
    """Same number of transforms; each expected one has a detected one within 2° and 1% of the diameter."""
    assert len(found) == len(expected), (found, expected)
    F = [np.asarray(f).reshape(4, 4) for f in found]
    for e in expected:
        E = np.asarray(e, dtype=float).reshape(4, 4)
        errs = [(rotation_error_deg(_nearest_rotation(E[:3, :3]), T[:3, :3]), np.linalg.norm(E[:3, 3] - T[:3, 3]))
                for T in F]
        assert any(r < 2.0 and t < 0.01 * diameter for r, t in errs), (E, F, errs)


@pytest.mark.lmo
def test_auto_matches_models_info_on_lmo(lmo_models):
    auto = SYMMETRIES.build("auto")
    for m in lmo_models:
        info = m.info()
        got = auto(m)
        assert set(got) == {"symmetries_discrete", "symmetries_continuous"}
        assert got["symmetries_continuous"] == [], m.obj_id
        _assert_matches(got["symmetries_discrete"], info.get("symmetries_discrete", []), m.diameter)
        if m.obj_id in (10, 11):
            assert len(got["symmetries_discrete"]) == 1  # eggbox and glue: one 2-fold turn


def test_auto_matches_procedural_objects():
    auto = AutoSymmetry()
    for m in procedural_objects():
        got = auto(m)
        info = m.info()
        _assert_matches(got["symmetries_discrete"], info.get("symmetries_discrete", []), m.diameter)
        exp_c = info.get("symmetries_continuous", [])
        assert len(got["symmetries_continuous"]) == len(exp_c), m.name
        for g, e in zip(got["symmetries_continuous"], exp_c):
            assert abs(float(np.dot(g["axis"], e["axis"]))) > math.cos(math.radians(1.0))
            off = np.asarray(g["offset"]) - np.asarray(e["offset"])
            assert np.linalg.norm(off - (off @ np.asarray(e["axis"])) * np.asarray(e["axis"])) < 1.0


def test_auto_finds_order_six_about_z():
    cone = trimesh.creation.cone(radius=60.0, height=90.0, sections=6)  # hexagonal pyramid: C6 only
    cone = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(cone.vertices, cone.faces, 4.0))
    cone.apply_translation(-cone.bounds.mean(axis=0))
    m = ObjectModel(obj_id=1, mesh=cone)
    got = AutoSymmetry()(m)
    assert got["symmetries_continuous"] == []
    Ts = [np.asarray(t).reshape(4, 4) for t in got["symmetries_discrete"]]
    assert len(Ts) == 5
    angles = sorted(round(math.degrees(math.atan2(T[1, 0], T[0, 0])) % 360) for T in Ts)
    assert angles == [60, 120, 180, 240, 300]
    for T in Ts:
        assert np.allclose(T[:3, 2], [0, 0, 1], atol=0.02)


def test_auto_use_color_breaks_geometric_symmetry():
    z = procedural_objects(obj_ids=[5])[0]
    assert len(AutoSymmetry(use_color=True)(z)["symmetries_discrete"]) == 1  # texture is symmetric too
    # same geometry, texture that is not invariant under the turn: a colour ramp along x
    recol = z.mesh.copy()
    x = recol.vertices[:, 0]
    ramp = ((x - x.min()) / np.ptp(x) * 255).astype(np.uint8)
    recol.visual = trimesh.visual.ColorVisuals(recol, vertex_colors=np.c_[ramp, 255 - ramp, ramp, np.full_like(ramp, 255)])
    m = ObjectModel(obj_id=5, mesh=recol)
    assert len(AutoSymmetry(use_color=False)(m)["symmetries_discrete"]) == 1
    assert AutoSymmetry(use_color=True)(m)["symmetries_discrete"] == []


def test_auto_errors():
    with pytest.raises(ValueError, match="max_order must be >= 2"):
        SYMMETRIES.build("auto", max_order=1)
    bare = ObjectModel(obj_id=3, mesh=trimesh.creation.box((100, 60, 40)))
    with pytest.raises(ValueError, match="object 3 has no vertex colours"):
        AutoSymmetry(use_color=True)(bare)


def test_auto_box_three_twofold_axes():
    box = trimesh.creation.box((120.0, 80.0, 50.0))
    box = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(box.vertices, box.faces, 5.0))
    got = AutoSymmetry()(ObjectModel(obj_id=1, mesh=box))
    expected = []
    for ax in np.eye(3):
        S = np.eye(4)
        S[:3, :3] = rotation_about_axis(ax, math.pi)
        expected.append(S.reshape(-1).tolist())
    _assert_matches(got["symmetries_discrete"], expected, 150.0)
