import numpy as np

from kpd6d.geometry import LINEMOD_K, pose_from_view, project_points
from kpd6d.objects import procedural_objects
from kpd6d.visualize import GT_COLOR, draw_box_3d, draw_overlay, draw_pose


def test_box_is_drawn_through_the_projected_corners():
    model = procedural_objects(obj_ids=[1])[0]
    R, t = pose_from_view(0.4, 0.5, 600.0)
    img = np.zeros((480, 640, 3), np.uint8)
    draw_box_3d(img, model.bbox_corners, LINEMOD_K, R, t, GT_COLOR, thickness=1)
    uv = project_points(model.bbox_corners, LINEMOD_K, R, t)
    drawn = img.any(axis=-1)
    for u, v in uv:  # every corner (independently projected) lies on a drawn pixel (±1 px)
        x, y = int(np.rint(u)), int(np.rint(v))
        assert drawn[y - 1:y + 2, x - 1:x + 2].any()
    # and nothing is drawn far outside the corners' bounding box
    ys, xs = np.nonzero(drawn)
    assert xs.min() >= uv[:, 0].min() - 2 and xs.max() <= uv[:, 0].max() + 2
    assert ys.min() >= uv[:, 1].min() - 2 and ys.max() <= uv[:, 1].max() + 2


def test_invalid_or_behind_camera_poses_draw_nothing():
    model = procedural_objects(obj_ids=[1])[0]
    img = np.zeros((120, 160, 3), np.uint8)
    draw_box_3d(img, model.bbox_corners, LINEMOD_K, np.full((3, 3), np.nan), np.zeros(3), GT_COLOR)
    draw_pose(img, LINEMOD_K, np.eye(3), np.array([0.0, 0.0, -500.0]), model)
    assert not img.any()


def test_overlay_keeps_the_input_and_colours_gt_and_prediction():
    model = procedural_objects(obj_ids=[1])[0]
    R, t = pose_from_view(0.4, 0.5, 600.0)
    img = np.zeros((480, 640, 3), np.uint8)
    out = draw_overlay(img, LINEMOD_K, {1: model.bbox_corners}, [(1, R, t)], [(1, R, t + np.array([40.0, 0.0, 0.0]))])
    assert not img.any() and out.any()
    colours = {tuple(c) for c in out.reshape(-1, 3)[out.reshape(-1, 3).any(axis=1)]}
    assert (0, 200, 0) in colours and (30, 90, 255) in colours
