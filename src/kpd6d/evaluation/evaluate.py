"""Moved to :mod:`kpd6d.evaluation.runner`; this re-export keeps the old import path working for now."""

from kpd6d.evaluation.runner import (  # noqa: F401
    ADD_THRESHOLDS,
    PX_THRESHOLDS,
    compute_metrics,
    eval_instances,
    evaluate,
    match_predictions,
)
