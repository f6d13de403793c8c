"""Helpers shared by the config-driven entry points: where the Hydra configs are, plain values, typed
values naming their key, and the run folder."""

from __future__ import annotations

import inspect
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from kpd6d.io import to_plain  # lives with the file writers; re-exported here

__all__ = ["RENAMED_STAGE_KEYS", "ConfigError", "cfg_float", "cfg_int", "check_number_fields", "check_stage_config",
           "config_dir", "renamed_overrides", "run_dir_of", "to_float", "to_fraction", "to_int", "to_plain"]


def config_dir() -> Path:
    """The ``conf/`` folder: ``kpd6d/conf`` in an installed wheel, else the checkout's top-level ``conf/``."""
    pkg = Path(__file__).resolve().parent
    for cand in (pkg / "conf", pkg.parent.parent / "conf"):
        if (cand / "train.yaml").is_file():
            return cand
    raise FileNotFoundError(
        f"kpd6d configs not found (looked in {pkg / 'conf'} and {pkg.parent.parent / 'conf'}); "
        "reinstall the package (pip install .) or run from a source checkout"
    )

_MISSING = object()


class ConfigError(ValueError):
    """A config value of the wrong type; the message names the key (``a.b``) and the value."""


def _lookup(cfg: Any, key: str, default: Any) -> Any:
    node = cfg
    for part in key.split("."):
        node = node[part] if (isinstance(node, Mapping) or hasattr(node, "keys")) and part in node else _MISSING
        if node is _MISSING:
            if default is _MISSING:
                raise ConfigError(f"config key {key} is missing")
            return default
    return node


def to_int(value: Any, key: str) -> int:
    """``int(value)``; a value that is no integer raises :class:`ConfigError` naming ``key``."""
    if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
        raise ConfigError(f"{key} must be an integer, got {value!r}")
    try:
        return int(value)
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"{key} must be an integer, got {value!r}") from None


def to_float(value: Any, key: str) -> float:
    """``float(value)``; a value that is no number raises :class:`ConfigError` naming ``key``."""
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{key} must be a number, got {value!r}") from None
    if isinstance(value, bool) or math.isnan(out):
        raise ConfigError(f"{key} must be a number, got {value!r}")
    return out


def to_fraction(value: Any, key: str) -> float:
    """``float(value)`` for a share or probability: a number in [0, 1], else :class:`ConfigError` naming ``key``."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value <= 1.0:
        raise ConfigError(f"{key} must be a number in [0, 1], got {value!r}")
    return float(value)


def cfg_int(cfg: Any, key: str, default: Any = _MISSING) -> int:
    """``int`` of the config value at the dotted ``key`` (``"data.workers"``); a value that is no
    integer raises :class:`ConfigError` naming the key and the value (not ``invalid literal for int()``)."""
    return to_int(_lookup(cfg, key, default), key)


def cfg_float(cfg: Any, key: str, default: Any = _MISSING) -> float:
    """``float`` of the config value at the dotted ``key``; errors name the key and the value."""
    return to_float(_lookup(cfg, key, default), key)


def check_number_fields(params: Mapping[str, Any], factory: Any, where: str) -> None:
    """Check the values of ``params`` given to ``factory`` (a class or function) for the parameters
    it annotates ``int`` or ``float`` (optionally ``| None``): one that is not a number raises
    :class:`ConfigError` naming ``where.<parameter>`` and the value. Values are not converted (so
    recorded parameters stay as given)."""
    try:
        sig = inspect.signature(factory)
    except (TypeError, ValueError):
        return
    for name, p in sig.parameters.items():
        if name not in params or p.annotation is inspect.Parameter.empty:
            continue
        ann = p.annotation if isinstance(p.annotation, str) else getattr(p.annotation, "__name__", str(p.annotation))
        kind = ann.replace(" ", "")
        value = params[name]
        if value is None and kind.endswith("|None"):
            continue
        if kind in ("int", "int|None"):
            to_int(value, f"{where}.{name}")
        elif kind in ("float", "float|None"):
            to_float(value, f"{where}.{name}")


def run_dir_of(cfg: Any) -> Path:
    """Where a job writes: ``cfg.run_dir`` when set (callers such as :mod:`kpd6d.workflow` give each
    stage its own folder), else Hydra's output folder when running under Hydra, else the cwd."""
    explicit = cfg.get("run_dir") if hasattr(cfg, "get") else getattr(cfg, "run_dir", None)
    if explicit:
        return Path(explicit)
    try:
        from hydra.core.hydra_config import HydraConfig

        if HydraConfig.initialized():
            return Path(HydraConfig.get().runtime.output_dir)
    except ImportError:  # pragma: no cover
        pass
    return Path(os.getcwd())


