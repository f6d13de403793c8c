"""Heatmap codec (``CODECS``): one object that encodes crop keypoints into target heatmaps and
decodes heatmaps back into crop keypoints, built from one ``codec`` config node (as mmpose 1.x's
``mmpose/codecs``).

The ``heatmap`` codec holds what target generation, the network's decoding and the crop transform
share: ``input_size`` (crop side, px), ``out_stride`` (crop px per heatmap px; heatmap side =
``input_size / out_stride``), ``sigma`` (heatmap px; target ``exp(-‖p − x‖² / σ²)``, see
:mod:`kpd6d.kpd.heatmaps`), ``crop_scale`` (crop side = ``crop_scale`` × the box's longer side) and
``decoder`` (a ``DECODERS`` config: the decode strategy, conf/decoder/).

* :meth:`HeatmapCodec.encode` — keypoints (..., K, 2) crop px (+ visibility) → target heatmaps
  (..., K, H, W) and per-keypoint weights (..., K) (the visibility; ones without one).
* :meth:`HeatmapCodec.decode` — heatmaps (B, K, H, W) → keypoints (B, K, 2) crop px and
  confidences (B, K).
* :meth:`HeatmapCodec.crop_affine` — boxes (..., 4) xywh image px → the image → crop affines
  (..., 2, 3) of the crops the codec's keypoints live in.

Config: ``{name: heatmap, input_size, out_stride, sigma, crop_scale, decoder: {name: ..., ...}}``
(conf/codec/heatmap.yaml; in the KPD stage ``stage.kpd.codec`` with the decoder group mounted at
``stage.kpd.codec.decoder``). :func:`codec_config` maps the older separate fields onto it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from kpd6d.kpd.heatmaps import crop_to_heatmap, gaussian_heatmaps, heatmap_to_crop
from kpd6d.registry import CODECS

__all__ = ["CODEC_FIELDS", "DEFAULT_DECODER", "HeatmapCodec", "build_codec", "codec_config"]

DEFAULT_DECODER = {"name": "subpixel"}
# the fields that used to be passed separately (dataset, KPDModule, checkpoints before the codec)
CODEC_FIELDS = ("input_size", "out_stride", "sigma", "crop_scale", "decoder")


class HeatmapCodec:
    """Gaussian heatmap targets at ``out_stride`` and a ``DECODERS`` decode strategy (module docstring)."""

    name = "heatmap"

    def __init__(self, input_size: int = 256, out_stride: int = 4, sigma: float = 2.0, crop_scale: float = 1.25,
                 decoder: Mapping | str | None = None) -> None:
        from kpd6d.io import to_plain
        from kpd6d.registry import DECODERS, build_from_cfg

        if int(out_stride) < 1:
            raise ValueError(f"heatmap codec: out_stride must be >= 1, got {out_stride}")
        if int(input_size) < 1 or int(input_size) % int(out_stride):
            raise ValueError(f"heatmap codec: input_size {input_size} must be a positive multiple of "
                             f"out_stride {out_stride}")
        if float(sigma) <= 0:
            raise ValueError(f"heatmap codec: sigma must be > 0, got {sigma}")
        if float(crop_scale) <= 0:
            raise ValueError(f"heatmap codec: crop_scale must be > 0, got {crop_scale}")
        self.input_size, self.out_stride = int(input_size), int(out_stride)
        self.sigma, self.crop_scale = float(sigma), float(crop_scale)
        dcfg = {"name": decoder} if isinstance(decoder, str) else to_plain(decoder)
        self.decoder_cfg: dict[str, Any] = dict(dcfg) if dcfg else dict(DEFAULT_DECODER)
        self.decoder = build_from_cfg(DECODERS, self.decoder_cfg)

    @property
    def heatmap_size(self) -> int:
        """Heatmap side (px): ``input_size / out_stride``."""
        return self.input_size // self.out_stride

    def config(self) -> dict[str, Any]:
        """The codec's config node (what ``build_codec`` takes back; what KPD checkpoints record)."""
        return {"name": self.name, "input_size": self.input_size, "out_stride": self.out_stride,
                "sigma": self.sigma, "crop_scale": self.crop_scale, "decoder": dict(self.decoder_cfg)}

    def __repr__(self) -> str:
        c = self.config()
        c.pop("name")
        return f"HeatmapCodec({', '.join(f'{k}={v!r}' for k, v in c.items())})"

    # -- encode / decode --------------------------------------------------------------------------
    def encode(self, keypoints, visibility=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Keypoints (..., K, 2) crop px → (target heatmaps (..., K, S/s, S/s) float32, weights (..., K)).

        Every keypoint gets its Gaussian (visible or not, see :func:`gaussian_heatmaps`); the weights
        are ``visibility`` as float (all ones when None).
        """
        kp = torch.as_tensor(keypoints).float()
        targets = gaussian_heatmaps(crop_to_heatmap(kp, self.out_stride), self.heatmap_size, self.sigma)
        if visibility is None:
            weights = torch.ones(kp.shape[:-1], dtype=kp.dtype, device=kp.device)
        else:
            weights = torch.as_tensor(visibility, device=kp.device).to(kp.dtype)
            if weights.shape != kp.shape[:-1]:
                raise ValueError(f"heatmap codec: visibility shape {tuple(weights.shape)} does not match the "
                                 f"keypoints' {tuple(kp.shape[:-1])}")
        return targets, weights

    def decode(self, heatmaps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Heatmaps (B, K, H, W) → (keypoints (B, K, 2) crop px, confidences (B, K))."""
        coords, conf = self.decoder(heatmaps.float())
        return heatmap_to_crop(coords, self.out_stride), conf

    # -- the crop transform -----------------------------------------------------------------------
    def crop_affine(self, boxes_xywh):
        """Image → crop affine(s) (..., 2, 3) for boxes (..., 4) xywh px (numpy or torch, as given):
        a square ``input_size`` crop, ``crop_scale`` × the box's longer side, centred on the box."""
        from kpd6d.geometry import box_to_crop_affine

        return box_to_crop_affine(boxes_xywh, self.input_size, scale=self.crop_scale)


@CODECS.register("heatmap")
def heatmap(input_size: int = 256, out_stride: int = 4, sigma: float = 2.0, crop_scale: float = 1.25,
            decoder: Mapping | str | None = None) -> HeatmapCodec:
    return HeatmapCodec(input_size=input_size, out_stride=out_stride, sigma=sigma, crop_scale=crop_scale,
                        decoder=decoder)


def codec_config(codec: Mapping | HeatmapCodec | None = None, *, what: str = "codec", **legacy: Any) -> dict[str, Any]:
    """One codec config node from ``codec`` (a config or a codec) or the older separate fields
    (``input_size``, ``out_stride``, ``sigma``, ``crop_scale``, ``decoder``; None = not given).

    Giving both is an error (which one would win is not obvious); giving neither is the default codec.
    """
    from kpd6d.io import to_plain

    unknown = sorted(set(legacy) - set(CODEC_FIELDS))
    if unknown:
        raise TypeError(f"{what}: unknown codec field(s) {unknown}; known: {', '.join(CODEC_FIELDS)}")
    given = {k: v for k, v in legacy.items() if v is not None}
    if codec is not None:
        if given:
            raise ValueError(f"{what}: pass the codec config or the separate fields {sorted(given)}, not both "
                             f"(set them inside codec: codec.{next(iter(sorted(given)))})")
        cfg = codec.config() if isinstance(codec, HeatmapCodec) else to_plain(codec)
        if not isinstance(cfg, Mapping):
            raise TypeError(f"{what}: codec must be a mapping with a 'name' key or a HeatmapCodec, "
                            f"got {type(codec).__name__}")
        cfg = dict(cfg)
        cfg.setdefault("name", HeatmapCodec.name)
        return cfg
    cfg = {"name": HeatmapCodec.name, **{k: to_plain(v) for k, v in given.items()}}
    return cfg


def build_codec(codec: Mapping | HeatmapCodec | None = None, *, what: str = "codec", **legacy: Any):
    """The codec of a config node (``CODECS``), a codec as is, or one from the separate fields."""
    from kpd6d.registry import build_from_cfg

    if isinstance(codec, HeatmapCodec) and not any(v is not None for v in legacy.values()):
        return codec
    return build_from_cfg(CODECS, codec_config(codec, what=what, **legacy))
