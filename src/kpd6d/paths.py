"""Moved to :mod:`kpd6d.config`; this re-export keeps the old import path working for now."""

from kpd6d.config import config_dir  # noqa: F401
