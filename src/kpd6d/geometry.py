"""BOP pose conventions, in one place.

* Units: millimetres. Camera: OpenCV (x right, y down, z forward). Pixel centres at integer
  coordinates (OpenCV's convention): the top-left pixel covers [-0.5, 0.5]^2.
* A pose (R, t) maps model to camera: ``x_c = R x_m + t``.
* OpenGL (pyrender) cameras look down -z with y up; the only conversion between the two lives here
  (:func:`cv_pose_to_gl_camera_pose`, :func:`gl_camera_pose_to_cv_pose`, :data:`CV_TO_GL`).

Every function accepts numpy arrays or torch tensors with arbitrary leading batch dimensions
(``(..., N, 3)`` points, ``(..., 3, 3)`` rotations / intrinsics, ``(..., 3)`` translations) and
returns the same array type. No other module re-implements projection.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = [
    "CV_TO_GL",
    "LINEMOD_IMAGE_SIZE",
    "LINEMOD_K",
    "MIN_BOX_PX",
    "ROTATION_ATOL",
    "affine_apply",
    "backproject",
    "bbox_from_points",
    "box_iou_xywh",
    "box_problem",
    "box_to_crop_affine",
    "check_box_inputs",
    "check_intrinsics",
    "clip_box_to_image",
    "clip_xywh_to_image",
    "compose_poses",
    "cv_pose_to_gl_camera_pose",
    "cv_pose_to_gl_model_view",
    "gl_camera_pose_to_cv_pose",
    "invert_affine",
    "invert_pose",
    "look_at_pose",
    "pose_from_view",
    "pose_matrix",
    "project_points",
    "random_rotation",
    "rotation_about_axis",
    "rotation_error_deg",
    "rotation_problem",
    "split_pose",
    "transform_points",
    "translation_error",
    "view_from_pose",
]

#: LineMod / LM-O camera (BOP), 640x480.
LINEMOD_K = np.array(
    [[572.4114, 0.0, 325.2611], [0.0, 573.57043, 242.04899], [0.0, 0.0, 1.0]], dtype=np.float64
)
LINEMOD_IMAGE_SIZE = (640, 480)  # (width, height)

#: Flips an OpenCV camera frame into an OpenGL one (and back: it is its own inverse).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


def _swap(x):
    return x.swapaxes(-1, -2)


def _as_like(value, like):
    """Convert ``value`` (numpy) to the array type / dtype / device of ``like``."""
    if _is_torch(like):
        import torch

        return torch.as_tensor(np.asarray(value), dtype=like.dtype, device=like.device)
    return np.asarray(value, dtype=like.dtype if np.issubdtype(like.dtype, np.floating) else np.float64)


# ---------------------------------------------------------------------------------------------
# rigid transforms
# ---------------------------------------------------------------------------------------------
def transform_points(points, R, t):
    """``x_c = R x_m + t`` for points (..., N, 3), R (..., 3, 3), t (..., 3)."""
    return points @ _swap(R) + t[..., None, :]


def compose_poses(R1, t1, R2, t2):
    """Pose of ``T1 @ T2`` (apply (R2, t2) first, then (R1, t1))."""
    R = R1 @ R2
    t = (R1 @ t2[..., :, None])[..., 0] + t1
    return R, t


def invert_pose(R, t):
    """Inverse of x -> R x + t: (R^T, -R^T t)."""
    Rt = _swap(R)
    return Rt, -(Rt @ t[..., :, None])[..., 0]


def pose_matrix(R, t):
    """4x4 homogeneous matrix(es) from R (..., 3, 3) and t (..., 3)."""
    if _is_torch(R):
        import torch

        T = torch.zeros((*R.shape[:-2], 4, 4), dtype=R.dtype, device=R.device)
    else:
        R = np.asarray(R, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64)
        T = np.zeros((*R.shape[:-2], 4, 4), dtype=np.float64)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def split_pose(T):
    """(R, t) from 4x4 matrix(es)."""
    return T[..., :3, :3], T[..., :3, 3]


# ---------------------------------------------------------------------------------------------
# projection
# ---------------------------------------------------------------------------------------------
def project_points(points, K, R=None, t=None, *, return_depth: bool = False):
    """Project model points (..., N, 3) to pixels (..., N, 2): ``x = K [R|t] X``.

    With ``R``/``t`` omitted the points are already in the camera frame. Points at or behind the
    camera plane (z <= 0) give non-finite or meaningless pixels; ``return_depth=True`` also returns
    z (..., N) so callers can test for that.
    """
    if (R is None) != (t is None):
        raise ValueError(f"project_points: {'R given without t' if t is None else 't given without R'}")
    pc = transform_points(points, R, t) if R is not None else points
    uvw = pc @ _swap(K)
    z = uvw[..., 2]
    uv = uvw[..., :2] / z[..., None]
    return (uv, pc[..., 2]) if return_depth else uv


def backproject(uv, depth, K):
    """Inverse of :func:`project_points` in the camera frame: pixels (..., N, 2) at depths z (..., N)
    (mm along the optical axis, as rendered depth maps hold) -> camera-frame points (..., N, 3).

    Map them to the model frame with ``transform_points(pc, *invert_pose(R, t))``.
    """
    K = K if _is_torch(uv) or not isinstance(K, np.ndarray) else np.asarray(K, dtype=np.float64)
    fx, fy, cx, cy = K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2]
    fx, fy, cx, cy = (v[..., None] if getattr(v, "ndim", 0) else v for v in (fx, fy, cx, cy))
    x = (uv[..., 0] - cx) / fx * depth
    y = (uv[..., 1] - cy) / fy * depth
    if _is_torch(uv):
        import torch

        return torch.stack([x, y, depth], dim=-1)
    return np.stack([x, y, np.broadcast_to(depth, x.shape)], axis=-1)


def bbox_from_points(uv):
    """Axis-aligned box (..., 4) as BOP's (x, y, w, h) from pixels (..., N, 2)."""
    lo = uv.min(axis=-2) if not _is_torch(uv) else uv.amin(dim=-2)
    hi = uv.max(axis=-2) if not _is_torch(uv) else uv.amax(dim=-2)
    wh = hi - lo
    if _is_torch(uv):
        import torch

        return torch.cat([lo, wh], dim=-1)
    return np.concatenate([lo, wh], axis=-1)


