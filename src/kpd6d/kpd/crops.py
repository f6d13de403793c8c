"""KPD training / validation crops over a BOP dataset (generated or real).

For every annotated instance: a square crop around its box (GT ``bbox_visib`` / ``bbox_obj`` or a
detector's box), enlarged by the codec's ``crop_scale``, resized to its ``input_size`` with
``cv2.warpAffine`` and :meth:`kpd6d.kpd.codec.HeatmapCodec.crop_affine`; the designated keypoints
projected with the (symmetry-canonicalised) GT pose and mapped into the crop; the codec's target
heatmaps for all keypoints (visible or not) and per-keypoint visibility flags.

Negative crops (``negative_fraction`` p > 0, for training): an item is, with probability p, a crop of
the same size elsewhere in its image — centred on another annotated instance (another object) or
anywhere — that does not touch any visible box of the instance's object; its target heatmaps are all
zero (``negative`` 1, every keypoint invisible). The network then learns that a crop without its object
has no keypoints, so its heatmap maxima (the keypoint confidences) tell a detector's false boxes on
clutter from true ones when candidates are verified (:mod:`kpd6d.pnp.estimator`).

:func:`inference_crops` makes the same crops of a batch of image tensors on their device (kornia's
``warp_affine``), as the KPD's inference does.

Full-box crops (``full_box_p`` p > 0, for training): an item is, with probability p, cropped on the
instance's full box — the GT ``bbox_obj`` (the box of the whole projected object, occluded parts
included) clipped to the image — instead of ``box_source``'s box, before box augmentation. That is the
box the re-crop of ``refine_boxes`` cuts at inference (:mod:`kpd6d.pnp.estimator`: the object projected
with the estimated pose, clipped to the image); on an occluded object it holds the hidden part's
keypoints, which a crop of the visible box often leaves outside, where no heatmap can put them.

Visibility (``visibility=``): ``crop`` — inside the crop; ``mask`` — also on the instance's visible
mask (catches occlusion by other objects, not self-occlusion); ``depth`` — also not behind the scene
depth at its pixel (catches self- and inter-object occlusion); ``auto`` — ``depth`` when the frame
has a depth image, else ``mask`` when it has masks, else ``crop``.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from kpd6d.geometry import affine_apply, box_iou_xywh, clip_xywh_to_image, project_points
from kpd6d.kpd.codec import build_codec

__all__ = ["BOX_SOURCES", "VISIBILITY_MODES", "KPDCropDataset", "canonicalizer_for", "inference_crops",
           "load_detection_boxes"]

BOX_SOURCES = ("visib", "obj", "detections")
VISIBILITY_MODES = ("auto", "depth", "mask", "crop")


def canonicalizer_for(model, boundary: str = "model_x") -> Callable[[np.ndarray, np.ndarray],
                                                                    tuple[np.ndarray, np.ndarray]]:
    """``(R, t) -> (R, t)`` canonicalising the pose of a symmetric model (identity otherwise); ``boundary``:
    where a rotational symmetry's canonical range starts (:func:`kpd6d.symmetry.handler_for_model`)."""
    if not model.is_symmetric:
        return lambda R, t: (R, t)
    try:
        from kpd6d.symmetry import handler_for_model
    except ImportError as exc:  # pragma: no cover - kpd6d.symmetry is part of the library
        raise ImportError(f"object {model.obj_id} is symmetric but kpd6d.symmetry is unavailable: {exc}") from exc
    return handler_for_model(model, boundary=boundary).canonicalize


def load_detection_boxes(path: str | os.PathLike) -> dict[tuple[int, int], list[tuple[int, np.ndarray, float]]]:
    """BOP detection JSON (list of ``{scene_id, image_id, category_id, bbox (xywh), score}``) →
    ``{(scene_id, im_id): [(obj_id, box, score), ...]}``."""
    from kpd6d.io import read_json

    p = Path(path)
    entries = read_json(p, what="detections file", error=ValueError)
    if not isinstance(entries, list):
        raise ValueError(f"detections file {str(p)!r} must hold a JSON list of detections")
    out: dict[tuple[int, int], list] = {}
    for i, e in enumerate(entries):
        try:
            key = (int(e["scene_id"]), int(e["image_id"]))
            box = np.asarray(e["bbox"], dtype=np.float64).reshape(4)
            out.setdefault(key, []).append((int(e["category_id"]), box, float(e.get("score", 1.0))))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"detections file {str(p)!r}: entry {i} is malformed ({exc!r}); needs "
                             "scene_id, image_id, category_id, bbox [x, y, w, h]") from exc
    return out


