"""Moved to :mod:`kpd6d.pnp.top_l`; this re-export keeps the old import path working for now."""

from kpd6d.pnp.top_l import solve_top_l, top_l, top_l_mask  # noqa: F401