def box_to_crop_affine(box_xywh, out_size: tuple[int, int] | int, *, scale: float = 1.0, square: bool = True):
    """2x3 affine(s) mapping image pixels to crop pixels.

    The crop is centred on the box, ``scale`` times its size (its longer side when ``square``), and
    resized to ``out_size`` = (width, height). Pixel centres are at integer coordinates in both
    images, so the box centre maps to ``((W - 1) / 2, (H - 1) / 2)``. Works on (..., 4) boxes.
    Map crop pixels back to the image with ``affine_apply(invert_affine(A), uv)``.
    """
    if isinstance(out_size, int):
        out_size = (out_size, out_size)
    W, H = out_size
    torch_in = _is_torch(box_xywh)
    b = box_xywh if torch_in else np.asarray(box_xywh, dtype=np.float64)
    x, y, w, h = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    cx, cy = x + w / 2.0, y + h / 2.0
    if torch_in:
        import torch

        sw = torch.maximum(w, h) if square else w
        sh = torch.maximum(w, h) if square else h
        sw = torch.clamp(sw * scale, min=1e-6)
        sh = torch.clamp(sh * scale, min=1e-6)
        ax, ay = W / sw, H / sh
        A = torch.zeros((*b.shape[:-1], 2, 3), dtype=b.dtype, device=b.device)
    else:
        sw = np.maximum(w, h) if square else w
        sh = np.maximum(w, h) if square else h
        sw = np.maximum(sw * scale, 1e-6)
        sh = np.maximum(sh * scale, 1e-6)
        ax, ay = W / sw, H / sh
        A = np.zeros((*b.shape[:-1], 2, 3), dtype=np.float64)
    # crop pixel u' = ax * (u - cx) + (W - 1) / 2  (pixel centres at integers in both frames)
    A[..., 0, 0] = ax
    A[..., 1, 1] = ay
    A[..., 0, 2] = (W - 1) / 2.0 - ax * cx
    A[..., 1, 2] = (H - 1) / 2.0 - ay * cy
    return A