class KPDCropDataset(Dataset):
    """Instance crops with keypoints, heatmaps and visibility (see the module docstring).

    Items are dicts of tensors: ``image`` (3, S, S) float [0, 1]; ``keypoints`` (k, 2) crop px;
    ``keypoints_image`` (k, 2) image px; ``visibility`` (k,) float {0, 1}; ``heatmaps`` (k, S/s, S/s)
    (when ``return_heatmaps``); ``affine`` (2, 3) image → crop; ``box`` (4,) the box cropped
    (after box augmentation); ``K`` (3, 3); ``R``, ``t`` (canonicalised GT pose); ``obj_id``;
    ``obj_index`` (index into ``obj_ids``); ``negative`` (float, 1 for a negative crop: ``heatmaps``
    zero, ``visibility`` zero, ``keypoints`` where the projections fall, outside the crop).

    ``codec`` (a :class:`~kpd6d.kpd.codec.HeatmapCodec` or its config) sets the crop size, crop scale
    and targets; the separate ``input_size`` / ``out_stride`` / ``sigma`` / ``crop_scale`` (older
    spelling; None = the codec default) map onto one.
    """

    def __init__(self, root: str | os.PathLike | Any, split: str = "train", obj_ids: Sequence[int] | None = None,
                 keypoints: Mapping[int, np.ndarray] | None = None, input_size: int | None = None,
                 out_stride: int | None = None, sigma: float | None = None, crop_scale: float | None = None,
                 box_source: str = "visib",
                 detections: str | os.PathLike | None = None, detection_iou: float = 0.5,
                 box_augment: Callable | None = None, min_visib_fract: float = 0.1,
                 visibility: str = "auto", return_heatmaps: bool = True, max_instances: int | None = None,
                 models: Sequence | None = None, image_cache_mb: float = 0.0, codec: Any = None,
                 negative_fraction: float = 0.0, symmetry_boundary: str = "model_x", full_box_p: float = 0.0) -> None:
        from kpd6d.data import BopDataset

        if box_source not in BOX_SOURCES:
            raise ValueError(f"box_source {box_source!r} unknown; known: {', '.join(BOX_SOURCES)}")
        if visibility not in VISIBILITY_MODES:
            raise ValueError(f"visibility {visibility!r} unknown; known: {', '.join(VISIBILITY_MODES)}")
        self.codec = build_codec(codec, what="KPDCropDataset", input_size=input_size, out_stride=out_stride,
                                 sigma=sigma, crop_scale=crop_scale)
        if box_source == "detections" and detections is None:
            raise ValueError("box_source='detections' needs a detections file (BOP detection JSON)")
        self.ds = root if isinstance(root, BopDataset) else BopDataset(root, split=split, obj_ids=obj_ids)
        kps = dict(keypoints) if keypoints is not None else self.ds.load_keypoints()
        present = self.ds.instance_obj_ids()
        self.obj_ids = sorted(int(o) for o in (obj_ids if obj_ids is not None else present))
        missing = [o for o in self.obj_ids if o not in kps]
        if missing:
            raise KeyError(f"no keypoints for object(s) {missing} (keypoints given for {sorted(kps)})")
        self.keypoints_3d = {o: np.asarray(kps[o], dtype=np.float64) for o in self.obj_ids}
        ks = {o: len(v) for o, v in self.keypoints_3d.items()}
        if len(set(ks.values())) != 1:
            raise ValueError(f"every object needs the same number of keypoints, got {ks}")
        self.num_keypoints = next(iter(ks.values()))
        models = list(models) if models is not None else self.ds.load_models(self.obj_ids)
        self.models = {m.obj_id: m for m in models if m.obj_id in self.obj_ids}
        from kpd6d.symmetry.handlers import check_boundary

        check_boundary(symmetry_boundary)  # also for datasets without a symmetric object
        self._canon = {o: canonicalizer_for(m, symmetry_boundary) for o, m in self.models.items()}
        self.box_source = box_source
        self.box_augment = box_augment
        negative_fraction = float(negative_fraction)
        if not 0.0 <= negative_fraction < 1.0:
            raise ValueError(f"negative_fraction must be in [0, 1), got {negative_fraction}")
        self.negative_fraction = negative_fraction
        full_box_p = float(full_box_p)
        if not 0.0 <= full_box_p <= 1.0:
            raise ValueError(f"full_box_p must be in [0, 1], got {full_box_p}")
        self.full_box_p = full_box_p
        self.visibility = visibility
        self.return_heatmaps = return_heatmaps
        self.detections = load_detection_boxes(detections) if box_source == "detections" else None
        self.detection_iou = float(detection_iou)
        # decoded images kept in memory (per process) up to image_cache_mb: an epoch after the first
        # then costs no JPEG decoding, which on a small CPU is a sizeable share of a training step
        self.image_cache_mb = float(image_cache_mb)
        self._cache: dict[int, np.ndarray] = {}
        self._cache_bytes = 0
        self.items: list[tuple[int, int]] = []
        for fi, fr in enumerate(self.ds.frames):
            for ii, inst in enumerate(fr.instances):
                if inst.obj_id not in self.keypoints_3d:
                    continue
                if min_visib_fract and inst.visib_fract is not None and inst.visib_fract < min_visib_fract:
                    continue
                self.items.append((fi, ii))
        if max_instances is not None and len(self.items) > int(max_instances):
            keep = np.linspace(0, len(self.items) - 1, int(max_instances)).round().astype(int)  # evenly spread
            self.items = [self.items[i] for i in keep]
        if not self.items:
            raise ValueError(f"{self.ds!r}: no instances of objects {self.obj_ids} with visib_fract >= {min_visib_fract}")

    def __len__(self) -> int:
        return len(self.items)

    # the codec's fields, as the dataset exposed them before the codec
    @property
    def input_size(self) -> int:
        return self.codec.input_size

    @property
    def out_stride(self) -> int:
        return self.codec.out_stride

    @property
    def sigma(self) -> float:
        return self.codec.sigma

    @property
    def crop_scale(self) -> float:
        return self.codec.crop_scale

    # -- pieces -----------------------------------------------------------------------------------
    def _rgb(self, fi: int) -> np.ndarray:
        img = self._cache.get(fi)
        if img is None:
            img = self.ds.frames[fi].load_rgb()
            if self._cache_bytes + img.nbytes <= self.image_cache_mb * 2**20:
                self._cache[fi] = img
                self._cache_bytes += img.nbytes
        return img

    def _box(self, frame, inst, full_hw: tuple[int, int] | None = None) -> np.ndarray:
        """The instance's crop box: ``box_source``'s; with ``full_hw`` (the image's (H, W)) its full box clipped to
        the image (its visible box when almost none of the full box is inside)."""
        if full_hw is not None:
            gt = inst.bbox_obj if inst.bbox_obj is not None else self._projected_box(frame, inst)
            clipped = clip_xywh_to_image(gt, full_hw[1], full_hw[0])
            if clipped is not None:
                return clipped
        gt = inst.bbox_visib if self.box_source in ("visib", "detections") else inst.bbox_obj
        if gt is None:  # no scene_gt_info: the box of the projected model
            gt = self._projected_box(frame, inst)
        gt = np.asarray(gt, dtype=np.float64)
        if self.box_source == "detections" and full_hw is None:
            cands = [d for d in self.detections.get((frame.scene_id, frame.im_id), []) if d[0] == inst.obj_id]
            if cands:
                ious = box_iou_xywh(gt, np.stack([c[1] for c in cands]))
                j = int(np.argmax(ious))
                if ious[j] >= self.detection_iou:
                    return cands[j][1].copy()
        return gt

    def _projected_box(self, frame, inst) -> np.ndarray:
        """The box of the instance's model points projected with its GT pose (xywh, unclipped)."""
        from kpd6d.geometry import bbox_from_points

        m = self.models[inst.obj_id]
        return bbox_from_points(project_points(m.sample_points(500, seed=0), frame.K, inst.R, inst.t))

    def _visibility(self, frame, inst, uv_img, z, in_crop) -> np.ndarray:
        vis = in_crop.copy()
        mode = self.visibility
        if mode == "auto":
            mode = "depth" if frame.scene_dir is not None and frame.depth_path().is_file() else (
                "mask" if frame.scene_dir is not None and frame.mask_visib_path(inst.gt_index).is_file() else "crop")
        if mode == "crop":
            return vis
        if mode == "depth":
            img = frame.load_depth()
        else:
            img = frame.load_mask_visib(inst.gt_index)
        H, W = img.shape[:2]
        px = np.round(uv_img).astype(np.int64)
        inside = (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)
        vals = np.zeros(len(px), dtype=np.float64)
        vals[inside] = img[px[inside, 1], px[inside, 0]]
        if mode == "mask":
            return vis & inside & (vals > 0)
        tol = max(5.0, 0.03 * self.models[inst.obj_id].diameter)
        # depth 0 = unknown: do not call the keypoint occluded
        return vis & inside & ((vals <= 0) | (z <= vals + tol))

    # -- item -------------------------------------------------------------------------------------
    def _negative_box(self, frame, inst, box: np.ndarray, size: tuple[int, int],
                      rng: np.random.Generator) -> np.ndarray | None:
        """A box of ``box``'s size whose crop touches no visible box of ``inst``'s object in ``frame``:
        centred on another object's instance (half of the tries, when there is one) or anywhere in the
        image (``size``: its (H, W)); None when 20 tries find none."""
        H, W = size
        own = np.array([self._box(frame, o) for o in frame.instances if o.obj_id == inst.obj_id], dtype=np.float64)
        others = [o for o in frame.instances if o.obj_id != inst.obj_id]
        side = self.crop_scale * max(box[2], box[3])  # the crop's side (image px)
        for _ in range(20):
            if others and rng.random() < 0.5:
                ob = np.asarray(self._box(frame, others[int(rng.integers(len(others)))]), dtype=np.float64)
                cx, cy = ob[0] + ob[2] / 2, ob[1] + ob[3] / 2
            else:
                cx, cy = rng.uniform(0, W), rng.uniform(0, H)
            if box_iou_xywh(np.array([cx - side / 2, cy - side / 2, side, side]), own).max() <= 0:  # no overlap
                return np.array([cx - box[2] / 2, cy - box[3] / 2, box[2], box[3]], dtype=np.float64)
        return None

    def __getitem__(self, idx: int) -> dict[str, Any]:
        fi, ii = self.items[idx]
        frame = self.ds.frames[fi]
        inst = frame.instances[ii]
        rng = None
        if self.box_augment is not None or self.negative_fraction > 0 or self.full_box_p > 0:
            rng = np.random.default_rng(int(torch.randint(0, 2**31 - 1, ()).item()))
        rgb = self._rgb(fi)
        full = self.full_box_p > 0 and rng.random() < self.full_box_p
        box = self._box(frame, inst, full_hw=rgb.shape[:2] if full else None)
        if self.box_augment is not None:
            box = self.box_augment(box, rng, obj_id=inst.obj_id)
        negative = False
        if self.negative_fraction > 0 and rng.random() < self.negative_fraction:
            neg_box = self._negative_box(frame, inst, np.asarray(box, dtype=np.float64), rgb.shape[:2], rng)
            if neg_box is not None:
                box, negative = neg_box, True
        S = self.input_size
        A = self.codec.crop_affine(box)
        crop = cv2.warpAffine(rgb, A, (S, S), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        R, t = self._canon[inst.obj_id](np.asarray(inst.R, dtype=np.float64), np.asarray(inst.t, dtype=np.float64))
        K = np.asarray(frame.K, dtype=np.float64)
        uv_img, z = project_points(self.keypoints_3d[inst.obj_id], K, R, t, return_depth=True)
        uv = affine_apply(A, uv_img)
        in_crop = (uv[:, 0] >= -0.5) & (uv[:, 0] < S - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < S - 0.5) & (z > 0)
        vis = np.zeros_like(in_crop) if negative else self._visibility(frame, inst, uv_img, z, in_crop)
        item = {
            "image": torch.from_numpy(np.ascontiguousarray(crop.transpose(2, 0, 1))).float().div_(255.0),
            "keypoints": torch.from_numpy(uv).float(),
            "keypoints_image": torch.from_numpy(uv_img).float(),
            "visibility": torch.from_numpy(vis.astype(np.float32)),
            "affine": torch.from_numpy(A),
            "box": torch.from_numpy(np.asarray(box, dtype=np.float64)),
            "K": torch.from_numpy(K),
            "R": torch.from_numpy(R),
            "t": torch.from_numpy(t),
            "obj_id": int(inst.obj_id),
            "obj_index": self.obj_ids.index(int(inst.obj_id)),
            "negative": float(negative),
        }
        if self.return_heatmaps:
            item["heatmaps"] = self.codec.encode(item["keypoints"])[0]
            if negative:
                item["heatmaps"].zero_()
        return item


def inference_crops(images: torch.Tensor, boxes, image_index, codec) -> tuple[torch.Tensor, torch.Tensor]:
    """The codec's crops of boxes over a batch of images, on the images' device.

    ``images`` (B, 3, H, W) float; ``boxes`` (N, 4) xywh px; ``image_index`` (N,) which image each box
    is in. Returns ``crops`` (N, 3, S, S) (float32, kornia ``warp_affine``: the same affine and
    sampling as the cv2 training crops) and the image → crop affines ``A`` (N, 2, 3) float64; map
    crop keypoints back with ``affine_apply(invert_affine(A), uv)``.
    """
    from kornia.geometry.transform import warp_affine

    dev = images.device
    boxes = torch.as_tensor(boxes, dtype=torch.float64, device=dev).reshape(-1, 4)
    image_index = torch.as_tensor(image_index, dtype=torch.long, device=dev).reshape(-1)
    S = codec.input_size
    A = codec.crop_affine(boxes)
    crops = warp_affine(images[image_index].float(), A.float(), (S, S), align_corners=True)
    return crops, A
