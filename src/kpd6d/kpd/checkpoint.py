"""The KPD checkpoint schema: what a checkpoint records, reading and validating one, and older
checkpoints mapped onto the current record.

A KPD checkpoint is a Lightning checkpoint of :class:`~kpd6d.kpd.module.KPDModule` (written by the
trainer's ``ModelCheckpoint`` or ``trainer.save_checkpoint``) whose ``hyper_parameters`` are
:func:`kpd_hparams`: everything inference needs, so :func:`load_kpd_module` rebuilds the module
without any training config — covered object ids, their 3-D keypoints, diameters, symmetries and
sample points (for ADD(-S) and 2-D projection metrics), the heatmap ``codec`` (input size, output
stride, σ, crop scale, decoder: :mod:`kpd6d.kpd.codec`), backbone (with its input normalisation)
and head, plus the training settings.

Checkpoints written before the codec record ``input_size`` / ``out_stride`` / ``sigma`` /
``crop_scale`` / ``decoder`` separately; :func:`upgrade_hparams` maps them onto ``codec``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from kpd6d.finetune import finetune_config
from kpd6d.io import to_plain
from kpd6d.kpd.codec import CODEC_FIELDS, codec_config

__all__ = ["kpd_hparams", "load_kpd_module", "read_kpd_checkpoint", "upgrade_hparams"]

REQUIRED_HPARAMS = ("obj_ids", "keypoints_3d")


def kpd_hparams(*, obj_ids: Sequence[int], keypoints_3d: Sequence, diameters: Sequence[float],
                symmetric: Sequence[bool] | None, model_points: Sequence | None, symmetries: Sequence | None,
                backbone: Mapping | None, head: Mapping | None, grouping: str, codec: Mapping,
                loss: Mapping | None, optimizer: Mapping | None, scheduler: Mapping | None,
                augment: Mapping | None, top_l: int | None, pnp: Mapping | None, channels_last: bool,
                finetune: Mapping | None) -> dict[str, Any]:
    """The hyper-parameter record of a KPD checkpoint (plain values, defaults filled in)."""
    n = len(obj_ids)
    return {
        "obj_ids": [int(o) for o in obj_ids], "keypoints_3d": to_plain(keypoints_3d),
        "diameters": [float(d) for d in diameters],
        "symmetric": [bool(s) for s in (symmetric if symmetric is not None else [False] * n)],
        "model_points": to_plain(model_points) if model_points is not None else None,
        "symmetries": to_plain(symmetries) if symmetries is not None else None,
        "backbone": to_plain(backbone) or {"name": "resnet101"}, "head": to_plain(head) or {"name": "deconv"},
        "grouping": grouping, "codec": to_plain(codec),
        "loss": to_plain(loss) or {}, "optimizer": to_plain(optimizer) or {"name": "adam", "lr": 1e-3},
        "scheduler": to_plain(scheduler), "augment": to_plain(augment), "top_l": top_l,
        "pnp": to_plain(pnp) or {"name": "epnp"}, "channels_last": bool(channels_last),
        "finetune": finetune_config(to_plain(finetune), "KPDModule finetune"),
    }


def upgrade_hparams(hparams: Mapping[str, Any]) -> dict[str, Any]:
    """A checkpoint's hyper-parameters in the current schema: the separate codec fields of older
    checkpoints (``input_size``, ``out_stride``, ``sigma``, ``crop_scale``, ``decoder``) become one
    ``codec`` node (their defaults then were the codec's: 256, 4, 2.0, 1.25, subpixel)."""
    hp = dict(hparams)
    legacy = {k: hp.pop(k) for k in CODEC_FIELDS if k in hp}
    if legacy:
        hp["codec"] = codec_config(hp.get("codec"), what="KPD checkpoint hyper-parameters", **legacy)
    return hp


def _takes_pretrained(backbone_cfg: Mapping) -> bool:
    import inspect

    from kpd6d.registry import BACKBONES

    name = backbone_cfg.get("name")
    if "pretrained" in backbone_cfg:
        return True
    if name not in BACKBONES:
        return False
    try:
        return "pretrained" in inspect.signature(BACKBONES.get(name)).parameters
    except (TypeError, ValueError):
        return False


def read_kpd_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Read and validate a KPD checkpoint file; returns the checkpoint dict (on the CPU).

    Raises ``FileNotFoundError`` (no file) or ``ValueError`` naming what is wrong: empty, unreadable,
    a detector checkpoint, or not a KPD one (no ``obj_ids`` / ``keypoints_3d`` / ``state_dict``).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"KPD checkpoint {str(p)!r} does not exist")
    if p.stat().st_size == 0:
        raise ValueError(f"KPD checkpoint {str(p)!r} is empty (0 bytes): an interrupted copy or save?")
    try:
        ckpt = torch.load(str(p), map_location="cpu", weights_only=False)
    except Exception as exc:
        raise ValueError(f"KPD checkpoint {str(p)!r} cannot be read (truncated, or not a torch checkpoint): "
                         f"{type(exc).__name__}: {exc}") from exc
    if isinstance(ckpt, dict) and "kpd6d_detector" in ckpt:
        raise ValueError(f"{str(p)!r} is a detector checkpoint, not a KPD one: pass it as detector_ckpt "
                         "(kpd_ckpt takes kpd/checkpoints/best.ckpt of a KPD run)")
    hparams = ckpt.get("hyper_parameters") if isinstance(ckpt, dict) else None
    if not isinstance(hparams, Mapping) or not set(REQUIRED_HPARAMS) <= set(hparams) \
            or not isinstance(ckpt.get("state_dict"), Mapping):
        found = sorted(ckpt) if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(f"{str(p)!r} is not a kpd6d KPD checkpoint (expected a Lightning checkpoint of KPDModule "
                         f"with hyper_parameters obj_ids / keypoints_3d and a state_dict; found {found})")
    return ckpt


def load_kpd_module(cls, path: str | os.PathLike, map_location: Any = "cpu"):
    """``cls`` (KPDModule) rebuilt from the checkpoint at ``path`` for inference (eval mode)."""
    p = Path(path)
    ckpt = read_kpd_checkpoint(p)
    hparams = upgrade_hparams(ckpt["hyper_parameters"])
    backbone = hparams.get("backbone")
    if isinstance(backbone, Mapping) and _takes_pretrained(backbone):
        # the weights are in the checkpoint: never consult a pretrained file or package again
        hparams["backbone"] = {**dict(backbone), "pretrained": None}
    # built from the checkpoint already read (Lightning's load_from_checkpoint would read the file again)
    module = cls(**hparams)
    try:
        module.load_state_dict(ckpt["state_dict"])
    except RuntimeError as exc:  # weights that do not fit the recorded network
        raise ValueError(f"KPD checkpoint {str(p)!r}: its weights do not fit the network its hyper-parameters "
                         f"describe: {exc}") from exc
    if isinstance(map_location, (str, torch.device)):
        module.to(map_location)
    return module.eval()
