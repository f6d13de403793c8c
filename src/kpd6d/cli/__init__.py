"""Command-line entry points (Hydra apps over the configs in ``conf/``)."""
