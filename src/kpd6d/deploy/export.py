"""ONNX export of a KPD checkpoint and a detector checkpoint (``kpd6d-export``; docs/deployment.md).

:func:`export_models` writes into ``out_dir``:

* ``kpd.onnx`` — input ``crops`` (N, 3, S, S) float32 RGB in [0, 1] (the raw crops: the backbone's
  mean/std normalisation is *inside* the graph, as in ``KeypointNet.forward``), dynamic N (the
  crops of one call); output ``heatmaps`` (N, G·k, S/s, S/s), all G object groups (the runtime
  picks each crop's group, ``grouping: per_object``; G = 1 for ``shared``).
* ``detector.onnx`` (CenterNet) — input ``images`` (B, 3, h, w) float32 RGB in [0, 1] at the
  detector's *fixed* input size (w, h) (the runtime resizes the image, bilinear antialiased, as
  ``Detector.network_images``; normalisation inside the graph), dynamic B; outputs ``heatmap``
  (sigmoid probabilities), ``wh`` and ``offset`` (B, ·, h/4, w/4). Peak extraction, top-k and the
  post-processing run in numpy (:mod:`kpd6d.deploy.ops`). ``detector_ckpt="oracle"`` / None
  exports no detector (the runtime then takes GT boxes from ``targets``).
* ``kpd6d_export.json`` — the sidecar: everything inference needs besides the weights (object ids,
  3D keypoints and model points per object, the codec, normalisation, detector decoding
  parameters, the source checkpoints, versions).

Only CenterNet detectors export (torchvision FCOS / Faster R-CNN need their NMS and anchors in
the graph: not done); other names raise :class:`ExportError`.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from kpd6d.deploy import SIDECAR
from kpd6d.io import atomic_write_text, to_plain

__all__ = ["DEFAULT_OPSET", "FORMAT_VERSION", "ExportError", "export_detector", "export_kpd", "export_models"]

DEFAULT_OPSET = 17
FORMAT_VERSION = 1


class ExportError(ValueError):
    """A checkpoint or setting that cannot be exported; the message says why."""


class _KPDGraph(nn.Module):
    """Raw crops in [0, 1] → heatmaps of every object group (normalisation inside)."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, crops: torch.Tensor) -> torch.Tensor:
        return self.net(crops)


class _CenterNetGraph(nn.Module):
    """Network-size images in [0, 1] → (sigmoid heatmap, wh, offset) (normalisation inside)."""

    def __init__(self, det: nn.Module) -> None:
        super().__init__()
        self.det = det

    def forward(self, images: torch.Tensor):
        out = self.det(images)
        return torch.sigmoid(out["heatmap"].float()), out["wh"].float(), out["offset"].float()


