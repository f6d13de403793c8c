"""Draw a BOP frame's ground truth over its image (projected 3D box, axes, keypoints) to check a
dataset by eye: ``python -m kpd6d.synth.preview ROOT [--split train] [--index 0] --out preview.png``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from kpd6d.visualize import draw_pose

__all__ = ["draw_frame"]

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
    from kpd6d.data import BopDataset
    from kpd6d.io import atomic_write_image

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
