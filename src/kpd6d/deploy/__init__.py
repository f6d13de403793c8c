"""Deployment: ONNX export of the two networks and a torch-free ONNX Runtime / OpenVINO CPU runtime.

* :mod:`kpd6d.deploy.export` — :func:`~kpd6d.deploy.export.export_models` (KPD + detector checkpoints
  → ``kpd.onnx``, ``detector.onnx`` and the ``kpd6d_export.json`` sidecar); imports torch.
* :mod:`kpd6d.deploy.runtime` — :class:`~kpd6d.deploy.runtime.RuntimePipeline`: crop → KPD → decode →
  top-l → PnP and the detector's post-processing in numpy / OpenCV on ``onnxruntime`` or ``openvino``
  sessions; imports neither torch nor :mod:`kpd6d.kpd.module`.
* :mod:`kpd6d.deploy.ops` — the numpy image operations the runtime needs (crop sampling, antialiased
  resize, CenterNet decoding), written to match the torch / kornia ones.

See docs/deployment.md. Submodules are imported on use.
"""

from __future__ import annotations

__all__ = ["BACKENDS", "SIDECAR"]

#: inference backends of PosePipeline / kpd6d-evaluate / kpd6d-predict
BACKENDS = ("torch", "onnxruntime", "openvino", "openvino_bf16")
#: the sidecar file name in an export folder
SIDECAR = "kpd6d_export.json"
