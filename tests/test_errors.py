"""Pose errors against hand computations, brute force (explicit loops, cv2.projectPoints) and LM-O eggbox."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kpd6d.evaluation import (
    add_error,
    adds_error,
    keypoint_errors,
    mspd_error,
    mssd_error,
    proj2d_error,
    rotation_error,
    symmetry_transforms,
    translation_error,
)
from kpd6d.geometry import LINEMOD_K

I3 = np.eye(3)
Z3 = np.zeros(3)
RZ180 = np.diag([-1.0, -1.0, 1.0])
TRI = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])


def _T(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def test_add_hand_values():
    assert add_error(I3, [3.0, 4.0, 0.0], I3, Z3, TRI) == pytest.approx(5.0)
    # 180 deg about z: distances 0, 2, 4 -> mean 2
    assert add_error(RZ180, Z3, I3, Z3, TRI) == pytest.approx(2.0)
    assert add_error(I3, Z3, I3, Z3, TRI) == 0.0


def test_adds_hand_values():
    pts = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    # est shifted by 6 along x: est points 6, 16; GT 0 -> nearest 6; GT 10 -> nearest 6 at distance 4
    assert adds_error(I3, [6.0, 0, 0], I3, Z3, pts) == pytest.approx(5.0)
    assert add_error(I3, [6.0, 0, 0], I3, Z3, pts) == pytest.approx(6.0)
    # a symmetric pair: rotating by 180 deg about the midpoint maps the set onto itself
    sym = np.array([[-1.0, 0, 0], [1.0, 0, 0]])
    assert add_error(RZ180, Z3, I3, Z3, sym) == pytest.approx(2.0)
    assert adds_error(RZ180, Z3, I3, Z3, sym) == pytest.approx(0.0)


def test_adds_matches_brute_force():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(200, 3)) * 30
    Re, Rg = Rotation.random(2, random_state=1).as_matrix()
    te, tg = rng.normal(size=3) * 5, rng.normal(size=3) * 5
    pe, pg = pts @ Re.T + te, pts @ Rg.T + tg
    brute = np.mean([np.min(np.linalg.norm(pe - g, axis=1)) for g in pg])
    assert adds_error(Re, te, Rg, tg, pts) == pytest.approx(brute, rel=1e-12)


def test_proj2d_hand_and_cv2():
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    # points at depth 100; shifting x by 1 mm moves every projection by fx / z = 1 px
    assert proj2d_error(I3, [1.0, 0, 100], I3, [0, 0, 100.0], TRI, K) == pytest.approx(1.0)
    rng = np.random.default_rng(1)
    pts = rng.uniform(-50, 50, (30, 3))
    Re, Rg = Rotation.random(2, random_state=2).as_matrix()
    te, tg = np.array([5.0, -3, 700]), np.array([0.0, 0, 690])
    pe = cv2.projectPoints(pts, cv2.Rodrigues(Re)[0], te, LINEMOD_K, None)[0].reshape(-1, 2)
    pg = cv2.projectPoints(pts, cv2.Rodrigues(Rg)[0], tg, LINEMOD_K, None)[0].reshape(-1, 2)
    ref = np.linalg.norm(pe - pg, axis=1).mean()
    assert proj2d_error(Re, te, Rg, tg, pts, LINEMOD_K) == pytest.approx(ref, rel=1e-10)


def test_rotation_and_translation_errors():
    Rz30 = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    assert rotation_error(Rz30, I3) == pytest.approx(30.0)
    assert rotation_error(RZ180, I3) == pytest.approx(180.0)
    assert translation_error([3.0, 4.0, 12.0], Z3) == pytest.approx(13.0)
    assert translation_error(np.array([[1.0], [2.0], [2.0]]), Z3) == pytest.approx(3.0)  # (3, 1) accepted


def test_non_finite_estimate_is_inf_and_bad_shapes_raise():
    nan_R = np.full((3, 3), np.nan)
    for value in (add_error(nan_R, Z3, I3, Z3, TRI), adds_error(I3, [np.nan] * 3, I3, Z3, TRI),
                  proj2d_error(nan_R, Z3, I3, [0, 0, 100.0], TRI, LINEMOD_K),
                  mssd_error(nan_R, Z3, I3, Z3, TRI), mspd_error(nan_R, Z3, I3, Z3, TRI, LINEMOD_K),
                  rotation_error(nan_R, I3), translation_error([np.nan] * 3, Z3)):
        assert value == math.inf
    with pytest.raises(ValueError, match=r"points must be a non-empty \(N, 3\)"):
        add_error(I3, Z3, I3, Z3, np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"R \(3, 3\) and t"):
        add_error(np.eye(4), Z3, I3, Z3, TRI)
    with pytest.raises(ValueError, match=r"K must be \(3, 3\)"):
        proj2d_error(I3, Z3, I3, Z3, TRI, np.eye(4))
    with pytest.raises(ValueError, match=r"symmetries\[0\] must be a 4x4"):
        mssd_error(I3, Z3, I3, Z3, TRI, [np.eye(3)])


# -- MSSD / MSPD -------------------------------------------------------------------------------
def test_mssd_mspd_hand_values():
    pts = np.array([[0.0, 0, 0], [10.0, 0, 0], [0, 5.0, 0]])
    t0 = np.array([0.0, 0, 100])
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    assert mssd_error(I3, t0 + np.array([0, 0, 2.0]), I3, t0, pts) == pytest.approx(2.0)
    assert mspd_error(I3, t0 + np.array([1.0, 0, 0]), I3, t0, pts, K) == pytest.approx(1.0)  # 1 mm at z=100: 1 px
    # 180 deg about z: the far point (10,0,0) lands on (-10,0,0): max distance 20 ...
    assert mssd_error(RZ180, t0, I3, t0, pts) == pytest.approx(20.0)
    # ... unless that rotation is a symmetry of the object
    syms = [np.eye(4), _T(RZ180, Z3)]
    assert mssd_error(RZ180, t0, I3, t0, pts, syms) == pytest.approx(0.0, abs=1e-12)
    assert mspd_error(RZ180, t0, I3, t0, pts, K, syms) == pytest.approx(0.0, abs=1e-9)
    # the bop_toolkit {"R", "t"} dict form is accepted too
    dsyms = [{"R": I3, "t": np.zeros((3, 1))}, {"R": RZ180, "t": np.zeros((3, 1))}]
    assert mssd_error(RZ180, t0, I3, t0, pts, dsyms) == pytest.approx(0.0, abs=1e-12)


def _brute(R_e, t_e, R_g, t_g, pts, syms, K=None):
    """bop_toolkit's loop: for each symmetry, max distance over points; min over symmetries."""
    if K is None:
        est = np.array([R_e @ p + t_e for p in pts])
    else:
        est = cv2.projectPoints(pts, cv2.Rodrigues(R_e)[0], t_e, K, None)[0].reshape(-1, 2)
    best = math.inf
    for S in syms:
        R = R_g @ S[:3, :3]
        t = R_g @ S[:3, 3] + t_g
        if K is None:
            gt = np.array([R @ p + t for p in pts])
        else:
            gt = cv2.projectPoints(pts, cv2.Rodrigues(R)[0], t, K, None)[0].reshape(-1, 2)
        best = min(best, max(np.linalg.norm(e - g) for e, g in zip(est, gt)))
    return best


