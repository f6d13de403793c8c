"""The end-to-end pose pipeline: detector -> (crop -> KPD heatmaps -> decode) -> top-l -> PnP.

``PosePipeline(detector, kpd, pnp, top_l)(image (H, W, 3) uint8 RGB, K (3, 3))`` returns one dict
per detected object: ``obj_id``, ``R`` (3, 3), ``t`` (3,) mm, ``score`` (the detection score),
``keypoints_2d`` (k, 2) image px, ``confidences`` (k,), plus ``box`` (4,) xywh, ``used`` (k,) bool
(the top-l keypoints given to PnP), ``confidence`` in [0, 1] and ``residual_px`` (below) and ``ok`` /
``reason`` (``R``/``t`` are NaN when not ok: a failure, never dropped); a detection box with w or h below :data:`MIN_BOX_PX` or outside the
image is not ok, with reason "degenerate box ...". :meth:`PosePipeline.predict_batch` does the same for a batch of
images (one detector call, one KPD call over every object of every image, one batched PnP).
``refine_boxes=n`` (default 0, the paper) repeats crop -> KPD -> PnP n more times, each time on the
box of the object projected with the pose just estimated: the crop no longer depends on the
detector's box size and centre, only on its finding the object.

Pose confidence (:mod:`kpd6d.pnp.confidence`): with ``c_i`` the KPD's keypoint confidences (heatmap
maxima), ``U`` the top-l keypoints given to PnP, ``I`` the PnP inliers among them and ``residual_px``
their mean reprojection error, ``confidence = sum_{i in I} clip(c_i, 0, 1) / |U| * exp(-residual_px /
residual_scale_px)`` (``residual_scale_px`` default 10 px); 0 when PnP failed. ``ok`` = PnP ok (its
validity gates) and ``confidence >= min_confidence`` (default 0: PnP's verdict alone).

:meth:`PosePipeline.detect` (the detector alone) and :meth:`PosePipeline.predict_boxes` (KPD + PnP
on given boxes) are the two halves of ``predict_batch``; tracking (:mod:`kpd6d.tracking`) calls them
separately.

The KPD contract (``kpd6d.kpd``) does the crop, heatmap network and decoding inside
``predict_keypoints(images, boxes, image_index, obj_ids)``; the pipeline keeps the stage times of
its last call in :attr:`PosePipeline.last_timings` (seconds: ``detect``, ``kpd``, ``pnp``,
``total``).
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from kpd6d.geometry import MIN_BOX_PX, box_problem, check_box_inputs, check_intrinsics
from kpd6d.io import stack_rgb_images
from kpd6d.pnp.confidence import RESIDUAL_SCALE_PX
from kpd6d.pnp.top_l import pose_records, solve_top_l, top_l_mask

__all__ = ["MIN_BOX_PX", "PipelineInputError", "PosePipeline", "box_problem", "default_device", "images_to_tensor"]


class PipelineInputError(ValueError):
    """An image, intrinsics or component the pipeline cannot use; the message says which and why."""


def default_device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def images_to_tensor(images: Sequence[np.ndarray] | np.ndarray, device: Any = "cpu") -> torch.Tensor:
    """uint8 RGB images (H, W, 3) (a list or a (B, H, W, 3) array, equal sizes) -> float (B, 3, H, W) in [0, 1]."""
    x = torch.from_numpy(stack_rgb_images(images, PipelineInputError)).to(device)
    return x.permute(0, 3, 1, 2).float().div_(255.0)


def _check_K(K, n: int) -> np.ndarray:
    return check_intrinsics(K, n, PipelineInputError)


class PosePipeline:
    """Detector + KPD + PnP. ``pnp`` is a solver object or a ``PNP_SOLVERS`` name; ``top_l`` the number
    of most confident keypoints passed to PnP (None: all)."""

    def __init__(self, detector, kpd, pnp: Any = "epnp_ransac", top_l: int | None = 20,
                 device: str | torch.device | None = None, refine_boxes: int = 0, min_confidence: float = 0.0,
                 residual_scale_px: float = RESIDUAL_SCALE_PX) -> None:
        if not hasattr(detector, "predict"):
            raise PipelineInputError(f"detector must have .predict(images, targets=None), got {type(detector).__name__}")
        if not hasattr(kpd, "predict_keypoints") or not hasattr(kpd, "keypoints_3d"):
            raise PipelineInputError(f"kpd must have .predict_keypoints(...) and .keypoints_3d, got {type(kpd).__name__}")
        if isinstance(pnp, str) or isinstance(pnp, dict):
            from kpd6d.registry import PNP_SOLVERS, build_from_cfg

            pnp = PNP_SOLVERS.build(pnp) if isinstance(pnp, str) else build_from_cfg(PNP_SOLVERS, pnp)
        if top_l is not None and int(top_l) < 4:
            raise PipelineInputError(f"top_l must be >= 4 (PnP needs at least 4 points) or None, got {top_l}")
        self.detector, self.kpd, self.pnp = detector, kpd, pnp
        self.top_l = None if top_l is None else int(top_l)
        if int(refine_boxes) < 0:
            raise PipelineInputError(f"refine_boxes must be >= 0, got {refine_boxes}")
        self.refine_boxes = int(refine_boxes)
        if not 0.0 <= float(min_confidence) <= 1.0:
            raise PipelineInputError(f"min_confidence must be in [0, 1], got {min_confidence}")
        if not float(residual_scale_px) > 0:
            raise PipelineInputError(f"residual_scale_px must be > 0, got {residual_scale_px}")
        self.min_confidence, self.residual_scale_px = float(min_confidence), float(residual_scale_px)
        self.device = torch.device(device) if device is not None else default_device()
        for m in (detector, kpd):
            if isinstance(m, torch.nn.Module):
                m.to(self.device).eval()
        self.last_timings: dict[str, float] = {}

    # -- construction ---------------------------------------------------------------------------
    @classmethod
    def from_checkpoints(cls, detector: str | os.PathLike, kpd: str | os.PathLike, *, pnp: Any = "epnp_ransac",
                         top_l: int | None = 20, device: str | torch.device | None = None,
                         obj_ids: Sequence[int] | None = None, refine_boxes: int = 0, min_confidence: float = 0.0,
                         residual_scale_px: float = RESIDUAL_SCALE_PX, **detector_overrides: Any) -> PosePipeline:
        """Load a detector checkpoint (or ``"oracle"``) and a KPD checkpoint."""
        from kpd6d.kpd.module import KPDModule

        device = torch.device(device) if device is not None else default_device()
        kpd_module = KPDModule.load_checkpoint(kpd)
        if str(detector) == "oracle":
            from kpd6d.registry import DETECTORS

            det = DETECTORS.build("oracle", obj_ids=list(obj_ids) if obj_ids else None, **detector_overrides)
        else:
            from kpd6d.detection import load_detector

            det = load_detector(detector, obj_ids=obj_ids, map_location=device, **detector_overrides)
        return cls(det, kpd_module, pnp=pnp, top_l=top_l, device=device, refine_boxes=refine_boxes,
                   min_confidence=min_confidence, residual_scale_px=residual_scale_px)

    @classmethod
    def from_export(cls, export_dir: str | os.PathLike, backend: str = "onnxruntime", *, pnp: Any = "epnp_ransac",
                    top_l: int | None = 20, detector: str = "export", obj_ids: Sequence[int] | None = None,
                    refine_boxes: int = 0, device: str | torch.device | None = None, threads: int | None = None,
                    min_confidence: float = 0.0, residual_scale_px: float = RESIDUAL_SCALE_PX,
                    **detector_overrides: Any):
        """A pipeline from a ``kpd6d-export`` folder on ``backend`` (``kpd6d.deploy.BACKENDS``).

        ``onnxruntime`` / ``openvino``: a :class:`kpd6d.deploy.runtime.RuntimePipeline` (the same
        interface and pose dicts, numpy, no torch); ``torch``: this class on the checkpoints the export
        was made from. ``detector="oracle"``: GT boxes from ``targets`` instead of the exported detector.
        """
        from kpd6d.deploy import BACKENDS
        from kpd6d.deploy.runtime import RuntimePipeline, read_sidecar

        if backend not in BACKENDS:
            raise PipelineInputError(f"backend {backend!r} unknown; known: {', '.join(BACKENDS)}")
        if backend != "torch":
            return RuntimePipeline(export_dir, backend, pnp=pnp, top_l=top_l, refine_boxes=refine_boxes,
                                   detector=detector, obj_ids=obj_ids, threads=threads, min_confidence=min_confidence,
                                   residual_scale_px=residual_scale_px, **detector_overrides)
        src = read_sidecar(export_dir)["source"]
        det = "oracle" if detector == "oracle" or not src.get("detector_ckpt") else src["detector_ckpt"]
        return cls.from_checkpoints(det, src["kpd_ckpt"], pnp=pnp, top_l=top_l, device=device, obj_ids=obj_ids,
                                    refine_boxes=refine_boxes, min_confidence=min_confidence,
                                    residual_scale_px=residual_scale_px, **detector_overrides)

    @classmethod
    def for_backend(cls, backend: str = "torch", *, detector_ckpt: Any, kpd_ckpt: Any = None, export_dir: Any = None,
                    **kwargs: Any):
        """What ``kpd6d-evaluate`` / ``kpd6d-predict`` build: ``backend=torch`` → :meth:`from_checkpoints`
        (``detector_ckpt``, ``kpd_ckpt``); otherwise :meth:`from_export` on ``export_dir`` (with the
        oracle's GT boxes when ``detector_ckpt`` is ``"oracle"``)."""
        backend = str(backend or "torch")
        if backend == "torch":
            if kpd_ckpt is None:
                raise PipelineInputError("backend=torch needs kpd_ckpt=<KPD checkpoint>")
            return cls.from_checkpoints(detector_ckpt, kpd_ckpt, **kwargs)
        if not export_dir:
            raise PipelineInputError(f"backend={backend} needs export_dir=<a kpd6d-export folder>")
        kwargs.pop("device", None)
        return cls.from_export(export_dir, backend, detector="oracle" if str(detector_ckpt) == "oracle" else "export",
                               **kwargs)

    # -- inference ------------------------------------------------------------------------------
    def __call__(self, image: np.ndarray, K, targets: dict | None = None) -> list[dict]:
        """Poses of the objects in one uint8 RGB image with intrinsics ``K`` (3, 3)."""
        return self.predict_batch([image], K, None if targets is None else [targets])[0]

    @torch.no_grad()
    def predict_batch(self, images: Sequence[np.ndarray] | np.ndarray | torch.Tensor, K,
                      targets: list[dict] | None = None) -> list[list[dict]]:
        """Poses for a batch of images (uint8 (H, W, 3) arrays, or a float (B, 3, H, W) tensor in [0, 1]).

        ``K`` is (3, 3) for all images or (B, 3, 3); ``targets`` goes to the detector (the oracle's GT
        boxes). Returns one list of pose dicts per image. The same as :meth:`detect` followed by
        :meth:`predict_boxes` on its boxes.
        """
        t0 = time.perf_counter()
        x = self._images(images)
        Ks = _check_K(K, x.shape[0])
        dets = self._detect(x, targets)
        t1 = time.perf_counter()
        out = self._estimate(x, Ks, [d["box"] for d in dets], [d["image_index"] for d in dets],
                             [d["obj_id"] for d in dets], [d["score"] for d in dets])
        self.last_timings["detect"] = t1 - t0
        self.last_timings["total"] = time.perf_counter() - t0
        return out

    @torch.no_grad()
    def detect(self, images: Sequence[np.ndarray] | np.ndarray | torch.Tensor,
               targets: list[dict] | None = None) -> list[list[dict]]:
        """The detector alone: per image a list of ``{"box": (4,) xywh px, "obj_id", "score"}`` (highest
        score first, only objects the KPD has keypoints for): the boxes :meth:`predict_batch` estimates."""
        t0 = time.perf_counter()
        x = self._images(images)
        out: list[list[dict]] = [[] for _ in range(x.shape[0])]
        for d in self._detect(x, targets):
            out[d["image_index"]].append({"box": d["box"], "obj_id": d["obj_id"], "score": d["score"]})
        self.last_timings = {"detect": time.perf_counter() - t0, "kpd": 0.0, "pnp": 0.0,
                             "total": time.perf_counter() - t0}
        return out

    @torch.no_grad()
    def predict_boxes(self, images: Sequence[np.ndarray] | np.ndarray | torch.Tensor, K, boxes, obj_ids,
                      image_index=None, scores=None) -> list[list[dict]]:
        """KPD + PnP (and ``refine_boxes``) on given boxes, no detector: what tracking runs on the boxes of
        the objects projected with their previous poses.

        ``boxes`` (N, 4) xywh px, ``obj_ids`` (N,), ``image_index`` (N,) which image each box is in
        (None: all in image 0), ``scores`` (N,) copied to the pose dicts' ``score`` (None: 1). Returns
        one list of pose dicts per image, in the order of the boxes. Objects the KPD has no keypoints
        for raise :class:`PipelineInputError`.
        """
        t0 = time.perf_counter()
        x = self._images(images)
        Ks = _check_K(K, x.shape[0])
        boxes, obj_ids, img_idx, scores = check_box_inputs(boxes, obj_ids, image_index, scores, x.shape[0],
                                                           self.kpd.keypoints_3d, error=PipelineInputError)
        out = self._estimate(x, Ks, boxes.tolist(), img_idx, obj_ids, scores)
        self.last_timings["detect"] = 0.0
        self.last_timings["total"] = time.perf_counter() - t0
        return out

    def object_points(self, obj_id: int) -> np.ndarray:
        """(P, 3) mm points of object ``obj_id`` whose projection bounds it in the image: the surface
        points a KPD checkpoint carries, else its keypoints (box refinement and tracking crop on their box)."""
        surface = getattr(self.kpd, "surface_points", None)
        if surface is not None:
            return np.asarray(surface(int(obj_id)), dtype=np.float64).reshape(-1, 3)
        return np.asarray(self.kpd.keypoints_3d[int(obj_id)], dtype=np.float64).reshape(-1, 3)

    def _images(self, images) -> torch.Tensor:
        return images.to(self.device) if isinstance(images, torch.Tensor) else images_to_tensor(images, self.device)

    def _detect(self, x: torch.Tensor, targets) -> list[dict]:
        """The detections of the batch ``x`` the KPD can localise, flat: box, image_index, obj_id, score."""
        B = x.shape[0]
        dets = self.detector.predict(x, targets=targets)
        if len(dets) != B:
            raise PipelineInputError(f"detector returned {len(dets)} results for {B} images")
        known = {int(o) for o in self.kpd.keypoints_3d}
        flat = []
        for b, d in enumerate(dets):
            for box, oid, s in zip(d.boxes.tolist(), d.obj_ids.tolist(), d.scores.tolist()):
                if int(oid) in known:  # the KPD cannot localise objects it has no keypoints for
                    flat.append({"box": box, "image_index": b, "obj_id": int(oid), "score": float(s)})
        return flat

    def _estimate(self, x: torch.Tensor, Ks: np.ndarray, boxes: list, img_idx: list[int], obj_ids: list[int],
                  scores: list[float]) -> list[list[dict]]:
        """crop -> KPD -> top-l -> PnP (``refine_boxes`` more times) on ``boxes``; sets ``last_timings``."""
        B = x.shape[0]
        out: list[list[dict]] = [[] for _ in range(B)]
        if not boxes:
            self.last_timings = {"detect": 0.0, "kpd": 0.0, "pnp": 0.0, "total": 0.0}
            return out
        boxes_t = torch.tensor(boxes, dtype=torch.float32, device=self.device)
        idx_t = torch.tensor(img_idx, dtype=torch.long, device=self.device)
        ids_t = torch.tensor(obj_ids, dtype=torch.long, device=self.device)
        pts3d = np.stack([np.asarray(self.kpd.keypoints_3d[o], dtype=np.float64).reshape(-1, 3) for o in obj_ids])
        Kn = Ks[np.asarray(img_idx)]
        t_kpd = t_pnp = 0.0
        for it in range(self.refine_boxes + 1):
            ta = time.perf_counter()
            kp2d, conf = self.kpd.predict_keypoints(x, boxes_t, idx_t, ids_t)
            kp2d = torch.as_tensor(kp2d).float()
            conf = torch.as_tensor(conf).float()
            used = top_l_mask(conf, self.top_l)
            if self.device.type == "cuda":
                torch.cuda.synchronize()
            tb = time.perf_counter()
            kp2d_np = kp2d.detach().cpu().numpy().astype(np.float64)
            conf_np = conf.detach().cpu().numpy().astype(np.float64)
            used_np = used.detach().cpu().numpy()
            if pts3d.shape[1] != kp2d_np.shape[1]:
                raise PipelineInputError(f"KPD returned {kp2d_np.shape[1]} keypoints but keypoints_3d has {pts3d.shape[1]}")
            est = solve_top_l(self.pnp, pts3d, kp2d_np, Kn, conf_np, self.top_l)
            t_kpd += tb - ta
            t_pnp += time.perf_counter() - tb
            if it < self.refine_boxes:
                boxes_t = self._boxes_from_poses(est, obj_ids, img_idx, Ks, boxes_t, x.shape[-2:])
        pose_records(est, boxes, x.shape[-2:], img_idx, obj_ids, scores, kp2d_np, conf_np, used_np, out,
                     points_3d=pts3d, K=Kn, min_confidence=self.min_confidence,
                     residual_scale_px=self.residual_scale_px)
        self.last_timings = {"detect": 0.0, "kpd": t_kpd, "pnp": t_pnp, "total": t_kpd + t_pnp}
        return out

    def _boxes_from_poses(self, est, obj_ids, img_idx, Ks, boxes_t, hw) -> torch.Tensor:
        """Box refinement: each solved instance's box becomes the box of its object's surface points
        (the model points a KPD checkpoint carries, else its keypoints) projected with the estimated
        pose, clipped to the image; failed or degenerate ones keep their box."""
        from kpd6d.geometry import bbox_from_points, project_points

        H, W = int(hw[0]), int(hw[1])
        new = boxes_t.detach().cpu().numpy().astype(np.float64)
        for n, (oid, b) in enumerate(zip(obj_ids, img_idx)):
            if not bool(est.ok[n]):
                continue
            pts = self.object_points(oid)
            uv, z = project_points(pts, Ks[b], np.asarray(est.R[n]), np.asarray(est.t[n]), return_depth=True)
            if not (z > 0).all() or not np.isfinite(uv).all():
                continue
            lo = np.clip(uv.min(0), 0, [W, H])
            hi = np.clip(uv.max(0), 0, [W, H])
            if (hi - lo).min() < 2:
                continue
            new[n] = bbox_from_points(np.stack([lo, hi]))
        return torch.as_tensor(new, dtype=boxes_t.dtype, device=boxes_t.device)