def invert_affine(A):
    """Inverse of 2x3 affine(s) (..., 2, 3)."""
    M = A[..., :2, :2]
    b = A[..., :2, 2]
    if _is_torch(A):
        import torch

        Mi = torch.linalg.inv(M)
        out = torch.zeros_like(A)
    else:
        Mi = np.linalg.inv(M)
        out = np.zeros_like(A, dtype=np.float64)
    out[..., :2, :2] = Mi
    out[..., :2, 2] = -(Mi @ b[..., :, None])[..., 0]
    return out


def affine_apply(A, uv):
    """Apply 2x3 affine(s) (..., 2, 3) to pixels (..., N, 2)."""
    return uv @ _swap(A[..., :2, :2]) + A[..., None, :2, 2]


# ---------------------------------------------------------------------------------------------
# rotations
# ---------------------------------------------------------------------------------------------
def rotation_error_deg(R1, R2):
    """Geodesic angle (degrees) between rotations (..., 3, 3)."""
    rel = _swap(R1) @ R2
    tr = rel[..., 0, 0] + rel[..., 1, 1] + rel[..., 2, 2]
    c = (tr - 1.0) / 2.0
    if _is_torch(c):
        import torch

        return torch.rad2deg(torch.arccos(torch.clamp(c, -1.0, 1.0)))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


#: How far a given rotation may be from orthonormal (max |R R^T - I|) and still count as one. Real
#: BOP ground truth is rounded: LM-O's scene_gt.json reaches 0.0096 (418 of 1816 instances above
#: 1e-3), so the tolerance is 5x that; a scaled, transposed-layout, quaternion or axis-angle input
#: is far above it.
ROTATION_ATOL = 0.05


def rotation_problem(R, atol: float = ROTATION_ATOL) -> str:
    """Why the (3, 3) matrix ``R`` is not a rotation ("" when it is one within ``atol``)."""
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    if not np.isfinite(R).all():
        return "is not finite"
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > atol:
        return f"is not orthonormal (max |R R^T - I| = {err:.3g} > {atol:g})"
    det = float(np.linalg.det(R))
    if det <= 0:
        return f"is a reflection, not a rotation (det = {det:.3g})"
    return ""


def translation_error(t1, t2):
    """Euclidean distance (mm) between translations (..., 3)."""
    d = t1 - t2
    return (d * d).sum(-1) ** 0.5


def rotation_about_axis(axis, angle: float) -> np.ndarray:
    """Rodrigues: rotation by ``angle`` radians about unit ``axis`` (3,)."""
    a = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(a)
    if n == 0 or not np.isfinite(n):
        raise ValueError(f"rotation axis must be a finite non-zero vector, got {axis!r}")
    a = a / n
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * Kx + (1 - math.cos(angle)) * (Kx @ Kx)


def random_rotation(rng: np.random.Generator, size: int | None = None) -> np.ndarray:
    """Uniform random rotation(s) (3, 3) or (size, 3, 3) (unit quaternions, Shoemake)."""
    n = 1 if size is None else size
    u1, u2, u3 = rng.random((3, n))
    q = np.stack(
        [
            np.sqrt(1 - u1) * np.sin(2 * np.pi * u2),
            np.sqrt(1 - u1) * np.cos(2 * np.pi * u2),
            np.sqrt(u1) * np.sin(2 * np.pi * u3),
            np.sqrt(u1) * np.cos(2 * np.pi * u3),
        ],
        axis=-1,
    )
    x, y, z, w = q.T
    R = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    ).reshape(n, 3, 3)
    return R[0] if size is None else R


