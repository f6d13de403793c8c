"""kpd6d: 6D object pose from one RGB image by localizing designated surface keypoints.

Stages: detector -> crop -> keypoint detector (heatmaps) -> top-l confident keypoints -> PnP.
Conventions (BOP): millimetres, OpenCV camera (x right, y down, z forward), a pose maps model
to camera, x_c = R x_m + t. See docs/data.md.
"""

__version__ = "0.1.0"
