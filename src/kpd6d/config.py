"""Helpers shared by the config-driven entry points: where the Hydra configs are, plain values and
the run folder."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from kpd6d.io import to_plain  # lives with the file writers; re-exported here

__all__ = ["config_dir", "run_dir_of", "to_plain"]


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