def _export(module: nn.Module, example: torch.Tensor, path: Path, input_name: str, output_names: list[str],
            opset: int) -> None:
    import warnings

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    dyn = {input_name: {0: "batch"}, **{o: {0: "batch"} for o in output_names}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer / deprecation chatter of the TorchScript exporter
        torch.onnx.export(module, (example,), str(tmp), input_names=[input_name], output_names=output_names,
                          dynamic_axes=dyn, opset_version=int(opset), do_constant_folding=True, dynamo=False)
    os.replace(tmp, path)


def export_kpd(kpd, out_dir: str | os.PathLike, opset: int = DEFAULT_OPSET) -> dict[str, Any]:
    """Export a :class:`~kpd6d.kpd.module.KPDModule` to ``out_dir/kpd.onnx``; returns its sidecar node.
    (The module is left on the CPU, in eval mode.)"""
    kpd = kpd.cpu().eval()
    net = kpd.net.to(memory_format=torch.contiguous_format)
    S = kpd.codec.input_size
    _export(_KPDGraph(net).eval(), torch.rand(2, 3, S, S), Path(out_dir) / "kpd.onnx", "crops", ["heatmaps"], opset)
    if kpd.hparams.get("channels_last", False):
        kpd.net.to(memory_format=torch.channels_last)
    hp = kpd.hparams
    mp = hp.model_points
    return {
        "file": "kpd.onnx", "input": "crops", "output": "heatmaps",
        "obj_ids": [int(o) for o in hp.obj_ids],
        "keypoints_3d": [np.asarray(k, dtype=np.float64).tolist() for k in hp.keypoints_3d],
        "model_points": None if mp is None else [np.asarray(p, dtype=np.float64).tolist() for p in mp],
        "diameters": [float(d) for d in hp.diameters],
        "symmetric": None if hp.symmetric is None else [bool(s) for s in hp.symmetric],
        "num_keypoints": int(kpd.num_keypoints), "num_groups": int(kpd.net.num_groups), "grouping": hp.grouping,
        "codec": to_plain(kpd.codec.config()), "heatmap_size": int(kpd.codec.heatmap_size),
        "normalization": {"mean": to_plain(hp.backbone["mean"]), "std": to_plain(hp.backbone["std"]),
                          "in_graph": True, "input_range": [0.0, 1.0]},
        "pnp": to_plain(hp.get("pnp")), "top_l": hp.get("top_l"),
    }


def export_detector(det, out_dir: str | os.PathLike, opset: int = DEFAULT_OPSET) -> dict[str, Any]:
    """Export a CenterNet detector to ``out_dir/detector.onnx``; returns its sidecar node.
    (The detector is left on the CPU, in eval mode.)"""
    from kpd6d.detection.centernet import CenterNet

    spec = det.spec() if hasattr(det, "spec") else {}
    if not isinstance(det, CenterNet):
        raise ExportError(f"detector {spec.get('name', type(det).__name__)!r} cannot be exported: only centernet "
                          "detectors export to ONNX (fcos / faster_rcnn: not supported; use detector_ckpt=oracle "
                          "or the torch backend)")
    if det.input_size is None:
        raise ExportError("centernet with input_size=null cannot be exported: detector.onnx has a fixed input size")
    det = det.cpu().eval()
    w, h = det.input_size
    _export(_CenterNetGraph(det).eval(), torch.rand(1, 3, h, w), Path(out_dir) / "detector.onnx", "images",
            ["heatmap", "wh", "offset"], opset)
    return {
        "name": "centernet", "file": "detector.onnx", "input": "images", "outputs": ["heatmap", "wh", "offset"],
        "input_size": [int(w), int(h)], "resize": "bilinear, align_corners=false, antialias=true",
        "obj_ids": [int(o) for o in det.obj_ids], "stride": int(det.stride),
        "top_k": int(min(det.max_detections * (4 if det.one_per_object else 1), 500)),
        "score_threshold": float(det.score_threshold), "max_detections": int(det.max_detections),
        "one_per_object": bool(det.one_per_object),
        "normalization": {"mean": to_plain(det.resolved_params["mean"]), "std": to_plain(det.resolved_params["std"]),
                          "in_graph": True, "input_range": [0.0, 1.0]},
        "box_stats": to_plain(det.box_stats),
    }


def _versions() -> dict[str, str]:
    import kpd6d

    out = {"kpd6d": kpd6d.__version__, "torch": torch.__version__}
    try:
        import onnx

        out["onnx"] = onnx.__version__
    except ImportError:  # pragma: no cover - torch.onnx.export needs it
        pass
    return out


def export_models(kpd_ckpt: str | os.PathLike, detector_ckpt: str | os.PathLike | None, out_dir: str | os.PathLike,
                  opset: int = DEFAULT_OPSET, check: bool = True) -> dict[str, Any]:
    """Export ``kpd_ckpt`` (and ``detector_ckpt``: a CenterNet checkpoint, or ``"oracle"`` / None for
    none) into ``out_dir``; returns the sidecar written to ``out_dir/kpd6d_export.json``.

    ``check``: run ``onnx.checker`` on the written graphs.
    """
    from kpd6d.kpd.ensemble import is_manifest
    from kpd6d.kpd.module import KPDModule

    if is_manifest(kpd_ckpt):
        raise ValueError(f"kpd_ckpt={str(kpd_ckpt)!r} is a networks manifest (one KPD per object); export takes one "
                         "KPD checkpoint (a shared network, kpd_networks=shared)")
    try:
        import onnx  # torch.onnx.export needs it
    except ImportError as exc:
        raise ImportError("kpd6d export needs the onnx package: pip install kpd6d[deploy]") from exc
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    kpd = KPDModule.load_checkpoint(kpd_ckpt)
    sidecar: dict[str, Any] = {
        "format": "kpd6d_export", "format_version": FORMAT_VERSION, "opset": int(opset),
        "kpd": export_kpd(kpd, out, opset),
        "source": {"kpd_ckpt": str(Path(kpd_ckpt).resolve()),
                   "detector_ckpt": None if detector_ckpt in (None, "oracle") else str(Path(detector_ckpt).resolve())},
        "versions": _versions(), "exported_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    if detector_ckpt is None or str(detector_ckpt) == "oracle":
        sidecar["detector"] = {"name": "oracle"}
    else:
        from kpd6d.detection import load_detector

        sidecar["detector"] = export_detector(load_detector(detector_ckpt), out, opset)
    if check:
        import onnx

        for node in (sidecar["kpd"], sidecar["detector"]):
            if "file" in node:
                onnx.checker.check_model(str(out / node["file"]))
    import json

    atomic_write_text(out / SIDECAR, json.dumps(sidecar, indent=1))
    return sidecar
