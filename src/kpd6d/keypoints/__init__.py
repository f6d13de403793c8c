"""Keypoint designation (``DESIGNATORS``: ``sift``, ``bbox_corners``, ``fps``) and keypoint JSON I/O."""

from kpd6d.keypoints.io import (
    KeypointFile,
    KeypointFileError,
    load_keypoints,
    model_fingerprint,
    read_keypoint_file,
    save_keypoints,
)

__all__ = [
    "KeypointFile",
    "KeypointFileError",
    "load_keypoints",
    "model_fingerprint",
    "read_keypoint_file",
    "save_keypoints",
]
