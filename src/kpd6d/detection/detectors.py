"""The ``DETECTORS`` registry entries and the detector checkpoint format.

Entries: ``centernet`` (default of this project), ``fcos``, ``faster_rcnn``, ``oracle``.
``save_detector(detector, path)`` writes a self-contained file (entry name, constructor parameters,
object ids, input size, box-error statistics, weights); ``load_detector(path)`` rebuilds a ready
detector from it, or from a ``DetectorModule`` Lightning checkpoint, without any training config.
"""

from __future__ import annotations

import functools
import inspect
import os
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from kpd6d.data.bop_io import DEFAULT_BOX_FIELD
from kpd6d.detection.centernet import CenterNet
from kpd6d.detection.detections import DetectionInputError, Detector, check_test_scales
from kpd6d.detection.oracle import OracleDetector
from kpd6d.detection.torchvision_detectors import TorchvisionDetector
from kpd6d.io import to_plain
from kpd6d.registry import DETECTORS

__all__ = ["CHECKPOINT_KEY", "INFERENCE_OVERRIDES", "build_detector", "check_detector_overrides", "load_detector",
           "save_detector"]

CHECKPOINT_KEY = "kpd6d_detector"
FORMAT_VERSION = 1
#: inference settings a loaded detector may be given instead of its checkpoint's (load_detector, the configs'
#: ``detector_overrides``)
INFERENCE_OVERRIDES = ("score_threshold", "max_detections", "one_per_object", "test_scales")
#: constructor parameters that only say where initial weights come from
_WEIGHT_PARAMS = ("backbone_weights_path", "weights_path", "backbone_pretrained")


def _register(name: str, factory):
    """Register ``factory`` under ``name``; the built detector remembers (name, params) for saving,
    every constructor parameter included (defaults resolved), so a checkpoint rebuilds the same
    detector even after a default changes."""

    @functools.wraps(factory)
    def build(**params: Any) -> Detector:
        det = factory(**params)
        bound = inspect.signature(factory).bind(**params)
        bound.apply_defaults()
        # values the detector resolved itself (e.g. its backbone's normalisation) replace null defaults
        det._spec = {"name": name, "params": to_plain({**bound.arguments, **getattr(det, "resolved_params", {})})}
        return det

    DETECTORS.add(name, build)
    return build


_register("centernet", CenterNet)
_register("oracle", OracleDetector)


def fcos(obj_ids: Sequence[int] | None = None, backbone: str = "resnet18", input_size: Sequence[int] | None = (320, 240),
         score_threshold: float = 0.1, max_detections: int = 100, one_per_object: bool = False,
         backbone_weights_path: str | None = None, weights_path: str | None = None,
         nms_threshold: float = 0.6, backbone_pretrained: str | None = None, mean: Sequence[float] | None = None,
         std: Sequence[float] | None = None) -> TorchvisionDetector:
    """torchvision FCOS (anchor-free, FPN strides 8..128)."""
    return TorchvisionDetector("fcos", obj_ids, backbone, input_size, score_threshold, max_detections, one_per_object,
                               backbone_weights_path, weights_path, nms_threshold, backbone_pretrained, mean, std)


def faster_rcnn(obj_ids: Sequence[int] | None = None, backbone: str = "resnet18",
                input_size: Sequence[int] | None = (320, 240), score_threshold: float = 0.1,
                max_detections: int = 100, one_per_object: bool = False, backbone_weights_path: str | None = None,
                weights_path: str | None = None, nms_threshold: float = 0.5, backbone_pretrained: str | None = None,
                mean: Sequence[float] | None = None, std: Sequence[float] | None = None) -> TorchvisionDetector:
    """torchvision Faster R-CNN (two-stage, FPN strides 4..64)."""
    return TorchvisionDetector("faster_rcnn", obj_ids, backbone, input_size, score_threshold, max_detections,
                               one_per_object, backbone_weights_path, weights_path, nms_threshold, backbone_pretrained,
                               mean, std)


_register("fcos", fcos)
_register("faster_rcnn", faster_rcnn)


def build_detector(name: str, **params: Any) -> Detector:
    return DETECTORS.build(name, **params)


def detector_record(detector: Detector) -> dict:
    """The checkpoint metadata of ``detector`` (everything except its weights)."""
    spec = detector.spec()
    if not spec:
        raise DetectionInputError(f"{type(detector).__name__} was not built through DETECTORS; cannot save it")
    return {
        "format_version": FORMAT_VERSION,
        "name": spec["name"],
        "params": spec["params"],
        "obj_ids": list(detector.obj_ids or []),
        "class_to_obj_id": {i: oid for i, oid in enumerate(detector.obj_ids or [])},
        "input_size": list(detector.input_size) if detector.input_size else None,
        "box_stats": detector.box_stats,
        "box": detector.box_field,
    }


