"""Symmetry handlers (``SYMMETRIES``: ``none``, ``rotational``, ``discrete``, ``continuous``, ``auto``).

See :mod:`kpd6d.symmetry.handlers` for canonicalisation of poses and :mod:`kpd6d.symmetry.auto` for
the detection of an object's rotational symmetries from its mesh.
"""

from kpd6d.symmetry.auto import AutoSymmetry
from kpd6d.symmetry.handlers import (
    ContinuousSymmetry,
    DiscreteSymmetry,
    NoSymmetry,
    RotationalSymmetry,
    axis_angle_offset,
    handler_for_model,
    least_motion_reference,
    reference_direction,
)

__all__ = [
    "AutoSymmetry",
    "ContinuousSymmetry",
    "DiscreteSymmetry",
    "NoSymmetry",
    "RotationalSymmetry",
    "axis_angle_offset",
    "handler_for_model",
    "least_motion_reference",
    "reference_direction",
]
