"""Object models and the procedural objects that are the library's embedded default."""

from kpd6d.objects.model import ModelError, ObjectModel, load_bop_models, load_models_info
from kpd6d.objects.procedural import PROCEDURAL_NAMES, procedural_objects

__all__ = [
    "PROCEDURAL_NAMES",
    "ModelError",
    "ObjectModel",
    "load_bop_models",
    "load_models_info",
    "procedural_objects",
]
