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
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from kpd6d.geometry import MIN_BOX_PX, box_problem
from kpd6d.io import stack_rgb_images
from kpd6d.pnp.confidence import RESIDUAL_SCALE_PX
from kpd6d.pnp.estimator import PoseEstimatorBase

__all__ = ["MIN_BOX_PX", "PipelineInputError", "PosePipeline", "box_problem", "default_device", "images_to_tensor"]


class PipelineInputError(ValueError):
    """An image, intrinsics or component the pipeline cannot use; the message says which and why."""


def default_device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def images_to_tensor(images: Sequence[np.ndarray] | np.ndarray, device: Any = "cpu") -> torch.Tensor:
    """uint8 RGB images (H, W, 3) (a list or a (B, H, W, 3) array, equal sizes) -> float (B, 3, H, W) in [0, 1]."""
    x = torch.from_numpy(stack_rgb_images(images, PipelineInputError)).to(device)
    return x.permute(0, 3, 1, 2).float().div_(255.0)


class PosePipeline(PoseEstimatorBase):
    """Detector + KPD + PnP. ``pnp`` is a solver object or a ``PNP_SOLVERS`` name; ``top_l`` the number
    of most confident keypoints passed to PnP (None: all). ``__call__``, ``predict_batch``, ``detect``,
    ``predict_boxes`` and box refinement are the shared core's (:class:`kpd6d.pnp.estimator.PoseEstimatorBase`);
    this class runs the torch networks."""

    input_error = PipelineInputError

    def __init__(self, detector, kpd, pnp: Any = "epnp_ransac", top_l: int | None = 20,
                 device: str | torch.device | None = None, refine_boxes: int = 0, min_confidence: float = 0.0,
                 residual_scale_px: float = RESIDUAL_SCALE_PX, box_scale: float = 1.0,
                 depth_calibration: Any = 1.0, candidates: Any = 1, crop_tta: Any = 1) -> None:
        if not hasattr(detector, "predict"):
            raise PipelineInputError(f"detector must have .predict(images, targets=None), got {type(detector).__name__}")
        if not hasattr(kpd, "predict_keypoints") or not hasattr(kpd, "keypoints_3d"):
            raise PipelineInputError(f"kpd must have .predict_keypoints(...) and .keypoints_3d, got {type(kpd).__name__}")
        self._set_options(pnp, top_l, refine_boxes, min_confidence, residual_scale_px, box_scale, depth_calibration,
                          candidates, crop_tta)
        self.detector, self.kpd = detector, kpd
        self.device = torch.device(device) if device is not None else default_device()
        for m in (detector, kpd):
            if isinstance(m, torch.nn.Module):
                m.to(self.device).eval()

    # -- construction ---------------------------------------------------------------------------
    @classmethod
    def from_checkpoints(cls, detector: str | os.PathLike, kpd: str | os.PathLike, *, pnp: Any = "epnp_ransac",
                         top_l: int | None = 20, device: str | torch.device | None = None,
                         obj_ids: Sequence[int] | None = None, refine_boxes: int = 0, min_confidence: float = 0.0,
                         residual_scale_px: float = RESIDUAL_SCALE_PX, box_scale: float = 1.0,
                         depth_calibration: Any = 1.0, candidates: Any = 1, crop_tta: Any = 1,
                         **detector_overrides: Any) -> PosePipeline:
        """Load a detector checkpoint (or ``"oracle"``) and a KPD checkpoint (or a networks manifest
        of one KPD per object, :mod:`kpd6d.kpd.ensemble`)."""
        from kpd6d.kpd.ensemble import load_kpd

        device = torch.device(device) if device is not None else default_device()
        kpd_module = load_kpd(kpd)
        if str(detector) == "oracle":
            from kpd6d.registry import DETECTORS

            scales = detector_overrides.pop("test_scales", None)
            det = DETECTORS.build("oracle", obj_ids=list(obj_ids) if obj_ids else None, **detector_overrides)
            det.set_test_scales(scales)  # a clear error unless one scale
        else:
            from kpd6d.detection import load_detector

            det = load_detector(detector, obj_ids=obj_ids, map_location=device, **detector_overrides)
        return cls(det, kpd_module, pnp=pnp, top_l=top_l, device=device, refine_boxes=refine_boxes,
                   min_confidence=min_confidence, residual_scale_px=residual_scale_px, box_scale=box_scale,
                   depth_calibration=depth_calibration, candidates=candidates, crop_tta=crop_tta)

    @classmethod
    def from_export(cls, export_dir: str | os.PathLike, backend: str = "onnxruntime", *, pnp: Any = "epnp_ransac",
                    top_l: int | None = 20, detector: str = "export", obj_ids: Sequence[int] | None = None,
                    refine_boxes: int = 0, device: str | torch.device | None = None, threads: int | None = None,
                    min_confidence: float = 0.0, residual_scale_px: float = RESIDUAL_SCALE_PX, box_scale: float = 1.0,
                    depth_calibration: Any = 1.0, candidates: Any = 1, crop_tta: Any = 1, **detector_overrides: Any):
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
                                   residual_scale_px=residual_scale_px, box_scale=box_scale, depth_calibration=depth_calibration,
                                   candidates=candidates, crop_tta=crop_tta, **detector_overrides)
        src = read_sidecar(export_dir)["source"]
        det = "oracle" if detector == "oracle" or not src.get("detector_ckpt") else src["detector_ckpt"]
        return cls.from_checkpoints(det, src["kpd_ckpt"], pnp=pnp, top_l=top_l, device=device, obj_ids=obj_ids,
                                    refine_boxes=refine_boxes, min_confidence=min_confidence,
                                    residual_scale_px=residual_scale_px, box_scale=box_scale, depth_calibration=depth_calibration,
                                    candidates=candidates, crop_tta=crop_tta, **detector_overrides)

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

    # -- what the shared core (kpd6d.pnp.estimator) asks of this pipeline ---------------------------
    def _batch(self, images) -> torch.Tensor:
        return images.to(self.device) if isinstance(images, torch.Tensor) else images_to_tensor(images, self.device)

    def _num_images(self, x: torch.Tensor) -> int:
        return int(x.shape[0])

    def _image_hw(self, x: torch.Tensor) -> tuple[int, int]:
        return int(x.shape[-2]), int(x.shape[-1])

    @torch.no_grad()
    def _run_detector(self, x: torch.Tensor, targets):
        return self.detector.predict(x, targets=targets)

    @torch.no_grad()
    def _keypoints(self, x: torch.Tensor, boxes: np.ndarray, image_index: np.ndarray, obj_ids: list[int]):
        dev = self.device
        kp2d, conf = self.kpd.predict_keypoints(
            x, torch.as_tensor(boxes, dtype=torch.float32, device=dev), torch.as_tensor(image_index, device=dev),
            torch.as_tensor(obj_ids, dtype=torch.long, device=dev))
        if dev.type == "cuda":
            torch.cuda.synchronize()
        kp2d = torch.as_tensor(kp2d).float().detach().cpu().numpy().astype(np.float64)
        return kp2d, torch.as_tensor(conf).float().detach().cpu().numpy().astype(np.float64)

    def object_points(self, obj_id: int) -> np.ndarray:
        """(P, 3) mm points of object ``obj_id`` whose projection bounds it in the image: the surface
        points a KPD checkpoint carries, else its keypoints (box refinement and tracking crop on their box)."""
        surface = getattr(self.kpd, "surface_points", None)
        if surface is not None:
            return np.asarray(surface(int(obj_id)), dtype=np.float64).reshape(-1, 3)
        return np.asarray(self.kpd.keypoints_3d[int(obj_id)], dtype=np.float64).reshape(-1, 3)
