"""Moved to :mod:`kpd6d.detection.metrics`; this re-export keeps the old import path working for now."""

from kpd6d.detection.metrics import DetectionEvaluator, evaluate_detector  # noqa: F401
