"""PnP solvers: accuracy on the real LM-O meshes, RANSAC vs least squares, batch vs single,
confidence weighting (checked against scipy's least_squares), and degenerate input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from scipy.optimize import least_squares

from kpd6d.config import config_dir
from kpd6d.evaluation import add_error
from kpd6d.geometry import LINEMOD_K, project_points, random_rotation
from kpd6d.pnp import BatchPoseEstimate, PoseEstimate
from kpd6d.pnp.checks import diagnose_solutions
from kpd6d.registry import PNP_SOLVERS, build_from_cfg

SOLVERS = ["epnp", "iterative", "sqpnp", "epnp_ransac", "sqpnp_ransac", "dlt", "weighted_lm"]


def random_pose(rng):
    z = rng.uniform(400.0, 1200.0)
    t = np.array([rng.uniform(-0.15, 0.15) * z, rng.uniform(-0.1, 0.1) * z, z])
    return random_rotation(rng), t


def synthetic(rng, n=50, noise=0.0, B=None):
    """Points in a 200 mm box, a LineMod-distance pose, their (noisy) projections."""
    if B is not None:
        items = [synthetic(rng, n, noise) for _ in range(B)]
        return tuple(np.stack(a) for a in zip(*items))
    X = rng.uniform(-100, 100, (n, 3))
    R, t = random_pose(rng)
    uv = project_points(X, LINEMOD_K, R, t) + rng.normal(0, noise, (n, 2)) if noise else project_points(X, LINEMOD_K, R, t)
    return X, uv, R, t


@pytest.fixture(scope="module")
def lmo_points(lmo_models):
    """50 surface points of every LM-O model (the keypoint count of the benchmark)."""
    return {m.obj_id: (m, m.sample_points(50, seed=m.obj_id)) for m in lmo_models}


def test_conf_files_build_every_solver():
    files = sorted((config_dir() / "pnp").glob("*.yaml"))
    names = {f.stem for f in files}
    assert set(SOLVERS) <= names
    for f in files:
        cfg = OmegaConf.load(f)
        assert cfg.name == f.stem
        solver = build_from_cfg(PNP_SOLVERS, cfg)
        assert callable(solver) and hasattr(solver, "solve_batch")


@pytest.mark.parametrize("name", SOLVERS)
def test_noise_free_lmo_poses_are_recovered(name, lmo_points):
    rng = np.random.default_rng(7)
    solver = PNP_SOLVERS.build(name)
    for _obj_id, (model, X) in lmo_points.items():
        for _ in range(2):
            R, t = random_pose(rng)
            est = solver(X, project_points(X, LINEMOD_K, R, t), LINEMOD_K)
            assert isinstance(est, PoseEstimate)
            assert est.ok, est.reason
            assert est.R.dtype == np.float64 and est.R.shape == (3, 3) and est.t.shape == (3,)
            assert est.inliers.dtype == bool and est.inliers.shape == (50,) and est.inliers.all()
            err = add_error(est.R, est.t, R, t, model.vertices)
            assert err < 1e-3 * model.diameter, (name, model.obj_id, err)


def test_ransac_matches_least_squares_on_true_inliers(lmo_points):
    """1 px noise + 30 % gross outliers: RANSAC's ADD within 10 % (+1 mm) of LM on the true inliers."""
    rng = np.random.default_rng(11)
    ransac = PNP_SOLVERS.build("epnp_ransac")
    lsq = PNP_SOLVERS.build("iterative")
    models = list(lmo_points.values())
    good = 0
    inlier_recall = []
    for trial in range(100):
        model, X = models[trial % len(models)]
        R, t = random_pose(rng)
        uv = project_points(X, LINEMOD_K, R, t) + rng.normal(0, 1.0, (50, 2))
        out = rng.choice(50, 15, replace=False)
        angle = rng.uniform(0, 2 * np.pi, 15)
        uv[out] += rng.uniform(30, 150, (15, 1)) * np.c_[np.cos(angle), np.sin(angle)]  # gross outliers
        true_in = np.ones(50, dtype=bool)
        true_in[out] = False
        est = ransac(X, uv, LINEMOD_K)
        ref = lsq(X[true_in], uv[true_in], LINEMOD_K)
        assert est.ok and ref.ok, (est.reason, ref.reason)
        e_r = add_error(est.R, est.t, R, t, model.vertices)
        e_l = add_error(ref.R, ref.t, R, t, model.vertices)
        good += e_r <= 1.1 * e_l + 1.0
        inlier_recall.append((est.inliers & true_in).sum() / true_in.sum())
        assert not (est.inliers & ~true_in).any()  # no gross outlier accepted
    assert good >= 95, good
    assert np.mean(inlier_recall) > 0.97


