"""Helpers shared by the config-driven entry points: plain values, typed values naming their key,
and the run folder."""

from __future__ import annotations

import inspect
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from kpd6d.io import to_plain  # lives with the file writers; re-exported here

__all__ = ["ConfigError", "cfg_float", "cfg_int", "check_number_fields", "run_dir_of", "to_float", "to_int", "to_plain"]

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
