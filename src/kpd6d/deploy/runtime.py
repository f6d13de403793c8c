"""The torch-free pose runtime: an export folder (:mod:`kpd6d.deploy.export`) on ONNX Runtime or
OpenVINO, CPU. Imports numpy, OpenCV (through :mod:`kpd6d.pnp`) and the backend's package only —
never torch, kornia or :mod:`kpd6d.kpd.module` (tests/test_deploy.py checks ``sys.modules`` in a
fresh process; tests/test_layering.py checks the imports).

:class:`RuntimePipeline` has the interface of :class:`kpd6d.pipeline.PosePipeline` (``__call__``,
``predict_batch``, ``detect``, ``predict_boxes``, ``object_points``, ``last_timings``,
``kpd.keypoints_3d``, ``refine_boxes``, ``min_confidence``) and returns the same pose dicts with
numpy arrays: detector (resize → ``detector.onnx`` → numpy peaks / top-k / post-processing, or
the oracle's GT boxes) → crops (numpy bilinear, the codec's affine) → ``kpd.onnx`` → the codec's
decoder in numpy (:mod:`kpd6d.kpd.decoders_numpy`) → top-l → PnP
(``PNP_SOLVERS``, numpy / OpenCV).

Backends: ``onnxruntime`` (``CPUExecutionProvider``), ``openvino`` (reads the ONNX files; CPU,
``INFERENCE_PRECISION_HINT=f32`` so that results match torch's float32 — OpenVINO picks bf16 on CPUs
that have it otherwise) and ``openvino_bf16`` (the same with ``INFERENCE_PRECISION_HINT=bf16``: about
1.6x faster networks on CPUs with AMX / AVX512-BF16, outputs no longer equal to torch's; its
accuracy cost is measured in docs/benchmarks.md, session 10). ``threads``: intra-op threads (None: the backend's default).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kpd6d.deploy import SIDECAR
from kpd6d.deploy.ops import (
    decode_centernet,
    oracle_detections,
    postprocess_detections,
    resize_bilinear_antialias,
    warp_affine_bilinear,
)
from kpd6d.geometry import (
    affine_apply,
    box_to_crop_affine,
    invert_affine,
)
from kpd6d.io import stack_rgb_images
from kpd6d.kpd.decoders_numpy import build_numpy_decoder, heatmap_to_crop
from kpd6d.pnp.confidence import RESIDUAL_SCALE_PX
from kpd6d.pnp.estimator import PoseEstimatorBase

__all__ = ["RUNTIME_BACKENDS", "BackendUnavailableError", "RuntimeDetector", "RuntimeKPD", "RuntimePipeline",
           "Session", "read_sidecar"]

RUNTIME_BACKENDS = ("onnxruntime", "openvino", "openvino_bf16")


class BackendUnavailableError(ImportError):
    """The backend's package is not installed; the message says what to install."""


def read_sidecar(export_dir: str | os.PathLike) -> dict[str, Any]:
    """The ``kpd6d_export.json`` of an export folder (a clear error when it is not one)."""
    from kpd6d.io import read_json

    d = Path(export_dir)
    p = d / SIDECAR
    if not p.is_file():
        raise FileNotFoundError(f"export_dir={str(d)!r} holds no {SIDECAR} (export one with kpd6d-export "
                                "kpd_ckpt=... detector_ckpt=... out_dir=...)")
    side = read_json(p, what="kpd6d export sidecar", error=ValueError)
    if not isinstance(side, dict) or side.get("format") != "kpd6d_export" or "kpd" not in side:
        raise ValueError(f"{str(p)!r} is not a kpd6d export sidecar (no format: kpd6d_export / kpd entry)")
    return side


class Session:
    """One ONNX graph on a backend: ``session(x) -> list of outputs`` (numpy float32)."""

    def __init__(self, path: str | os.PathLike, backend: str = "onnxruntime", threads: int | None = None,
                 precision: str = "f32") -> None:
        if backend not in RUNTIME_BACKENDS:
            raise ValueError(f"backend {backend!r} unknown; the runtime has {', '.join(RUNTIME_BACKENDS)} "
                             "(backend=torch runs the checkpoints: PosePipeline.from_checkpoints)")
        if backend == "openvino_bf16":
            backend, precision = "openvino", "bf16"
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"ONNX model {str(path)!r} does not exist")
        self.backend, self.path = backend, path
        if backend == "onnxruntime":
            try:
                import onnxruntime as ort
            except ImportError as exc:
                raise BackendUnavailableError("backend=onnxruntime needs the onnxruntime package: "
                                              "pip install kpd6d[deploy]") from exc
            so = ort.SessionOptions()
            if threads:
                so.intra_op_num_threads = int(threads)
                so.inter_op_num_threads = 1
            self._sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
            self._input = self._sess.get_inputs()[0].name
            self._run = lambda x: self._sess.run(None, {self._input: x})
        else:
            try:
                import openvino as ov
            except ImportError as exc:
                raise BackendUnavailableError("backend=openvino needs the openvino package: "
                                              "pip install kpd6d[deploy]") from exc
            core = ov.Core()
            config = {"INFERENCE_PRECISION_HINT": precision}
            if threads:
                config["INFERENCE_NUM_THREADS"] = int(threads)
            self._compiled = core.compile_model(core.read_model(str(path)), "CPU", config)
            self._request = self._compiled.create_infer_request()
            outputs = list(self._compiled.outputs)

            def run(x):
                res = self._request.infer({0: x})
                return [np.asarray(res[o]) for o in outputs]

            self._run = run

    def __call__(self, x: np.ndarray) -> list[np.ndarray]:
        return [np.asarray(o, dtype=np.float32) for o in self._run(np.ascontiguousarray(x, dtype=np.float32))]