def test_sqpnp_ransac_is_sqpnp_on_the_true_inliers(lmo_points):
    """1.5 px noise + 20 % gross outliers: sqpnp_ransac keeps every true inlier (its threshold follows the
    object's size) and rejects every outlier, so its pose is OpenCV's SQPnP on exactly the true inliers;
    plain SQPnP on all points is pulled off by the outliers. Without outliers it is SQPnP on all points."""
    rng = np.random.default_rng(12)
    robust, plain = PNP_SOLVERS.build("sqpnp_ransac"), PNP_SOLVERS.build("sqpnp")
    models = list(lmo_points.values())
    worse_plain = 0
    for trial in range(40):
        model, X = models[trial % len(models)]
        R, t = random_pose(rng)
        clean = project_points(X, LINEMOD_K, R, t) + rng.normal(0, 1.5, (50, 2))
        d = float(np.linalg.norm(clean.max(0) - clean.min(0)))
        uv = clean.copy()
        out = rng.choice(50, 10, replace=False)
        angle = rng.uniform(0, 2 * np.pi, 10)
        uv[out] += rng.uniform(0.3, 0.6) * d * np.c_[np.cos(angle), np.sin(angle)]  # gross outliers
        true_in = np.ones(50, dtype=bool)
        true_in[out] = False
        est = robust(X, uv, LINEMOD_K)
        assert est.ok, est.reason
        assert est.inliers.tolist() == true_in.tolist(), trial
        ok, rvec, tvec = cv2.solvePnP(X[true_in], uv[true_in], LINEMOD_K, None, flags=cv2.SOLVEPNP_SQPNP)
        assert ok
        assert np.allclose(est.R, cv2.Rodrigues(rvec)[0], atol=1e-9) and np.allclose(est.t, tvec.ravel(), atol=1e-6)
        e_robust = add_error(est.R, est.t, R, t, model.vertices)
        p = plain(X, uv, LINEMOD_K)
        worse_plain += (not p.ok) or add_error(p.R, p.t, R, t, model.vertices) > 2 * e_robust
        # no outliers: every point is an inlier and the result is SQPnP on all of them
        est0, p0 = robust(X, clean, LINEMOD_K), plain(X, clean, LINEMOD_K)
        assert est0.ok and est0.inliers.all() and np.allclose(est0.t, p0.t, atol=1e-6)
    assert worse_plain >= 30, worse_plain


def test_ransac_threshold_follows_the_object_size():
    fixed = PNP_SOLVERS.build("epnp_ransac")
    rel = PNP_SOLVERS.build("epnp_ransac", relative_error=0.1)
    small = np.array([[0.0, 0.0], [30.0, 40.0]])     # diagonal 50 px -> the 8 px floor
    large = np.array([[0.0, 0.0], [300.0, 400.0]])   # diagonal 500 px -> 50 px
    assert fixed.threshold(large) == 8.0
    assert rel.threshold(small) == 8.0 and rel.threshold(large) == pytest.approx(50.0)
    # 6 px noise on a large object: a fixed 8 px threshold drops true inliers, the relative one keeps them
    rng = np.random.default_rng(3)
    X = rng.uniform(-100, 100, (50, 3))
    R, t = random_rotation(rng), np.array([0.0, 0.0, 350.0])
    uv = project_points(X, LINEMOD_K, R, t) + rng.normal(0, 6.0, (50, 2))
    assert fixed(X, uv, LINEMOD_K).inliers.sum() < 50 <= rel(X, uv, LINEMOD_K).inliers.sum()


