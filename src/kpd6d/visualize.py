"""Drawing poses over images: projected 3D boxes, axes and keypoints (the one place for it).

Images are RGB uint8 (H, W, 3); poses follow BOP (model -> OpenCV camera, mm). Lines are drawn
with sub-pixel precision (OpenCV ``shift``), so overlays sit where :func:`kpd6d.geometry.project_points`
says the points are.
"""

from __future__ import annotations

import numpy as np

from kpd6d.geometry import project_points

__all__ = ["BOX_EDGES", "GT_COLOR", "PRED_COLOR", "draw_box_3d", "draw_overlay", "draw_pose", "draw_predictions"]

GT_COLOR = (0, 200, 0)  # RGB green (the paper's ground truth)
PRED_COLOR = (30, 90, 255)  # RGB blue (the paper's prediction)

#: the 12 edges of a box whose 8 corners are ordered x fastest (ObjectModel.bbox_corners)
BOX_EDGES = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]

_SHIFT = 4  # fractional bits of OpenCV's sub-pixel drawing


def _pt(p) -> tuple[int, int]:
    return round(float(p[0]) * (1 << _SHIFT)), round(float(p[1]) * (1 << _SHIFT))


def _valid_pose(R, t) -> bool:
    return bool(np.isfinite(np.asarray(R, float)).all() and np.isfinite(np.asarray(t, float)).all())


def draw_box_3d(image: np.ndarray, corners_3d: np.ndarray, K, R, t, color, thickness: int = 2) -> np.ndarray:
    """Draw the projected 3D box (8 corners, x fastest) at pose (R, t) in place; a non-finite pose or
    a corner behind the camera draws nothing. Returns the image."""
    import cv2

    if not _valid_pose(R, t):
        return image
    uv, z = project_points(np.asarray(corners_3d, float), np.asarray(K, float), np.asarray(R, float),
                           np.asarray(t, float), return_depth=True)
    if (z <= 0).any():
        return image
    for a, b in BOX_EDGES:
        cv2.line(image, _pt(uv[a]), _pt(uv[b]), color, thickness, cv2.LINE_AA, shift=_SHIFT)
    return image


def draw_pose(image: np.ndarray, K, R, t, model, keypoints: np.ndarray | None = None,
              color=GT_COLOR, thickness: int = 1) -> np.ndarray:
    """The model's projected 3D box, its axes (x red, y green, z blue, half the box size long) and
    ``keypoints`` (k, 3) (model frame) drawn in place."""
    import cv2

    draw_box_3d(image, model.bbox_corners, K, R, t, color, thickness)
    if not _valid_pose(R, t):
        return image
    c = model.bbox_min + model.bbox_size / 2
    L = float(model.bbox_size.max()) * 0.5
    axes = project_points(np.vstack([c, c + L * np.eye(3)]), K, R, t)
    for k, col in enumerate([(255, 0, 0), (0, 255, 0), (0, 0, 255)]):
        cv2.line(image, _pt(axes[0]), _pt(axes[k + 1]), col, thickness + 1, cv2.LINE_AA, shift=_SHIFT)
    if keypoints is not None and len(keypoints):
        for p in project_points(np.asarray(keypoints, dtype=np.float64), K, R, t):
            cv2.circle(image, _pt(p), 3 << _SHIFT, (255, 255, 0), -1, cv2.LINE_AA, shift=_SHIFT)
            cv2.circle(image, _pt(p), 3 << _SHIFT, (0, 0, 0), 1, cv2.LINE_AA, shift=_SHIFT)
    return image


def draw_overlay(image: np.ndarray, K, corners: dict[int, np.ndarray], gt: list[tuple[int, np.ndarray, np.ndarray]],
                 pred: list[tuple[int, np.ndarray, np.ndarray]]) -> np.ndarray:
    """A copy of ``image`` with GT boxes (green) and predicted boxes (blue); ``gt``/``pred`` are (obj_id, R, t)."""
    out = np.ascontiguousarray(image.copy())
    for oid, R, t in gt:
        if oid in corners:
            draw_box_3d(out, corners[oid], K, R, t, GT_COLOR, thickness=3)
    for oid, R, t in pred:
        if oid in corners:
            draw_box_3d(out, corners[oid], K, R, t, PRED_COLOR, thickness=1)
    return out


def draw_predictions(image: np.ndarray, K, preds: list[dict], corners: dict[int, np.ndarray]) -> np.ndarray:
    """A copy of ``image`` with the pipeline's predictions (``PosePipeline.predict_batch`` dicts): the
    boxes of the poses that were solved (blue), the keypoints PnP used as dots and ``obj_id:score`` labels."""
    import cv2

    out = draw_overlay(image, K, corners, [], [(p["obj_id"], p["R"], p["t"]) for p in preds if p["ok"]])
    for p in preds:
        for (u, v), used in zip(np.asarray(p["keypoints_2d"]), np.asarray(p.get("used", []), bool)):
            if used and np.isfinite(u) and np.isfinite(v):
                cv2.circle(out, (round(float(u)), round(float(v))), 2, (255, 200, 0), -1, cv2.LINE_AA)
        if p["ok"]:
            x, y = np.asarray(p["box"])[:2]
            cv2.putText(out, f"{p['obj_id']}:{p['score']:.2f}", (int(x), max(10, int(y) - 3)), cv2.FONT_HERSHEY_SIMPLEX,
                        0.4, PRED_COLOR, 1, cv2.LINE_AA)
    return out