def test_mssd_mspd_match_brute_force_with_many_symmetries():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-40, 40, (60, 3))
    info = {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [5.0, -3.0, 0.0]}],
            "symmetries_discrete": [list(_T(Rotation.from_euler("x", 180, degrees=True).as_matrix(), [0, 0, 8.0]).ravel())]}
    syms = symmetry_transforms(info, continuous_step_deg=7.5)  # 2 x 48 transforms
    assert syms.shape == (96, 4, 4)
    for _ in range(3):
        Re, Rg = Rotation.random(2, random_state=rng.integers(1 << 30)).as_matrix()
        te, tg = np.array([3.0, -2, 650]), np.array([-5.0, 4, 640])
        assert mssd_error(Re, te, Rg, tg, pts, syms) == pytest.approx(_brute(Re, te, Rg, tg, pts, syms), rel=1e-10)
        assert mspd_error(Re, te, Rg, tg, pts, LINEMOD_K, syms) == pytest.approx(
            _brute(Re, te, Rg, tg, pts, syms, LINEMOD_K), rel=1e-8)


def test_symmetric_proj2d_is_min_over_symmetries_of_the_mean_cv2():
    """Against cv2.projectPoints and an explicit loop over the symmetries (min over S of the mean)."""
    rng = np.random.default_rng(7)
    pts = rng.uniform(-40, 40, (50, 3))
    info = {"symmetries_discrete": [list(_T(RZ180, [0, 0, 6.0]).ravel())],
            "symmetries_continuous": [{"axis": [0, 1, 0], "offset": [2.0, 0, -1.0]}]}
    syms = symmetry_transforms(info, continuous_step_deg=30)  # 2 x 12
    for _ in range(3):
        Re, Rg = Rotation.random(2, random_state=rng.integers(1 << 30)).as_matrix()
        te, tg = np.array([4.0, -1, 600]), np.array([-2.0, 3, 610])
        pe = cv2.projectPoints(pts, cv2.Rodrigues(Re)[0], te, LINEMOD_K, None)[0].reshape(-1, 2)
        means = []
        for S in syms:
            R_s, t_s = Rg @ S[:3, :3], Rg @ S[:3, 3] + tg
            pg = cv2.projectPoints(pts, cv2.Rodrigues(R_s)[0], t_s, LINEMOD_K, None)[0].reshape(-1, 2)
            means.append(np.linalg.norm(pe - pg, axis=1).mean())
        got = proj2d_error(Re, te, Rg, tg, pts, LINEMOD_K, syms)
        assert got == pytest.approx(min(means), rel=1e-8)
        assert got <= proj2d_error(Re, te, Rg, tg, pts, LINEMOD_K) + 1e-9  # identity is one of the transforms
    assert proj2d_error(np.full((3, 3), np.nan), Z3, I3, [0, 0, 100.0], TRI, LINEMOD_K, syms[:2, :, :]) == math.inf