def save_detector(detector: Detector, path: str | os.PathLike, extra: dict | None = None) -> Path:
    """Write ``detector`` to ``path`` atomically (temp file + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {CHECKPOINT_KEY: detector_record(detector), "state_dict": detector.state_dict(), **(extra or {})}
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    os.close(fd)
    try:
        torch.save(payload, tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def check_detector_overrides(value: Any, error: type[Exception] = ValueError,
                             key: str = "detector_overrides") -> dict:
    """A config's ``detector_overrides`` (None or a mapping of :data:`INFERENCE_OVERRIDES`) checked and
    without its null entries (null: the checkpoint's value): ``score_threshold`` in [0, 1],
    ``max_detections`` a positive integer, ``one_per_object`` a boolean, ``test_scales`` a list of input-size
    factors (:meth:`Detector.set_test_scales`). ``error`` is raised naming ``key``."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise error(f"{key} must be a mapping of {', '.join(INFERENCE_OVERRIDES)}, got {value!r}")
    bad = sorted(str(k) for k in value if k not in INFERENCE_OVERRIDES)
    if bad:
        raise error(f"{key}: cannot override {bad}; known: {', '.join(INFERENCE_OVERRIDES)}")
    out = {}
    for k, v in value.items():
        if v is None:
            continue
        if k == "score_threshold":
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= float(v) <= 1.0:
                raise error(f"{key}.score_threshold must be a number in [0, 1], got {v!r}")
            v = float(v)
        elif k == "max_detections":
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise error(f"{key}.max_detections must be a positive integer, got {v!r}")
        elif k == "test_scales":
            v = list(check_test_scales(v, error, f"{key}.test_scales"))
        elif not isinstance(v, bool):
            raise error(f"{key}.one_per_object must be true or false, got {v!r}")
        out[k] = v
    return out


def load_detector(path: str | os.PathLike, obj_ids: Sequence[int] | None = None, map_location: Any = "cpu",
                  **overrides: Any) -> Detector:
    """Rebuild a ready (eval-mode) detector from ``save_detector``'s file or a Lightning checkpoint.

    ``obj_ids``: the objects you need; a checkpoint trained for other objects raises a clear error.
    ``overrides`` replace inference settings (``score_threshold``, ``max_detections``,
    ``one_per_object``, ``test_scales``).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"detector checkpoint {str(path)!r} does not exist")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as exc:
        raise DetectionInputError(f"cannot read detector checkpoint {str(path)!r}: {exc}") from exc
    if not isinstance(payload, dict) or CHECKPOINT_KEY not in payload:
        keys = sorted(payload) if isinstance(payload, dict) else type(payload).__name__
        raise DetectionInputError(f"{str(path)!r} is not a kpd6d detector checkpoint (no {CHECKPOINT_KEY!r} "
                                  f"entry; found {keys})")
    rec = payload[CHECKPOINT_KEY]
    have = [int(i) for i in rec.get("obj_ids") or []]
    if obj_ids is not None and have:
        missing = sorted(set(int(i) for i in obj_ids) - set(have))
        if missing:
            raise DetectionInputError(f"detector checkpoint {str(path)!r} was trained for obj_ids {have}; "
                                      f"it cannot detect requested obj_ids {missing}")
    overrides = check_detector_overrides(overrides, DetectionInputError, "load_detector overrides")
    test_scales = overrides.pop("test_scales", None)  # an inference setting of the Detector, not a constructor parameter
    params = dict(rec["params"])
    for k in _WEIGHT_PARAMS:  # the weights come from the checkpoint: no file or package is consulted
        params.pop(k, None)
    params.update(overrides)
    det = build_detector(rec["name"], **params)
    state = payload["state_dict"]
    prefix = payload.get("state_dict_prefix", "")
    if prefix:
        state = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
    try:
        det.load_state_dict(state)
    except RuntimeError as exc:
        raise DetectionInputError(f"weights in {str(path)!r} do not fit a {rec['name']} detector built from its "
                                  f"recorded parameters: {exc}") from exc
    # the rebuilt spec (defaults resolved) with the record's weight paths, which were not rebuilt
    det._spec["params"].update(to_plain({k: rec["params"][k] for k in _WEIGHT_PARAMS if k in rec["params"]}))
    det.box_stats = rec.get("box_stats")
    det.box_field = rec.get("box") or DEFAULT_BOX_FIELD  # checkpoints before the field: visible-box detectors
    det.set_test_scales(test_scales)
    det.to(map_location if isinstance(map_location, (str, torch.device)) else "cpu")
    return det.eval()
