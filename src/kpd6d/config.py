"""Helpers shared by the config-driven entry points: plain values and the run folder."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from kpd6d.io import to_plain  # lives with the file writers; re-exported here

__all__ = ["run_dir_of", "to_plain"]


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