@pytest.mark.parametrize("name", SOLVERS)
def test_batch_agrees_with_single_and_array_types(name):
    rng = np.random.default_rng(3)
    X, uv, _, t = synthetic(rng, n=30, noise=1.0, B=6)
    conf = rng.uniform(0.2, 1.0, (6, 30))
    conf[0, :3] = 0.0  # excluded points
    solver = PNP_SOLVERS.build(name)
    batch = solver.solve_batch(X, uv, LINEMOD_K, conf)
    assert isinstance(batch, BatchPoseEstimate) and len(batch) == 6
    assert batch.R.shape == (6, 3, 3) and batch.t.shape == (6, 3) and batch.inliers.shape == (6, 30)
    assert batch.ok.all(), batch.reasons
    assert not batch.inliers[0, :3].any()
    # near the truth under 1 px noise (DLT, an algebraic fit, is the least accurate: up to 6.4 % of z here)
    assert (np.linalg.norm(batch.t - t, axis=-1) < (0.1 if name == "dlt" else 0.02) * t[:, 2]).all()
    # weighted_lm starts batches from DLT and single problems from EPnP: both converge to the same minimum
    tol = 1e-6 if name == "weighted_lm" else 1e-9
    for b in range(6):
        single = solver(X[b], uv[b], LINEMOD_K, conf[b])
        assert single.ok
        np.testing.assert_allclose(batch.R[b], single.R, atol=tol)
        np.testing.assert_allclose(batch.t[b], single.t, atol=tol * 1e3)
        np.testing.assert_array_equal(batch.inliers[b], single.inliers)
        assert batch[b].ok and np.allclose(batch[b].t, batch.t[b])
    # torch in -> torch out (same values); per-problem K (B, 3, 3) is the same as a shared one
    tb = solver.solve_batch(torch.tensor(X), torch.tensor(uv), torch.tensor(LINEMOD_K), torch.tensor(conf))
    assert isinstance(tb.R, torch.Tensor) and tb.R.dtype == torch.float64 and tb.ok.dtype == torch.bool
    np.testing.assert_allclose(tb.t.numpy(), batch.t, atol=tol * 1e3)
    kb = solver.solve_batch(X, uv, np.broadcast_to(LINEMOD_K, (6, 3, 3)), conf)
    np.testing.assert_allclose(kb.t, batch.t, atol=tol * 1e3)
    ts = solver(torch.tensor(X[1]), torch.tensor(uv[1]), torch.tensor(LINEMOD_K))
    assert isinstance(ts.t, torch.Tensor) and ts.ok


