"""Run a function as a Hydra app over the library's ``conf/`` (works from a wheel and a checkout)."""

from __future__ import annotations

import sys
from collections.abc import Callable

from kpd6d.config import config_dir


def hydra_main(config_name: str) -> Callable[[Callable], Callable[[], None]]:
    """Decorator: ``@hydra_main("train")`` makes ``fn(cfg)`` a console-script ``main()``."""
    import hydra

    def deco(fn: Callable) -> Callable[[], None]:
        wrapped = hydra.main(config_path=str(config_dir()), config_name=config_name, version_base="1.3")(fn)
        wrapped.__doc__ = fn.__doc__

        def main() -> None:
            _reject_renamed_overrides(sys.argv[1:])
            wrapped()

        main.__doc__ = fn.__doc__
        return main

    return deco


def _reject_renamed_overrides(args: list[str]) -> None:
    """Overrides of settings that moved (Hydra would only say "not in struct"): exit naming the new spelling."""
    from kpd6d.config import renamed_overrides

    moved = renamed_overrides(args)
    if moved:
        raise SystemExit("error: " + "; ".join(moved))