# ---------------------------------------------------------------------------------------------
# viewpoints
# ---------------------------------------------------------------------------------------------
def look_at_pose(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)):
    """Model-to-camera pose (OpenCV) of a camera at ``eye`` (model frame, mm) looking at ``target``.

    The image's "up" (-y of the camera) is aligned with the projection of ``up``.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    z = target - eye
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-8:  # looking along `up`: pick any perpendicular
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in model coordinates
    t = -R @ eye
    return R, t


def pose_from_view(azimuth: float, elevation: float, distance: float, inplane: float = 0.0,
                   up=(0.0, 0.0, 1.0)):
    """Pose of a camera on a sphere around the model origin (angles in radians, distance in mm).

    Azimuth is measured about the model's ``up`` axis (z by default), elevation from the x-y plane
    towards +z; ``inplane`` rotates the image about the optical axis.
    """
    eye = distance * np.array(
        [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
    )
    up = np.asarray(up, dtype=np.float64)
    if not np.allclose(up, [0, 0, 1]):
        # express the sphere in a frame whose z is `up`
        Rz = _frame_with_z(up)
        eye = Rz @ eye
    R, t = look_at_pose(eye, up=up)
    if inplane:
        Rc = rotation_about_axis([0.0, 0.0, 1.0], inplane)
        R, t = Rc @ R, Rc @ t
    return R, t


def view_from_pose(R, t, up=(0.0, 0.0, 1.0)):
    """(azimuth, elevation, distance) of the camera of pose (R, t), the inverse of :func:`pose_from_view`."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    eye = -R.T @ t
    up = np.asarray(up, dtype=np.float64)
    if not np.allclose(up, [0, 0, 1]):
        eye = _frame_with_z(up).T @ eye
    d = float(np.linalg.norm(eye))
    return math.atan2(eye[1], eye[0]), math.asin(np.clip(eye[2] / max(d, 1e-12), -1, 1)), d


def _frame_with_z(z) -> np.ndarray:
    z = np.asarray(z, dtype=np.float64)
    z = z / np.linalg.norm(z)
    a = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(a, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


# ---------------------------------------------------------------------------------------------
# OpenCV <-> OpenGL (the only place)
# ---------------------------------------------------------------------------------------------
def cv_pose_to_gl_camera_pose(R, t) -> np.ndarray:
    """OpenGL camera-to-world 4x4 (pyrender ``camera_pose``) for a model placed at the world origin.

    Given the OpenCV model-to-camera pose (R, t): world = model frame, and the GL camera axes are
    the CV axes with y and z flipped.
    """
    T = pose_matrix(np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64))
    return np.linalg.inv(T) @ CV_TO_GL