def _weighted_reference(X, uv, K, w, R0, t0):
    """Independent weighted least squares: scipy least_squares over (rvec, t) with cv2.projectPoints."""

    def residuals(p):
        proj, _ = cv2.projectPoints(X, p[:3], p[3:], K, None)
        return (np.sqrt(w)[:, None] * (proj.reshape(-1, 2) - uv)).ravel()

    p0 = np.r_[cv2.Rodrigues(R0)[0].ravel(), t0]
    sol = least_squares(residuals, p0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return cv2.Rodrigues(sol.x[:3])[0], sol.x[3:]


def test_weighted_lm_minimises_the_confidence_weighted_error():
    rng = np.random.default_rng(5)
    X, uv, R, t = synthetic(rng, n=25, noise=2.0)
    w = rng.uniform(0.05, 1.0, 25)
    est = PNP_SOLVERS.build("weighted_lm")(X, uv, LINEMOD_K, w)
    assert est.ok
    R_ref, t_ref = _weighted_reference(X, uv, LINEMOD_K, w, R, t)
    np.testing.assert_allclose(est.R, R_ref, atol=1e-7)
    np.testing.assert_allclose(est.t, t_ref, atol=1e-4)


def test_weighted_lm_down_weights_an_outlier():
    rng = np.random.default_rng(8)
    X, uv, R, t = synthetic(rng, n=20, noise=0.5)
    diameter = np.linalg.norm(X[:, None] - X[None], axis=-1).max()
    uv[4] += [60.0, -45.0]  # one gross outlier
    solver = PNP_SOLVERS.build("weighted_lm")
    conf = np.ones(20)
    uniform = solver(X, uv, LINEMOD_K, conf)
    conf[4] = 1e-3
    weighted = solver(X, uv, LINEMOD_K, conf)
    clean = solver(np.delete(X, 4, 0), np.delete(uv, 4, 0), LINEMOD_K)
    e_u = add_error(uniform.R, uniform.t, R, t, X)
    e_w = add_error(weighted.R, weighted.t, R, t, X)
    e_c = add_error(clean.R, clean.t, R, t, X)
    assert e_w < 0.2 * e_u, (e_w, e_u)
    assert abs(e_w - e_c) < 0.1 * e_c + 0.05 * 1e-2 * diameter
    # confidence 0 removes the point entirely: the same pose as dropping it
    conf[4] = 0.0
    dropped = solver(X, uv, LINEMOD_K, conf)
    np.testing.assert_allclose(dropped.t, clean.t, atol=1e-6)
    assert not dropped.inliers[4] and dropped.inliers.sum() == 19


# -- degenerate input -----------------------------------------------------------------------------
def _case(kind, rng):
    X, uv, R, t = synthetic(rng, n=12)
    conf = None
    if kind == "nan_3d":
        X[3, 1] = np.nan
    elif kind == "inf_2d":
        uv[5, 0] = np.inf
    elif kind == "collinear_3d":
        X = np.outer(np.linspace(-50, 50, 12), [1.0, 2.0, -0.5])
        uv = project_points(X, LINEMOD_K, R, t)
    elif kind == "coincident_3d":
        X = np.tile([10.0, 20.0, 30.0], (12, 1))
        uv = project_points(X, LINEMOD_K, R, t) + rng.normal(0, 5, (12, 2))
    elif kind == "collinear_2d":
        uv = np.c_[np.linspace(100, 500, 12), np.full(12, 240.0)]
    elif kind == "coincident_2d":
        uv = np.tile([320.0, 240.0], (12, 1))
    elif kind == "all_confidences_zero":
        conf = np.zeros(12)
    elif kind == "negative_confidence":
        conf = np.ones(12)
        conf[2] = -1.0
    elif kind == "too_few":
        conf = np.zeros(12)
        conf[:3] = 1.0
    elif kind == "bad_K":
        return X, uv, np.zeros((3, 3)), conf
    return X, uv, LINEMOD_K, conf


DEGENERATE = {
    "nan_3d": "NaN/inf",
    "inf_2d": "NaN/inf",
    "collinear_3d": "3D points are collinear",
    "coincident_3d": "all 3D points coincide",
    "collinear_2d": "2D points are collinear",
    "coincident_2d": "all 2D points coincide",
    "all_confidences_zero": "all confidences are zero",
    "negative_confidence": "confidences must be >= 0",
    "too_few": "too few points: 3 usable",
    "bad_K": "K is not a valid camera matrix",
}


@pytest.mark.parametrize("name", SOLVERS)
def test_degenerate_inputs_give_reasons_never_exceptions(name):
    rng = np.random.default_rng(2)
    solver = PNP_SOLVERS.build(name)
    for kind, expected in DEGENERATE.items():
        X, uv, K, conf = _case(kind, rng)
        est = solver(X, uv, K, conf)
        assert not est.ok, (name, kind)
        assert expected in est.reason, (name, kind, est.reason)
        assert np.isnan(est.R).all() and np.isnan(est.t).all() and not est.inliers.any()
    # a batch mixing degenerate and good problems: only the degenerate ones fail
    Xs, uvs = [], []
    for kind in ["good", "collinear_3d", "good", "nan_3d", "good"]:
        X, uv, _, _ = _case(kind, rng)
        Xs.append(X)
        uvs.append(uv)
    res = solver.solve_batch(np.stack(Xs), np.stack(uvs), LINEMOD_K)
    assert res.ok.tolist() == [True, False, True, False, True], res.reasons
    assert "collinear" in res.reasons[1] and "NaN" in res.reasons[3] and res.reasons[0] == ""


@pytest.mark.parametrize("name", SOLVERS)
def test_minimum_point_counts(name):
    solver = PNP_SOLVERS.build(name)
    rng = np.random.default_rng(4)
    X, uv, _, _ = synthetic(rng, n=solver.min_points)
    assert solver(X, uv, LINEMOD_K).ok
    est = solver(X[:-1], uv[:-1], LINEMOD_K)
    assert not est.ok and f"needs >= {solver.min_points}" in est.reason


@pytest.mark.parametrize("name", SOLVERS)
def test_points_behind_the_camera_are_never_ok(name):
    """Projections of an object behind the camera (t_z < 0): no solver may report a usable pose."""
    rng = np.random.default_rng(6)
    X = rng.uniform(-100, 100, (30, 3))
    R = random_rotation(rng)
    uv = project_points(X, LINEMOD_K, R, np.array([20.0, -10.0, -800.0]))
    strict = PNP_SOLVERS.build(name, max_reprojection_error=2.0)
    est = strict(X, uv, LINEMOD_K)
    assert not est.ok
    assert "behind the camera" in est.reason or "reprojection error" in est.reason
    if name in ("iterative", "dlt"):  # these fit the behind-camera pose exactly; the check rejects it
        est = PNP_SOLVERS.build(name)(X, uv, LINEMOD_K)
        assert not est.ok and "behind the camera" in est.reason, est.reason


def test_nan_in_an_excluded_point_is_ignored():
    rng = np.random.default_rng(9)
    X, uv, _, t = synthetic(rng, n=12)
    X[0] = np.nan
    conf = np.ones(12)
    conf[0] = 0.0
    for name in SOLVERS:
        est = PNP_SOLVERS.build(name)(X, uv, LINEMOD_K, conf)
        assert est.ok, (name, est.reason)
        assert np.allclose(est.t, t, atol=1e-6)


def test_coplanar_points():
    """Planar objects: sqpnp / iterative solve them; dlt and OpenCV's EPnP (unreliable there) refuse."""
    rng = np.random.default_rng(10)
    for _ in range(3):
        X = np.c_[rng.uniform(-100, 100, (20, 2)), np.zeros(20)] @ random_rotation(rng).T
        R, t = random_pose(rng)
        uv = project_points(X, LINEMOD_K, R, t)
        for name in SOLVERS:
            est = PNP_SOLVERS.build(name)(X, uv, LINEMOD_K)
            if name in ("dlt", "epnp", "epnp_ransac", "sqpnp_ransac", "weighted_lm"):  # their EPnP starts refuse
                assert not est.ok and "coplanar" in est.reason, (name, est.reason)
            else:
                assert est.ok, (name, est.reason)
                assert add_error(est.R, est.t, R, t, X) < 1e-3
        lm = PNP_SOLVERS.build("weighted_lm", init="sqpnp", batch_init=None)
        est = lm(X, uv, LINEMOD_K)
        assert est.ok and add_error(est.R, est.t, R, t, X) < 1e-3
        batch = lm.solve_batch(np.stack([X, X]), np.stack([uv, uv]), LINEMOD_K)
        assert batch.ok.all() and add_error(batch.R[1], batch.t[1], R, t, X) < 1e-3


def test_mismatched_shapes_raise_value_error_naming_them():
    solver = PNP_SOLVERS.build("epnp")
    X = np.zeros((10, 3))
    with pytest.raises(ValueError, match=r"points_2d.*\(9, 2\)"):
        solver(X, np.zeros((9, 2)), LINEMOD_K)
    with pytest.raises(ValueError, match=r"points_3d \(10, 2\)"):
        solver(np.zeros((10, 2)), np.zeros((10, 2)), LINEMOD_K)
    with pytest.raises(ValueError, match=r"K \(4, 4\)"):
        solver(X, np.zeros((10, 2)), np.eye(4))
    with pytest.raises(ValueError, match=r"confidences \(7,\)"):
        solver(X, np.zeros((10, 2)), LINEMOD_K, np.ones(7))
    with pytest.raises(ValueError, match=r"K \(2, 3, 3\)"):
        solver.solve_batch(np.zeros((3, 10, 3)), np.zeros((3, 10, 2)), np.stack([LINEMOD_K] * 2))


def test_solution_checks_reject_non_finite_improper_and_behind():
    X = np.random.default_rng(0).uniform(-50, 50, (1, 10, 3))
    uv = np.zeros((1, 10, 2))
    use = np.ones((1, 10), dtype=bool)
    K = LINEMOD_K[None]
    t = np.array([[0.0, 0.0, 500.0]])

    def why(R, tt):
        return diagnose_solutions(R[None], tt, X, uv, K, use)[0]

    assert why(np.eye(3), t) == ""
    assert "non-finite" in why(np.full((3, 3), np.nan), t)
    assert "improper" in why(np.diag([1.0, 1.0, -1.0]), t)
    assert "improper" in why(2 * np.eye(3), t)
    assert "behind the camera" in why(np.eye(3), -t)


def test_ransac_and_weighted_lm_parameters_are_validated():
    with pytest.raises(ValueError, match="reprojection_error"):
        PNP_SOLVERS.build("epnp_ransac", reprojection_error=0)
    with pytest.raises(ValueError, match="min_inliers"):
        PNP_SOLVERS.build("epnp_ransac", min_inliers=3)
    with pytest.raises(ValueError, match="relative_error"):
        PNP_SOLVERS.build("sqpnp_ransac", relative_error=1.5)
    with pytest.raises(ValueError, match="cannot initialise itself"):
        PNP_SOLVERS.build("weighted_lm", init="weighted_lm")
    with pytest.raises(KeyError, match="known PnP solvers: dlt, epnp"):
        PNP_SOLVERS.build("weighted_lm", init="nope")
    with pytest.raises(TypeError, match="unknown parameter"):
        PNP_SOLVERS.build("epnp", threshold=3)
