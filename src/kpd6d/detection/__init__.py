"""Detector stage: boxes + object ids + scores per image (``DETECTORS``: centernet, fcos, faster_rcnn,
oracle). See docs/detection.md."""

from kpd6d.detection.detections import DetectionInputError, Detections, Detector, check_images
from kpd6d.detection.detectors import build_detector, load_detector, save_detector

__all__ = [
    "DetectionInputError",
    "Detections",
    "Detector",
    "build_detector",
    "check_images",
    "load_detector",
    "save_detector",
]