# -- symmetry transforms -----------------------------------------------------------------------
def test_symmetry_transforms_discrete_only():
    S = _T(RZ180, [1.0, 2.0, 3.0])
    out = symmetry_transforms({"diameter": 10.0, "symmetries_discrete": [list(S.ravel())]})
    np.testing.assert_allclose(out, [np.eye(4), S])
    np.testing.assert_allclose(symmetry_transforms({"diameter": 1.0}), [np.eye(4)])


def test_symmetry_transforms_continuous_hand_values():
    out = symmetry_transforms({"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]},
                              continuous_step_deg=90)
    c, s = [1, 0, -1, 0], [0, 1, 0, -1]
    expected = [_T(np.array([[c[i], -s[i], 0], [s[i], c[i], 0], [0, 0, 1]]), Z3) for i in range(4)]
    np.testing.assert_allclose(out, expected, atol=1e-12)
    # about an axis through an offset: the offset point is fixed; 180 deg maps the origin to 2*offset
    off = symmetry_transforms({"symmetries_continuous": [{"axis": [0, 0, 2.0], "offset": [1.0, 0, 0]}]},
                              continuous_step_deg=180)
    assert off.shape == (2, 4, 4)
    np.testing.assert_allclose(off[1] @ [1.0, 0, 0, 1], [1.0, 0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(off[1] @ [0.0, 0, 0, 1], [2.0, 0, 0, 1], atol=1e-12)


def test_symmetry_transforms_bop_step_and_combination_order():
    D = _T(Rotation.from_euler("x", 180, degrees=True).as_matrix(), [0, 0, 4.0])
    info = {"symmetries_discrete": [list(D.ravel())],
            "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}
    out = symmetry_transforms(info)  # bop_toolkit default max_sym_disc_step = 0.01 -> ceil(pi/0.01) = 315
    assert out.shape == (2 * 315, 4, 4)
    step = 2 * math.pi / 315
    C5 = _T(Rotation.from_rotvec([0, 0, 5 * step]).as_matrix(), Z3)
    np.testing.assert_allclose(out[5], C5, atol=1e-12)  # identity (discrete) first, then continuous
    np.testing.assert_allclose(out[315 + 5], C5 @ D, atol=1e-12)  # continuous applied after discrete
    assert symmetry_transforms(info, max_sym_disc_step=0.1).shape == (2 * 32, 4, 4)
    # 360/315 degrees as a step gives the same 315 (no floating-point extra step)
    assert symmetry_transforms(info, continuous_step_deg=360 / 315).shape == (630, 4, 4)
    with pytest.raises(ValueError, match="16"):
        symmetry_transforms({"symmetries_discrete": [[1, 0, 0]]})


# -- LM-O eggbox (obj 10), a symmetric object ----------------------------------------------------
def test_eggbox_symmetric_pose_is_accepted_by_adds_and_mssd(lmo_model_by_id, lmo_dir):
    from kpd6d.objects import load_models_info

    egg = lmo_model_by_id[10]
    info = load_models_info(lmo_dir / "models" / "models_info.json")[10]
    syms = symmetry_transforms(info)
    assert syms.shape == (2, 4, 4)
    pts = egg.vertices
    d = egg.diameter
    R_gt = Rotation.from_euler("xyz", [20, -35, 110], degrees=True).as_matrix()
    t_gt = np.array([30.0, -20.0, 800.0])
    S = syms[1]
    R_sym, t_sym = R_gt @ S[:3, :3], R_gt @ S[:3, 3] + t_gt  # GT composed with the symmetry
    add = add_error(R_sym, t_sym, R_gt, t_gt, pts)
    adds = adds_error(R_sym, t_sym, R_gt, t_gt, pts)
    mssd = mssd_error(R_sym, t_sym, R_gt, t_gt, pts, syms)
    mspd = mspd_error(R_sym, t_sym, R_gt, t_gt, pts, LINEMOD_K, syms)
    assert add > 0.1 * d  # ADD rejects the symmetric pose ...
    assert adds < 0.02 * d  # ... ADD-S and MSSD accept it
    assert mssd < 1e-6 and mspd < 1e-6
    assert mssd_error(R_sym, t_sym, R_gt, t_gt, pts) > 0.5 * d  # without the symmetry it is far off
    # a small error on top of the symmetric pose is measured as such
    t_off = t_sym + np.array([2.0, 0, 0])
    assert mssd_error(R_sym, t_off, R_gt, t_gt, pts, syms) == pytest.approx(2.0, abs=1e-9)
    # 2D projection: the plain error rejects the symmetric pose, the symmetric one accepts it
    assert proj2d_error(R_sym, t_sym, R_gt, t_gt, pts, LINEMOD_K) > 5.0
    assert proj2d_error(R_sym, t_sym, R_gt, t_gt, pts, LINEMOD_K, syms) < 1e-6


def test_keypoint_errors_scale_offset_and_median_against_cv2():
    rng = np.random.default_rng(3)
    X = rng.uniform(-50, 50, (20, 3))
    R, t = Rotation.from_euler("xyz", [20, -35, 70], degrees=True).as_matrix(), np.array([30.0, -20.0, 800.0])
    g, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, LINEMOD_K, None)
    g = g[:, 0]
    pred = g.mean(0) + 0.85 * (g - g.mean(0)) + [3.0, -4.0]  # drawn in to 85 %, moved (3, -4) px
    e = keypoint_errors(pred, X, R, t, LINEMOD_K)
    assert e["scale"] == pytest.approx(0.85, abs=1e-9) and e["centroid_px"] == pytest.approx(5.0, abs=1e-9)
    assert e["err_px"] == pytest.approx(float(np.median([math.dist(p, q) for p, q in zip(pred, g)])), abs=1e-9)
    # an object symmetric under 180 deg about z, keypoints drawn at GT composed with that symmetry: no error
    S = np.eye(4)
    S[:3, :3] = RZ180
    gs, _ = cv2.projectPoints(X @ RZ180.T, cv2.Rodrigues(R)[0], t, LINEMOD_K, None)
    e = keypoint_errors(gs[:, 0], X, R, t, LINEMOD_K, symmetries=[np.eye(4), S])
    assert e["err_px"] < 1e-9 and e["scale"] == pytest.approx(1.0, abs=1e-9)
    assert keypoint_errors(gs[:, 0], X, R, t, LINEMOD_K)["err_px"] > 5  # without the symmetry it is wrong
    bad = pred.copy()
    bad[0, 0] = np.nan
    assert all(math.isnan(v) for v in keypoint_errors(bad, X, R, t, LINEMOD_K).values())
    with pytest.raises(ValueError, match="19 2D keypoints for 20 3D keypoints"):
        keypoint_errors(pred[:19], X, R, t, LINEMOD_K)


def test_depth_ratio_hand_values_and_symmetry():
    """The centroid's depth, estimated over true: a box centred at (0, 0, 50) in the model frame."""
    from kpd6d.evaluation.errors import depth_ratio

    box = np.array([[x, y, z] for x in (-10, 10) for y in (-20, 20) for z in (30, 70)], dtype=np.float64)
    I3 = np.eye(3)
    assert depth_ratio(I3, [0, 0, 1100.0], I3, [0, 0, 1000.0], box) == pytest.approx(1150 / 1050)
    Rx = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # 90 deg about x: the centre moves to (0, -50, 0)
    assert depth_ratio(Rx, [0, 0, 1100.0], I3, [0, 0, 1000.0], box) == pytest.approx(1100 / 1050)
    # 180 deg about the box's own z axis through its centre maps it onto itself: the GT up to that symmetry is exact
    Rz = np.diag([-1.0, -1.0, 1.0])
    assert depth_ratio(Rz, [5.0, -3.0, 1000.0], I3, [5.0, -3.0, 1000.0], box) == pytest.approx(1.0)
    assert np.isnan(depth_ratio(np.full((3, 3), np.nan), [0, 0, 1.0], I3, [0, 0, 1.0], box))


def test_depth_by_visibility_bands():
    from kpd6d.evaluation.runner import depth_by_visibility

    recs = [{"visib_fract": v, "depth_ratio": d} for v, d in
            [(0.2, 1.10), (0.3, 1.00), (0.49, 1.30), (0.5, 1.01), (0.95, 0.97), (1.0, 1.0), (1.0, np.nan)]]
    recs.append({"add": 1.0})  # unmatched: no ratio
    b = depth_by_visibility(recs)
    assert [x["n"] for x in b] == [3, 1, 0, 2]
    assert b[0]["median"] == pytest.approx(1.10) and b[0]["within"] == pytest.approx(1 / 3)
    assert b[1]["within"] == 1.0 and np.isnan(b[2]["median"]) and b[3]["within"] == 0.5
