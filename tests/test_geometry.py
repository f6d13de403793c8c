"""kpd6d.geometry against independent computations (OpenCV, scipy, explicit 4x4 algebra, hand values)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from kpd6d import geometry as G

RNG_SEED = 1234


@pytest.fixture
def rng():
    return np.random.default_rng(RNG_SEED)


def _pose(rng, z=(400.0, 1200.0)):
    R = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    t = np.array([rng.uniform(-100, 100), rng.uniform(-100, 100), rng.uniform(*z)])
    return R, t


def _T(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


# -- projection --------------------------------------------------------------------------------
def test_project_points_matches_cv2_projectPoints(rng):
    K = G.LINEMOD_K
    for _ in range(5):
        R, t = _pose(rng)
        X = rng.uniform(-100, 100, (40, 3))
        ref, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K, None)
        np.testing.assert_allclose(G.project_points(X, K, R, t), ref.reshape(-1, 2), rtol=0, atol=1e-9)
        _uv, z = G.project_points(X, K, R, t, return_depth=True)
        np.testing.assert_allclose(z, (X @ R.T + t)[:, 2], atol=1e-9)


def test_project_points_camera_frame_and_hand_value():
    K = np.array([[100.0, 0, 50], [0, 200.0, 60], [0, 0, 1]])
    # (10, -5, 100) in the camera frame: u = 100*10/100 + 50 = 60, v = 200*(-5)/100 + 60 = 50
    np.testing.assert_allclose(G.project_points(np.array([[10.0, -5.0, 100.0]]), K), [[60.0, 50.0]])


def test_project_points_batched_numpy_and_torch(rng):
    B, N = 4, 7
    Rs = Rotation.random(B, random_state=1).as_matrix()
    ts = np.c_[rng.uniform(-50, 50, (B, 2)), rng.uniform(500, 900, B)]
    X = rng.uniform(-50, 50, (B, N, 3))
    Ks = np.stack([G.LINEMOD_K * [[s, 1, 1], [1, s, 1], [1, 1, 1]] for s in (0.5, 1.0, 1.5, 2.0)])
    out = G.project_points(X, Ks, Rs, ts)
    assert out.shape == (B, N, 2)
    for b in range(B):
        ref, _ = cv2.projectPoints(X[b], cv2.Rodrigues(Rs[b])[0], ts[b], Ks[b], None)
        np.testing.assert_allclose(out[b], ref.reshape(-1, 2), atol=1e-9)
    tout = G.project_points(torch.tensor(X), torch.tensor(Ks), torch.tensor(Rs), torch.tensor(ts))
    assert isinstance(tout, torch.Tensor) and tout.dtype == torch.float64
    np.testing.assert_allclose(tout.numpy(), out, atol=1e-9)
    # shared model points (N, 3) with a batch of poses
    shared = G.project_points(X[0], G.LINEMOD_K, Rs, ts)
    assert shared.shape == (B, N, 2)
    np.testing.assert_allclose(shared[2], G.project_points(X[0], G.LINEMOD_K, Rs[2], ts[2]), atol=1e-12)


def test_project_points_R_without_t_is_a_clear_error():
    with pytest.raises(ValueError, match="R given without t"):
        G.project_points(np.zeros((2, 3)), G.LINEMOD_K, np.eye(3), None)
    with pytest.raises(ValueError, match="t given without R"):
        G.project_points(np.zeros((2, 3)), G.LINEMOD_K, None, np.zeros(3))


# -- rigid transforms ----------------------------------------------------------------------------
def test_transform_compose_invert_match_4x4_algebra(rng):
    (R1, t1), (R2, t2) = _pose(rng), _pose(rng)
    X = rng.normal(size=(10, 3)) * 50
    Xh = np.c_[X, np.ones(len(X))]
    np.testing.assert_allclose(G.transform_points(X, R1, t1), (_T(R1, t1) @ Xh.T).T[:, :3], atol=1e-9)
    R, t = G.compose_poses(R1, t1, R2, t2)
    np.testing.assert_allclose(_T(R, t), _T(R1, t1) @ _T(R2, t2), atol=1e-9)
    Ri, ti = G.invert_pose(R1, t1)
    np.testing.assert_allclose(_T(Ri, ti), np.linalg.inv(_T(R1, t1)), atol=1e-9)
    T = G.pose_matrix(R1, t1)
    np.testing.assert_allclose(T, _T(R1, t1))
    Rs, ts = G.split_pose(T)
    np.testing.assert_allclose(Rs, R1)
    np.testing.assert_allclose(ts, t1)
    # torch, batched
    Tt = G.pose_matrix(torch.tensor(np.stack([R1, R2])), torch.tensor(np.stack([t1, t2])))
    np.testing.assert_allclose(Tt.numpy(), np.stack([_T(R1, t1), _T(R2, t2)]), atol=1e-12)
    Rc, tc = G.compose_poses(*(torch.tensor(a) for a in (R1, t1, R2, t2)))
    np.testing.assert_allclose(_T(Rc.numpy(), tc.numpy()), _T(R1, t1) @ _T(R2, t2), atol=1e-9)


# -- rotations -----------------------------------------------------------------------------------
def test_rotation_error_deg_matches_scipy_and_hand(rng):
    Rz30 = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    assert G.rotation_error_deg(np.eye(3), Rz30) == pytest.approx(30.0, abs=1e-9)
    A = Rotation.random(20, random_state=3).as_matrix()
    Bm = Rotation.random(20, random_state=4).as_matrix()
    ref = np.degrees((Rotation.from_matrix(A).inv() * Rotation.from_matrix(Bm)).magnitude())
    np.testing.assert_allclose(G.rotation_error_deg(A, Bm), ref, atol=1e-6)
    np.testing.assert_allclose(G.rotation_error_deg(torch.tensor(A), torch.tensor(Bm)).numpy(), ref, atol=1e-6)
    assert G.rotation_error_deg(A[0], A[0]) == pytest.approx(0.0, abs=1e-5)


def test_translation_error_hand():
    assert G.translation_error(np.array([3.0, 4.0, 0.0]), np.zeros(3)) == pytest.approx(5.0)


def test_rotation_about_axis_matches_cv2_rodrigues(rng):
    for _ in range(5):
        axis = rng.normal(size=3)
        angle = rng.uniform(-math.pi, math.pi)
        ref = cv2.Rodrigues(axis / np.linalg.norm(axis) * angle)[0]
        np.testing.assert_allclose(G.rotation_about_axis(axis, angle), ref, atol=1e-12)
    with pytest.raises(ValueError, match="axis"):
        G.rotation_about_axis([0, 0, 0], 1.0)


def test_random_rotation_is_haar_uniform():
    rng = np.random.default_rng(0)
    R = G.random_rotation(rng, 20000)
    np.testing.assert_allclose(R @ R.swapaxes(-1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    # Haar measure: E[R] = 0 and the angle has density (1 - cos θ)/π, mean π/2 + 2/π
    assert np.abs(R.mean(0)).max() < 0.02
    angles = Rotation.from_matrix(R).magnitude()
    assert angles.mean() == pytest.approx(math.pi / 2 + 2 / math.pi, abs=0.02)
    assert G.random_rotation(np.random.default_rng(5)).shape == (3, 3)


# -- viewpoints ----------------------------------------------------------------------------------
def test_look_at_pose_puts_target_on_optical_axis_and_up_upwards():
    eye = np.array([300.0, -400.0, 500.0])
    target = np.array([10.0, 20.0, 30.0])
    R, t = G.look_at_pose(eye, target, up=(0, 0, 1))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ eye + t, 0.0, atol=1e-9)  # camera centre at the eye
    pc = R @ target + t
    np.testing.assert_allclose(pc[:2], 0.0, atol=1e-9)
    assert pc[2] == pytest.approx(np.linalg.norm(target - eye))
    above = R @ (target + np.array([0.0, 0.0, 10.0])) + t
    assert above[1] < 0  # world up is image up (-y)
    # looking straight down the up axis still gives a rotation
    R2, _ = G.look_at_pose([0, 0, 500.0], up=(0, 0, 1))
    np.testing.assert_allclose(R2 @ R2.T, np.eye(3), atol=1e-12)


@pytest.mark.parametrize("up", [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (1.0, 1.0, 0.0)])
def test_pose_from_view_round_trip(up):
    az, el, d, inplane = 0.7, 0.3, 800.0, 0.4
    R, t = G.pose_from_view(az, el, d, inplane, up=up)
    np.testing.assert_allclose(np.linalg.norm(t), d, rtol=1e-12)  # origin at distance d on the axis
    np.testing.assert_allclose(t[:2], 0.0, atol=1e-9)
    az2, el2, d2 = G.view_from_pose(R, t, up=up)
    assert (az2, el2, d2) == pytest.approx((az, el, d), abs=1e-9)
    # elevation is measured towards `up`: the eye's component along up is d sin(el)
    eye = -R.T @ t
    u = np.asarray(up) / np.linalg.norm(up)
    assert eye @ u == pytest.approx(d * math.sin(el))


# -- crops and affines ---------------------------------------------------------------------------
def test_box_to_crop_affine_matches_cv2_getAffineTransform():
    box = np.array([100.0, 50.0, 80.0, 40.0])  # x, y, w, h -> square side 80 * 1.5 = 120
    W = H = 256
    A = G.box_to_crop_affine(box, W, scale=1.5)
    cx, cy, s = 140.0, 70.0, 120.0
    # three image points and where a crop of side s centred on (cx, cy) puts them (pixel centres at
    # integers: the crop's left edge x = cx - s/2 maps to -0.5)
    src = np.float32([[cx, cy], [cx - s / 2, cy - s / 2], [cx + s / 2, cy - s / 2]])
    dst = np.float32([[(W - 1) / 2, (H - 1) / 2], [-0.5, -0.5], [W - 0.5, -0.5]])
    np.testing.assert_allclose(A, cv2.getAffineTransform(src, dst), atol=1e-4)
    Ai = G.invert_affine(A)
    np.testing.assert_allclose(Ai, cv2.invertAffineTransform(A), atol=1e-9)
    uv = np.array([[10.0, 20.0], [300.0, 7.0]])
    np.testing.assert_allclose(G.affine_apply(A, uv), cv2.transform(uv[None], A)[0], atol=1e-9)
    np.testing.assert_allclose(G.affine_apply(Ai, G.affine_apply(A, uv)), uv, atol=1e-9)
    At = G.box_to_crop_affine(torch.tensor(box), (W, H), scale=1.5)
    np.testing.assert_allclose(At.numpy(), A, atol=1e-12)
    np.testing.assert_allclose(G.invert_affine(At).numpy(), Ai, atol=1e-9)
    # non-square: each axis scaled on its own
    A2 = G.box_to_crop_affine(box, (128, 64), square=False)
    np.testing.assert_allclose(G.affine_apply(A2, np.array([[100.0, 50.0]])), [[-0.5, -0.5]], atol=1e-9)


def test_bbox_from_points_hand():
    uv = np.array([[3.0, 4.0], [10.0, -2.0], [5.0, 8.0]])
    np.testing.assert_allclose(G.bbox_from_points(uv), [3.0, -2.0, 7.0, 10.0])
    np.testing.assert_allclose(G.bbox_from_points(torch.tensor(uv)).numpy(), [3.0, -2.0, 7.0, 10.0])


# -- OpenCV <-> OpenGL ---------------------------------------------------------------------------
def test_opencv_to_opengl_conversions(rng):
    R, t = _pose(rng)
    X = rng.uniform(-50, 50, (5, 3))
    cam_pose = G.cv_pose_to_gl_camera_pose(R, t)
    gl = (np.linalg.inv(cam_pose) @ np.c_[X, np.ones(5)].T).T[:, :3]
    cv = X @ R.T + t
    np.testing.assert_allclose(gl, cv * [1, -1, -1], atol=1e-9)  # GL: y up, looking down -z
    assert (gl[:, 2] < 0).all()
    R2, t2 = G.gl_camera_pose_to_cv_pose(cam_pose)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-9)
    np.testing.assert_allclose(G.cv_pose_to_gl_model_view(R, t), np.linalg.inv(cam_pose), atol=1e-9)


def test_check_box_inputs_normalises_and_names_what_is_wrong():
    from kpd6d.geometry import check_box_inputs

    boxes, ids, idx, scores = check_box_inputs([[1, 2, 30, 40], [5, 6, 7, 8]], [3, 4], None, None, 2, {3: 0, 4: 0})
    assert boxes.dtype == np.float64 and boxes.shape == (2, 4)
    assert ids == [3, 4] and idx == [0, 0] and scores == [1.0, 1.0]
    with pytest.raises(ValueError, match="2 boxes but 1 obj_ids"):
        check_box_inputs([[1, 2, 30, 40], [5, 6, 7, 8]], [3], None, None, 1, {3: 0})
    with pytest.raises(ValueError, match=r"image_index out of range \[0, 1\)"):
        check_box_inputs([[1, 2, 30, 40]], [3], [1], None, 1, {3: 0})

    class Custom(ValueError):
        pass

    with pytest.raises(Custom, match=r"track: the KPD has no keypoints for object\(s\) \[9\]"):
        check_box_inputs([[1, 2, 30, 40]], [9], None, [0.5], 1, {3: 0}, error=Custom, where="track")


def test_clip_box_to_image_hand_values():
    from kpd6d.geometry import clip_box_to_image

    np.testing.assert_allclose(clip_box_to_image([-10, 5], [50, 500], 640, 480), [0, 5, 50, 475])
    assert clip_box_to_image([639, 10], [700, 20], 640, 480) is None  # 1 px left: under MIN_BOX_PX
    np.testing.assert_allclose(clip_box_to_image([638, 10], [700, 20], 640, 480), [638, 10, 2, 10])
