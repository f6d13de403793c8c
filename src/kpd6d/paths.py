"""Where the library finds its Hydra configs (inside the wheel, or ``conf/`` of a source checkout)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["config_dir"]


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
