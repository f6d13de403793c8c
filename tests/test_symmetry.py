"""Symmetry handlers: canonical poses are equivalent, unique per symmetry class and in range."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kpd6d.geometry import (
    LINEMOD_K,
    pose_from_view,
    random_rotation,
    rotation_about_axis,
    transform_points,
    view_from_pose,
)
from kpd6d.objects import ObjectModel, procedural_objects
from kpd6d.registry import SYMMETRIES, UnknownNameError
from kpd6d.symmetry import (
    ContinuousSymmetry,
    DiscreteSymmetry,
    NoSymmetry,
    RotationalSymmetry,
    axis_angle_offset,
    handler_for_model,
)


def _random_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    R = random_rotation(rng, n)
    t = np.c_[rng.uniform(-100, 100, (n, 2)), rng.uniform(500, 1200, n)]
    return R, t


def _symmetric_image(R, t, S, pts):
    """Camera-frame points of the object seen at (R, t) after moving it by S (the same object)."""
    return transform_points(pts @ S[:3, :3].T + S[:3, 3], R, t)


def test_registry_names_and_unknown():
    assert {"none", "rotational", "continuous", "discrete"} <= set(SYMMETRIES.names())
    with pytest.raises(UnknownNameError, match=r"known symmetry handlers: .*rotational"):
        SYMMETRIES.build("spherical")
    with pytest.raises(ValueError, match="order must be an integer >= 2"):
        SYMMETRIES.build("rotational", order=1)
    with pytest.raises(ValueError, match="axis must be a finite non-zero"):
        SYMMETRIES.build("rotational", axis=[0, 0, 0])


def test_none_is_identity():
    R, t = _random_poses(5)
    h = SYMMETRIES.build("none")
    R2, t2 = h.canonicalize(R, t)
    assert np.array_equal(R, R2) and np.array_equal(t, t2)
    assert len(h.transforms()) == 1


@pytest.mark.parametrize("order", [2, 3, 5])
def test_rotational_about_z_canonical_range_equivalence_uniqueness(order):
    h = SYMMETRIES.build("rotational", order=order)
    alpha = 2 * math.pi / order
    Ts = h.transforms()
    assert len(Ts) == order and np.allclose(Ts[0], np.eye(4))
    assert np.allclose(Ts[1][:3, :3], rotation_about_axis([0, 0, 1], alpha))
    R, t = _random_poses(200, seed=order)
    Rc, tc = h.canonicalize(R, t)
    # in range: azimuth of the camera about z (independent: geometry.view_from_pose) in [0, α)
    az = np.array([view_from_pose(a, b)[0] for a, b in zip(Rc, tc)]) % (2 * math.pi)
    assert ((az >= -1e-9) & (az < alpha + 1e-9)).all()
    # equivalence: the canonical pose is the original composed with one of the symmetry transforms
    pts = np.random.default_rng(1).normal(size=(20, 3)) * 50
    for i in range(len(R)):
        ok = any(np.allclose(transform_points(pts, Rc[i], tc[i]), _symmetric_image(R[i], t[i], S, pts), atol=1e-6)
                 for S in Ts)
        assert ok
    # elevation and distance are unchanged
    for i in range(0, 200, 17):
        _, el0, d0 = view_from_pose(R[i], t[i])
        _, el1, d1 = view_from_pose(Rc[i], tc[i])
        assert el0 == pytest.approx(el1) and d0 == pytest.approx(d1)
    # uniqueness: every equivalent pose canonicalises to the same pose
    for S in Ts[1:]:
        Re = R @ S[:3, :3]
        te = t + np.einsum("nij,j->ni", R, S[:3, 3])
        Rc2, tc2 = h.canonicalize(Re, te)
        assert np.allclose(Rc2, Rc, atol=1e-9) and np.allclose(tc2, tc, atol=1e-6)
    assert h.in_canonical_range(Rc, tc).all()
    # single pose in, single pose out; a pose already canonical is left alone
    R1, t1 = h.canonicalize(R[0], t[0])
    assert R1.shape == (3, 3) and t1.shape == (3,)
    R2, t2 = h.canonicalize(R1, t1)
    assert np.allclose(R2, R1) and np.allclose(t2, t1)


def test_rotational_with_offset_axis():
    axis = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
    offset = np.array([10.0, -5.0, 3.0])
    h = RotationalSymmetry(order=4, axis=axis, offset=offset)
    for S in h.transforms():  # every transform fixes the axis line pointwise
        for s in (0.0, 37.0, -80.0):
            p = h.offset + s * axis
            assert np.allclose(S[:3, :3] @ p + S[:3, 3], p)
    R, t = _random_poses(50, seed=7)
    Rc, tc = h.canonicalize(R, t)
    phi = h.azimuth(Rc, tc)
    assert ((phi >= 0) & (phi < math.pi / 2 + 1e-9)).all()
    # independent azimuth: angle between the camera centre's axis-normal component and the reference
    eye = -np.einsum("nji,nj->ni", Rc, tc) - h.offset
    perp = eye - (eye @ axis)[:, None] * axis
    ref = np.array([1.0, 0, 0]) - axis[0] * axis
    ref /= np.linalg.norm(ref)
    cos = (perp @ ref) / np.linalg.norm(perp, axis=1)
    assert np.allclose(np.cos(phi), cos, atol=1e-9)


def test_rotational_render_identical_for_zblock():
    """Independent check through the renderer: the canonical pose of the 2-fold zblock looks the same."""
    from kpd6d.render import Renderer

    m = procedural_objects(obj_ids=[5])[0]
    h = handler_for_model(m)
    assert isinstance(h, RotationalSymmetry) and h.order == 2
    K = LINEMOD_K.copy()
    r = Renderer(160, 120, K * np.array([[0.25], [0.25], [1]]))
    R, t = pose_from_view(4.0, 0.6, 450.0, inplane=0.4)  # azimuth outside [0, π)
    Rc, tc = h.canonicalize(R, t)
    assert not np.allclose(Rc, R)
    a = r.render([(m, R, t)])
    b = r.render([(m, Rc, tc)])
    fg = a.masks_visib[0] | b.masks_visib[0]
    assert fg.sum() > 1000
    assert np.abs(a.rgb.astype(float) - b.rgb)[fg].mean() < 2.0
    assert (a.masks_visib[0] != b.masks_visib[0]).sum() < 0.01 * fg.sum()
    R_wrong = R @ rotation_about_axis([1, 0, 0], math.pi)  # not a symmetry: looks different
    c = r.render([(m, R_wrong, t)])
    assert np.abs(a.rgb.astype(float) - c.rgb)[fg].mean() > 20.0


def test_continuous_canonical_half_plane_and_equivalence():
    h = SYMMETRIES.build("continuous", axis=[0, 0, 1])
    R, t = _random_poses(100, seed=3)
    Rc, tc = h.canonicalize(R, t)
    eye = -np.einsum("nji,nj->ni", Rc, tc)
    assert np.allclose(eye[:, 1], 0.0, atol=1e-6) and (eye[:, 0] >= -1e-9).all()
    # the pose changed by a rotation about z only: R^T R_c is a rotation about z
    for i in range(100):
        D = R[i].T @ Rc[i]
        assert np.allclose(D[:, 2], [0, 0, 1], atol=1e-9)
        assert np.allclose(tc[i], t[i])  # axis through the origin: translation unchanged
        _, el0, d0 = view_from_pose(R[i], t[i])
        _, el1, d1 = view_from_pose(Rc[i], tc[i])
        assert el0 == pytest.approx(el1) and d0 == pytest.approx(d1)
    Ts = h.transforms()
    assert len(Ts) == 36 and np.allclose(Ts[0], np.eye(4))


def test_continuous_render_identical_for_vase():
    from kpd6d.render import Renderer

    m = procedural_objects(obj_ids=[6])[0]
    h = handler_for_model(m)
    assert isinstance(h, ContinuousSymmetry)
    r = Renderer(160, 120, LINEMOD_K * np.array([[0.25], [0.25], [1]]))
    R, t = pose_from_view(1.3, -0.4, 500.0, inplane=-0.7)
    Rc, tc = h.canonicalize(R, t)
    a = r.render([(m, R, t)])
    b = r.render([(m, Rc, tc)])
    fg = a.masks_visib[0] | b.masks_visib[0]
    assert fg.sum() > 1000
    assert np.abs(a.rgb.astype(float) - b.rgb)[fg].mean() < 4.0  # polygonal circle: edge pixels differ


def test_continuous_with_flip_puts_camera_on_positive_side():
    flip = np.eye(4)
    flip[:3, :3] = rotation_about_axis([1, 0, 0], math.pi)
    h = ContinuousSymmetry(axis=[0, 0, 1], flips=[flip])
    R, t = _random_poses(60, seed=4)
    Rc, tc = h.canonicalize(R, t)
    eye = -np.einsum("nji,nj->ni", Rc, tc)
    assert (eye[:, 2] >= -1e-9).all() and np.allclose(eye[:, 1], 0, atol=1e-6)


def test_axis_angle_offset_roundtrip_and_bop_matrix():
    S = np.eye(4)
    axis = np.array([0.2, -0.3, 0.9]) / np.linalg.norm([0.2, -0.3, 0.9])
    R = rotation_about_axis(axis, 2 * math.pi / 3)
    o = np.array([5.0, 1.0, -2.0])
    S[:3, :3], S[:3, 3] = R, o - R @ o
    a, ang, off = axis_angle_offset(S)
    assert np.allclose(a, axis) and ang == pytest.approx(2 * math.pi / 3)
    assert np.allclose(off, o - (o @ axis) * axis)
    # LM-O eggbox matrix (models_info.json): ~180° about ~z
    egg = np.array([-0.999964, -0.00333777, -0.0077452, 0.232611, 0.00321462, -0.999869, 0.0158593, 0.694388,
                    -0.00779712, 0.0158338, 0.999844, -0.0792063, 0, 0, 0, 1]).reshape(4, 4)
    a, ang, off = axis_angle_offset(egg)
    assert ang == pytest.approx(math.pi, abs=0.01) and a[2] > 0.999
    m = ObjectModel(obj_id=10, mesh=None, symmetries_discrete=[egg], _diameter=164.6)
    h = handler_for_model(m)
    assert isinstance(h, RotationalSymmetry) and h.order == 2
    S1 = h.transforms()[1]  # the exact turn is close to BOP's matrix
    assert np.allclose(S1[:3, :3], egg[:3, :3], atol=0.02) and np.allclose(S1[:3, 3], egg[:3, 3], atol=1.0)


def test_handler_for_model_choices():
    assert isinstance(handler_for_model(procedural_objects(obj_ids=[1])[0]), NoSymmetry)
    # several axes (a box's three 2-fold turns) -> discrete; canonicalisation unique per class
    flips = []
    for ax in np.eye(3):
        S = np.eye(4)
        S[:3, :3] = rotation_about_axis(ax, math.pi)
        flips.append(S)
    m = ObjectModel(obj_id=1, mesh=None, symmetries_discrete=flips, _diameter=100.0)
    h = handler_for_model(m)
    assert isinstance(h, DiscreteSymmetry) and len(h.transforms()) == 4
    R, t = _random_poses(40, seed=9)
    Rc, tc = h.canonicalize(R, t)
    for S in flips:
        Rc2, tc2 = h.canonicalize(R @ S[:3, :3], t)
        assert np.allclose(Rc2, Rc) and np.allclose(tc2, tc)
    # four listed 90°-multiples about z -> order 4
    quarter = []
    for k in (1, 2, 3):
        S = np.eye(4)
        S[:3, :3] = rotation_about_axis([0, 0, 1], k * math.pi / 2)
        quarter.append(S)
    h4 = handler_for_model(ObjectModel(obj_id=2, mesh=None, symmetries_discrete=quarter, _diameter=100.0))
    assert isinstance(h4, RotationalSymmetry) and h4.order == 4


def _flat_bottle():
    """A flat 2-fold object: a box thin in x, broad in y, tall in z, turned half-way about z."""
    import trimesh

    S = np.eye(4)
    S[:3, :3] = rotation_about_axis([0, 0, 1], math.pi)
    return ObjectModel(obj_id=11, mesh=trimesh.creation.box(extents=(30.0, 80.0, 170.0)), symmetries_discrete=[S])


def _boundary_pixel_motion(model, direction, turn):
    """Mean pixel distance between the model's surface points and their turned copies, seen by a LineMod
    camera 600 mm away along ``direction`` (elevation 0): what tells the two labels apart at that view."""
    from kpd6d.geometry import project_points

    d = np.asarray(direction, float) / np.linalg.norm(direction)
    R, t = pose_from_view(math.atan2(d[1], d[0]), 0.0, 600.0)
    pts = model.sample_points(500, seed=3)
    a = project_points(pts, LINEMOD_K, R, t)
    b = project_points(pts @ turn[:3, :3].T + turn[:3, 3], LINEMOD_K, R, t)
    return float(np.linalg.norm(a - b, axis=1).mean())


def test_least_motion_reference_flat_object():
    from kpd6d.symmetry import least_motion_reference

    m = _flat_bottle()
    ref = least_motion_reference(m.sample_points(2000, seed=0), [0, 0, 1])
    assert abs(ref[1]) > 0.999 and abs(ref[2]) < 1e-9  # along its broad side (y), normal to the axis
    # independent check with a perspective camera: the turn moves the object least, seen from there
    turn = m.symmetries_discrete[0]
    seen = {deg: _boundary_pixel_motion(m, [math.cos(math.radians(deg)), math.sin(math.radians(deg)), 0], turn)
            for deg in range(0, 180, 15)}
    assert min(seen, key=seen.get) == 90
    assert _boundary_pixel_motion(m, ref, turn) < 0.6 * _boundary_pixel_motion(m, [1, 0, 0], turn)
    with pytest.raises(ValueError, match="finite points"):
        least_motion_reference(np.zeros((0, 3)), [0, 0, 1])


def test_handler_boundary_choice_moves_the_canonical_range():
    m = _flat_bottle()
    hx = handler_for_model(m)
    hl = handler_for_model(m, boundary="least_motion")
    assert hx.reference is None and np.allclose(np.abs(hl.reference), [0, 1, 0], atol=0.02)
    assert "reference" in repr(hl)
    R, t = _random_poses(200, seed=4)
    Rc, tc = hl.canonicalize(R, t)
    # independent azimuth from +y (the new reference) about z: the camera centre's angle, in [0, π)
    eye = -np.einsum("nji,nj->ni", Rc, tc)
    az = np.mod(np.arctan2(-eye[:, 0] * np.sign(hl.reference[1]), eye[:, 1] * np.sign(hl.reference[1])), 2 * math.pi)
    assert ((az >= -1e-9) & (az < math.pi + 1e-9)).all()
    # equivalent to the model_x canonical pose (one turn apart or equal), both unique per class
    Rx, tx = hx.canonicalize(R, t)
    turned = np.einsum("nij,jk->nik", Rx, m.symmetries_discrete[0][:3, :3])
    same = np.isclose(Rc, Rx, atol=1e-9).all(axis=(1, 2))
    assert (same | np.isclose(Rc, turned, atol=1e-9).all(axis=(1, 2))).all()
    assert np.allclose(tc, tx, atol=1e-9)  # a turn about an axis through the origin keeps the translation
    assert 0.3 < same.mean() < 0.7  # the two ranges overlap by half
    with pytest.raises(ValueError, match=r"symmetry boundary 'widest' unknown; known: model_x, least_motion"):
        handler_for_model(m, boundary="widest")
    with pytest.raises(ValueError, match="must not be parallel"):
        RotationalSymmetry(order=2, reference=[0, 0, 2])
