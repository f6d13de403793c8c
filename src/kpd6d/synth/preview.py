"""Draw a BOP frame's ground truth over its image (projected 3D box, axes, keypoints) to check a
dataset by eye: ``python -m kpd6d.synth.preview ROOT [--split train] [--index 0] --out preview.png``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from kpd6d.geometry import project_points

__all__ = ["draw_frame", "draw_pose"]

# the 12 edges of a box whose 8 corners are ordered x fastest (ObjectModel.bbox_corners)
_BOX_EDGES = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]


def _pt(p) -> tuple[int, int]:
    return round(float(p[0]) * 16), round(float(p[1]) * 16)  # 4 fractional bits (cv2 shift=4)


def draw_pose(img: np.ndarray, K, R, t, model, keypoints: np.ndarray | None = None,
              color=(0, 255, 0), thickness: int = 1) -> np.ndarray:
    """Draw the model's projected 3D bounding box, its axes (x red, y green, z blue, half the
    box size long) and ``keypoints`` (k, 3) (model frame) onto RGB ``img`` in place."""
    import cv2

    corners = project_points(np.asarray(model.bbox_corners, dtype=np.float64), K, R, t)
    for a, b in _BOX_EDGES:
        cv2.line(img, _pt(corners[a]), _pt(corners[b]), color, thickness, cv2.LINE_AA, shift=4)
    c = model.bbox_min + model.bbox_size / 2
    L = float(model.bbox_size.max()) * 0.5
    axes = project_points(np.vstack([c, c + L * np.eye(3)]), K, R, t)
    for k, col in enumerate([(255, 0, 0), (0, 255, 0), (0, 0, 255)]):
        cv2.line(img, _pt(axes[0]), _pt(axes[k + 1]), col, thickness + 1, cv2.LINE_AA, shift=4)
    if keypoints is not None and len(keypoints):
        uv = project_points(np.asarray(keypoints, dtype=np.float64), K, R, t)
        for p in uv:
            cv2.circle(img, _pt(p), 3 * 16, (255, 255, 0), -1, cv2.LINE_AA, shift=4)
            cv2.circle(img, _pt(p), 3 * 16, (0, 0, 0), 1, cv2.LINE_AA, shift=4)
    return img


def draw_frame(frame, models_by_id: dict, keypoints: dict | None = None, draw_boxes: bool = True) -> np.ndarray:
    """The frame's image with every instance's pose drawn (and its 2D ``bbox_obj`` in white)."""
    import cv2

    img = frame.load_rgb().copy()
    for inst in frame.instances:
        model = models_by_id[inst.obj_id]
        if draw_boxes and inst.bbox_obj is not None:
            x, y, w, h = (int(v) for v in inst.bbox_obj)
            cv2.rectangle(img, (x, y), (x + w, y + h), (255, 255, 255), 1)
        kps = None if keypoints is None else keypoints.get(inst.obj_id)
        draw_pose(img, frame.K, inst.R, inst.t, model, kps)
    return img


def main(argv: list[str] | None = None) -> int:
    from kpd6d.data import BopDataset, atomic_write_image

    ap = argparse.ArgumentParser(prog="python -m kpd6d.synth.preview", description=__doc__)
    ap.add_argument("root")
    ap.add_argument("--split", default="train")
    ap.add_argument("--index", type=int, default=0)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    ds = BopDataset(args.root, args.split)
    frame = ds[args.index]
    models = {m.obj_id: m for m in ds.load_models(sorted({i.obj_id for i in frame.instances}))}
    kps = ds.load_keypoints() if ds.keypoints_path.is_file() else None
    atomic_write_image(Path(args.out), draw_frame(frame, models, kps), png_compression=9)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
