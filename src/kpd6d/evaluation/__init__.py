"""Pose evaluation: error functions (:mod:`.errors`), recall / AUC / accuracies (:mod:`.recall`),
and BOP19 scoring built on them (:mod:`.bop19`, :mod:`.results_io`)."""

from kpd6d.evaluation.errors import (
    add_error,
    adds_error,
    keypoint_errors,
    mspd_error,
    mssd_error,
    proj2d_error,
    rotation_error,
    symmetry_transforms,
    translation_error,
)
from kpd6d.evaluation.recall import add_s_accuracy, auc, proj2d_accuracy, recall_at

__all__ = [
    "add_error",
    "add_s_accuracy",
    "adds_error",
    "auc",
    "keypoint_errors",
    "mspd_error",
    "mssd_error",
    "proj2d_accuracy",
    "proj2d_error",
    "recall_at",
    "rotation_error",
    "symmetry_transforms",
    "translation_error",
]
