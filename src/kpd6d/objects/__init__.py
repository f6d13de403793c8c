"""Object models and the procedural objects that are the library's embedded default."""

from kpd6d.objects.model import ModelError, ObjectModel, load_bop_models, load_models_info

__all__ = ["ModelError", "ObjectModel", "load_bop_models", "load_models_info"]