class RuntimeKPD:
    """The exported KPD: ``predict_keypoints(images, boxes, image_index, obj_ids)`` as
    :meth:`kpd6d.kpd.module.KPDModule.predict_keypoints`, on (B, H, W, 3) float32 [0, 1] images."""

    def __init__(self, export_dir: str | os.PathLike, node: Mapping[str, Any], backend: str = "onnxruntime",
                 threads: int | None = None) -> None:
        self.node = dict(node)
        self.session = Session(Path(export_dir) / node["file"], backend, threads)
        self.obj_ids = [int(o) for o in node["obj_ids"]]
        self._index = {o: i for i, o in enumerate(self.obj_ids)}
        self.keypoints_3d = {o: np.asarray(k, dtype=np.float64) for o, k in zip(self.obj_ids, node["keypoints_3d"])}
        mp = node.get("model_points")
        self._surface = {o: np.asarray(p, dtype=np.float64) for o, p in zip(self.obj_ids, mp)} if mp else None
        codec = node["codec"]
        self.input_size, self.out_stride = int(codec["input_size"]), int(codec["out_stride"])
        self.crop_scale = float(codec["crop_scale"])
        self.decoder = build_numpy_decoder(codec.get("decoder"))
        self.num_keypoints, self.num_groups = int(node["num_keypoints"]), int(node["num_groups"])

    def surface_points(self, obj_id: int) -> np.ndarray:
        """(P, 3) model points (mm) of ``obj_id`` (else its keypoints), as ``KPDModule.surface_points``."""
        o = int(obj_id)
        return self._surface[o] if self._surface is not None else self.keypoints_3d[o]

    def crops(self, images: np.ndarray, boxes: np.ndarray, image_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The codec's crops (N, 3, S, S) float32 and image → crop affines (N, 2, 3) float64."""
        A = box_to_crop_affine(np.asarray(boxes, dtype=np.float64).reshape(-1, 4), self.input_size,
                               scale=self.crop_scale)
        S = self.input_size
        crops = np.zeros((len(A), 3, S, S), dtype=np.float32)
        for b in np.unique(image_index):
            sel = np.flatnonzero(image_index == b)
            crops[sel] = warp_affine_bilinear(images[int(b)], A[sel], S)
        return crops, A

    def heatmaps(self, crops: np.ndarray, obj_ids: Sequence[int]) -> np.ndarray:
        """Crops (N, 3, S, S) → each crop's object group of heatmaps (N, k, S/s, S/s)."""
        unknown = sorted({int(o) for o in obj_ids} - set(self._index))
        if unknown:
            raise KeyError(f"exported KPD does not cover object(s) {unknown}; it covers {self.obj_ids}")
        hm = self.session(crops)[0]
        if self.num_groups == 1:
            return hm
        N, _, h, w = hm.shape
        groups = np.asarray([self._index[int(o)] for o in obj_ids])
        return hm.reshape(N, self.num_groups, self.num_keypoints, h, w)[np.arange(N), groups]

    def predict_keypoints(self, images: np.ndarray, boxes, image_index, obj_ids) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints (N, k, 2) image px and confidences (N, k) (float32, as the torch module's)."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        image_index = np.asarray(image_index, dtype=np.int64).reshape(-1)
        k = self.num_keypoints
        if len(boxes) == 0:
            return np.zeros((0, k, 2), np.float32), np.zeros((0, k), np.float32)
        crops, A = self.crops(images, boxes, image_index)
        coords, conf = self.decoder(self.heatmaps(crops, list(obj_ids)))
        kp_img = affine_apply(invert_affine(A), heatmap_to_crop(coords, self.out_stride).astype(np.float64))
        return kp_img.astype(np.float32), conf.astype(np.float32)


class RuntimeDetector:
    """The exported CenterNet (or the oracle): ``predict(images (B, H, W, 3) float32 [0, 1], targets)``
    → one :class:`~kpd6d.deploy.ops.NumpyDetections` per image."""

    def __init__(self, export_dir: str | os.PathLike | None, node: Mapping[str, Any], backend: str = "onnxruntime",
                 threads: int | None = None, obj_ids: Sequence[int] | None = None, **overrides: Any) -> None:
        self.node = {**dict(node), **overrides}
        self.name = self.node["name"]
        if self.node.pop("test_scales", None) not in (None, 1, [1], (1,)):
            raise ValueError(f"the exported {self.name} detector runs at one input size (its ONNX graph is fixed): "
                             f"test_scales {overrides['test_scales']} needs the PyTorch checkpoint (kpd6d-evaluate)")
        self.obj_ids = None if obj_ids is None else [int(o) for o in obj_ids]
        if self.name == "oracle":
            self.session = None
            return
        if self.name != "centernet":
            raise ValueError(f"exported detector {self.name!r} is not supported by the runtime (centernet, oracle)")
        have = [int(o) for o in self.node["obj_ids"]]
        if self.obj_ids is not None and sorted(set(self.obj_ids) - set(have)):
            raise ValueError(f"exported detector covers obj_ids {have}; it cannot detect "
                             f"{sorted(set(self.obj_ids) - set(have))}")
        self.session = Session(Path(export_dir) / self.node["file"], backend, threads)

    def predict(self, images: np.ndarray, targets: Sequence[dict] | None = None):
        n = self.node
        if self.session is None:
            return oracle_detections(targets, self.obj_ids, int(n.get("max_detections", 100)))
        H, W = images.shape[1:3]
        w, h = n["input_size"]
        x = resize_bilinear_antialias(np.ascontiguousarray(images.transpose(0, 3, 1, 2)), (w, h))
        heat, wh, off = self.session(x)
        boxes, labels, scores = decode_centernet(heat, wh, off, int(n["stride"]), int(n["top_k"]))
        boxes = boxes * np.asarray([W / w, H / h, W / w, H / h], dtype=np.float32)
        return postprocess_detections(boxes, labels, scores, n["obj_ids"], float(n["score_threshold"]),
                                      int(n["max_detections"]), bool(n["one_per_object"]))


class RuntimePipeline(PoseEstimatorBase):
    """Detector + KPD + PnP from an export folder (module docstring). ``detector``: ``"export"`` (the
    exported detector; the oracle if none was exported) or ``"oracle"`` (GT boxes from ``targets``).
    ``__call__``, ``predict_batch``, ``detect``, ``predict_boxes`` and box refinement are the shared
    core's (:class:`kpd6d.pnp.estimator.PoseEstimatorBase`, as :class:`kpd6d.pipeline.PosePipeline`'s);
    this class runs the exported networks."""

    def __init__(self, export_dir: str | os.PathLike, backend: str = "onnxruntime", pnp: Any = "epnp_ransac",
                 top_l: int | None = 20, refine_boxes: int = 0, detector: str = "export",
                 obj_ids: Sequence[int] | None = None, threads: int | None = None, min_confidence: float = 0.0,
                 residual_scale_px: float = RESIDUAL_SCALE_PX, box_scale: float = 1.0,
                 depth_calibration: Any = 1.0, candidates: Any = 1, crop_tta: Any = 1,
                 **detector_overrides: Any) -> None:
        if backend not in RUNTIME_BACKENDS:
            raise ValueError(f"backend {backend!r} unknown; known: {', '.join(RUNTIME_BACKENDS)}")
        self._set_options(pnp, top_l, refine_boxes, min_confidence, residual_scale_px, box_scale, depth_calibration,
                          candidates, crop_tta)
        self.export_dir, self.backend = Path(export_dir), backend
        self.sidecar = read_sidecar(export_dir)
        self.kpd = RuntimeKPD(export_dir, self.sidecar["kpd"], backend, threads)
        dnode = {"name": "oracle"} if detector == "oracle" else self.sidecar.get("detector", {"name": "oracle"})
        self.detector = RuntimeDetector(export_dir, dnode, backend, threads, obj_ids=obj_ids, **detector_overrides)
        self.device = "cpu"

    # -- what the shared core (kpd6d.pnp.estimator) asks of this pipeline ---------------------------
    def _batch(self, images) -> np.ndarray:
        """uint8 RGB images (H, W, 3) (a list or (B, H, W, 3)) -> float32 (B, H, W, 3) in [0, 1]."""
        return stack_rgb_images(images).astype(np.float32) / np.float32(255.0)

    def _num_images(self, x: np.ndarray) -> int:
        return int(x.shape[0])

    def _image_hw(self, x: np.ndarray) -> tuple[int, int]:
        return int(x.shape[1]), int(x.shape[2])

    def _run_detector(self, x: np.ndarray, targets):
        return self.detector.predict(x, targets=targets)

    def _keypoints(self, x: np.ndarray, boxes: np.ndarray, image_index: np.ndarray, obj_ids: list[int]):
        # float32 boxes, as the torch pipeline's crops take them (the same crops to the last bit)
        kp2d, conf = self.kpd.predict_keypoints(x, boxes.astype(np.float32), image_index, obj_ids)
        return kp2d.astype(np.float64), conf.astype(np.float64)

    def object_points(self, obj_id: int) -> np.ndarray:
        """(P, 3) mm surface points of ``obj_id`` (as :meth:`PosePipeline.object_points`)."""
        return np.asarray(self.kpd.surface_points(int(obj_id)), dtype=np.float64).reshape(-1, 3)