#: settings of earlier versions -> where they live now. Keys are dotted paths below a stage node;
#: ``{stage}`` in the text is the node the user wrote (``stage``, ``detector_stage`` or ``kpd_stage``).
RENAMED_STAGE_KEYS = {
    # detector stage: one trainer node and a recipe group (kpd6d.training)
    "recipe": "the detector_recipe config group: detector_recipe@{stage}=NAME (paper, fast, cpu_budget)",
    "recipes": "conf/detector_recipe/NAME.yaml ({stage}.optimizer, {stage}.scheduler, {stage}.trainer.max_epochs)",
    "max_epochs": "{stage}.trainer.max_epochs",
    "max_minutes": "{stage}.trainer.max_time (DD:HH:MM:SS, e.g. 00:00:14:00)",
    "accelerator": "{stage}.trainer.accelerator",
    "precision": "{stage}.trainer.precision",
    "val_every_n_epochs": "{stage}.trainer.check_val_every_n_epoch",
    "log_every_n_steps": "{stage}.trainer.log_every_n_steps",
    # KPD stage: one heatmap codec node (kpd6d.kpd.codec)
    "kpd.input_size": "{stage}.kpd.codec.input_size",
    "kpd.out_stride": "{stage}.kpd.codec.out_stride",
    "kpd.sigma": "{stage}.kpd.codec.sigma",
    "kpd.crop_scale": "{stage}.kpd.codec.crop_scale",
    "decoder": "{stage}.kpd.codec.decoder (decoder@{stage}.kpd.codec.decoder=NAME)",
    # one fallback dataset for kpd6d-train, beside data.root
    "generate": "data.generate (kpd6d-train; kpd6d-run: data.num_train, data.options, ...)",
    "kpd.generate": "data.generate (kpd6d-train; kpd6d-run: data.num_train, data.options, ...)",
}
_STAGE_NODES = ("stage", "detector_stage", "kpd_stage")


def _renamed(node: str, key: str) -> str | None:
    for old, new in RENAMED_STAGE_KEYS.items():
        if key == old or key.startswith(old + "."):
            return f"{node}.{old} is now {new.format(stage=node)}"
    return None


def check_stage_config(stage: Any, where: str = "stage") -> None:
    """Raise ``ValueError`` naming the new spelling when the stage node ``stage`` sets a setting of an
    earlier version (e.g. from an experiment file)."""
    found = []
    for old in RENAMED_STAGE_KEYS:
        node = stage
        for part in old.split("."):
            node = node.get(part) if hasattr(node, "get") else None
            if node is None:
                break
        if node is not None:
            found.append(_renamed(where, old))
    if found:
        raise ValueError("; ".join(found))


def renamed_overrides(overrides) -> list[str]:
    """For command-line overrides that spell a stage setting of an earlier version
    (``stage.max_minutes=14``, ``kpd_stage.kpd.input_size=64``, ``decoder@stage.decoder=argmax``):
    what each is called now."""
    out = []
    for arg in overrides:
        key = str(arg).split("=", 1)[0].lstrip("+~")
        if "@" in key:  # group@package: the package is the config path
            key = key.split("@", 1)[1]
        node, _, rest = key.partition(".")
        if node in _STAGE_NODES and rest:
            msg = _renamed(node, rest)
            if msg:
                out.append(msg)
    return out
