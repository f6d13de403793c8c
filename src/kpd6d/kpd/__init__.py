"""Keypoint-detector (KPD) stage: crops → heatmap network → decoded keypoints + confidences → top-l.

Modules: :mod:`~kpd6d.kpd.heatmaps` (Gaussian targets, stride mapping), :mod:`~kpd6d.kpd.decoders`
(``DECODERS``), :mod:`~kpd6d.kpd.codec` (``CODECS``: the heatmap codec — targets, decoding, crop
size — that the crops, the module and inference share), :mod:`~kpd6d.kpd.checkpoint` (the KPD
checkpoint schema), :mod:`~kpd6d.kpd.backbones` (``BACKBONES``), :mod:`~kpd6d.kpd.heads` (heads and the
network), :mod:`~kpd6d.kpd.crops` (crop dataset over BOP data), :mod:`~kpd6d.kpd.box_augment`
(``jitter`` / ``pgpg``), :mod:`~kpd6d.kpd.augment` (kornia batch augmentation),
:mod:`~kpd6d.kpd.module` (``KPDModule``), :mod:`~kpd6d.kpd.train` (``train_kpd``). Top-l selection and
PnP on it live in :mod:`kpd6d.pnp.top_l`. Submodules are imported on use (torch / Lightning are heavy).
"""

from __future__ import annotations

__all__ = ["KPDModule"]


def __getattr__(name: str):
    if name == "KPDModule":
        from kpd6d.kpd.module import KPDModule

        return KPDModule
    raise AttributeError(f"module 'kpd6d.kpd' has no attribute {name!r}")