def gl_camera_pose_to_cv_pose(camera_pose) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`cv_pose_to_gl_camera_pose`: OpenCV model-to-camera (R, t)."""
    T = np.linalg.inv(np.asarray(camera_pose, dtype=np.float64) @ CV_TO_GL)
    return T[:3, :3], T[:3, 3]


def cv_pose_to_gl_model_view(R, t) -> np.ndarray:
    """Model-to-GL-camera 4x4 (a node pose in a scene whose camera sits at the origin, identity pose)."""
    return CV_TO_GL @ pose_matrix(np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64))


#: Detections whose box is narrower or lower than this (px) give no pose: their crop holds nothing
#: a keypoint detector can localise (a 1x1 image gave three "ok" poses from zero-size boxes).
MIN_BOX_PX = 2.0


def box_iou_xywh(a, b) -> np.ndarray:
    """IoU of box ``a`` (4,) with boxes ``b`` (N, 4), all xywh (numpy); (N,)."""
    a = np.asarray(a, dtype=np.float64).reshape(4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    x1 = np.maximum(a[0], b[:, 0])
    y1 = np.maximum(a[1], b[:, 1])
    x2 = np.minimum(a[0] + a[2], b[:, 0] + b[:, 2])
    y2 = np.minimum(a[1] + a[3], b[:, 1] + b[:, 3])
    inter = np.clip(x2 - x1, 0, None) * np.clip(y2 - y1, 0, None)
    return inter / np.maximum(a[2] * a[3] + b[:, 2] * b[:, 3] - inter, 1e-9)


def clip_box_to_image(lo, hi, width: int, height: int, min_size: float = MIN_BOX_PX) -> np.ndarray | None:
    """The box from corner ``lo`` (2,) to ``hi`` (2,) px clipped to a ``width`` x ``height`` image, as (4,) xywh;
    None when less than ``min_size`` of it is left on a side."""
    size = np.array([width, height], dtype=np.float64)
    lo = np.clip(np.asarray(lo, dtype=np.float64), 0, size)
    hi = np.clip(np.asarray(hi, dtype=np.float64), 0, size)
    if (hi - lo).min() < min_size:
        return None
    return np.concatenate([lo, hi - lo])


def clip_xywh_to_image(box, width: int, height: int, min_size: float = MIN_BOX_PX) -> np.ndarray | None:
    """:func:`clip_box_to_image` of an (x, y, w, h) box (e.g. a BOP ``bbox_obj``)."""
    b = np.asarray(box, dtype=np.float64)
    return clip_box_to_image(b[:2], b[:2] + b[2:], width, height, min_size)


def box_problem(box, width: int, height: int, min_size: float = MIN_BOX_PX) -> str:
    """Why the detection box ``box`` (x, y, w, h) px cannot give a pose in a ``width`` x ``height``
    image ("" when it can): non-finite, w or h below ``min_size``, or no overlap with the image."""
    x, y, w, h = (float(v) for v in box)
    shown = f"[{x:.4g}, {y:.4g}, {w:.4g}, {h:.4g}]"
    if not np.isfinite([x, y, w, h]).all():
        return f"degenerate box {shown} (x, y, w, h): not finite"
    if w < min_size or h < min_size:
        return f"degenerate box {shown} (x, y, w, h): w or h below {min_size:g} px"
    if x >= width or y >= height or x + w <= 0 or y + h <= 0:
        return f"degenerate box {shown} (x, y, w, h): outside the {width}x{height} image"
    return ""


def check_box_inputs(boxes, obj_ids, image_index, scores, num_images: int, known_ids,
                     error: type[Exception] = ValueError, where: str = "predict_boxes"):
    """Given boxes for a pose pipeline: ``boxes`` (N, 4) xywh -> float64 (N, 4); ``obj_ids`` (N,);
    ``image_index`` (N,) in [0, num_images) (None: all 0); ``scores`` (N,) (None: all 1). Returns
    ``(boxes, obj_ids, image_index, scores)`` (the last three as lists); ``error`` names a length
    mismatch, an index out of range or an object not in ``known_ids``."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    N = boxes.shape[0]
    obj_ids = [int(o) for o in np.asarray(obj_ids).reshape(-1)]
    img_idx = [0] * N if image_index is None else [int(b) for b in np.asarray(image_index).reshape(-1)]
    scores = [1.0] * N if scores is None else [float(v) for v in np.asarray(scores).reshape(-1)]
    if not (len(obj_ids) == len(img_idx) == len(scores) == N):
        raise error(f"{where}: {N} boxes but {len(obj_ids)} obj_ids, {len(img_idx)} image indices "
                    f"and {len(scores)} scores")
    if any(not 0 <= b < num_images for b in img_idx):
        raise error(f"{where}: image_index out of range [0, {num_images})")
    unknown = sorted(set(obj_ids) - {int(o) for o in known_ids})
    if unknown:
        raise error(f"{where}: the KPD has no keypoints for object(s) {unknown}")
    return boxes, obj_ids, img_idx, scores


def check_intrinsics(K, n: int, error: type[Exception] = ValueError) -> np.ndarray:
    """``K`` (3, 3) or (n, 3, 3), finite -> contiguous float64 (n, 3, 3); else ``error`` saying why."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape == (3, 3):
        K = np.broadcast_to(K, (n, 3, 3))
    if K.shape != (n, 3, 3) or not np.isfinite(K).all():
        raise error(f"K must be (3, 3) or ({n}, 3, 3) finite intrinsics, got shape {K.shape}")
    return np.ascontiguousarray(K)
