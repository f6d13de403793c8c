"""Run a function as a Hydra app over the library's ``conf/`` (works from a wheel and a checkout)."""

from __future__ import annotations

from collections.abc import Callable

from kpd6d.config import config_dir


def hydra_main(config_name: str) -> Callable[[Callable], Callable[[], None]]:
    """Decorator: ``@hydra_main("train")`` makes ``fn(cfg)`` a console-script ``main()``."""
    import hydra

    def deco(fn: Callable) -> Callable[[], None]:
        wrapped = hydra.main(config_path=str(config_dir()), config_name=config_name, version_base="1.3")(fn)
        wrapped.__doc__ = fn.__doc__
        return wrapped

    return deco
