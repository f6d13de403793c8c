"""Helpers shared by the config-driven entry points: plain values and the run folder."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["run_dir_of", "to_plain"]


def to_plain(x: Any) -> Any:
    """OmegaConf nodes, numpy arrays / scalars, mappings and sequences -> plain Python values
    (so hyper-parameters pickle, and JSON / YAML files are written cleanly)."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf

        if isinstance(x, (DictConfig, ListConfig)):
            return OmegaConf.to_container(x, resolve=True)
    except ImportError:  # pragma: no cover - omegaconf is a dependency
        pass
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, Mapping):
        return {k: to_plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_plain(v) for v in x]
    return x


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
