"""Plugin registries: one small generic :class:`Registry` and the ten registries of the library.

A registry maps a name to a factory. ``REGISTRY.build(name, **params)`` calls the factory; an
unknown name raises :class:`UnknownNameError` listing the known names. Each Hydra config group in
``conf/`` (e.g. ``conf/pnp/epnp.yaml``) holds ``name: <registry entry>`` plus the factory's
parameters, and :func:`build_from_cfg` builds it.

Entries come from the library's own modules (imported lazily on first use, so that importing
``kpd6d.registry`` stays cheap) and from third-party packages through the ``kpd6d.plugins``
entry-point group: each entry point names a module (or a callable taking no arguments) whose import
registers its entries. See docs/plugins.md.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable, Iterator, Mapping
from importlib import metadata
from typing import Any

__all__ = [
    "BACKBONES",
    "BOX_AUGMENTS",
    "CODECS",
    "DECODERS",
    "DESIGNATORS",
    "DETECTORS",
    "HEADS",
    "PNP_SOLVERS",
    "REFINERS",
    "REGISTRIES",
    "SYMMETRIES",
    "Registry",
    "UnknownNameError",
    "build_from_cfg",
    "load_plugins",
]

PLUGIN_GROUP = "kpd6d.plugins"


class UnknownNameError(KeyError):
    """An unknown registry name; the message lists the known names."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0])


class Registry:
    """Name -> factory mapping with a ``register`` decorator.

    ``modules`` are the library modules that register this registry's built-in entries; they are
    imported the first time the registry is queried.
    """

    def __init__(self, kind: str, modules: tuple[str, ...] = ()) -> None:
        self.kind = kind
        self._modules = modules
        self._factories: dict[str, Callable[..., Any]] = {}
        self._overrides: set[str] = set()  # names registered with override=True (e.g. by plugins)
        self._loaded = False

    # -- registration -------------------------------------------------------------------------
    def register(self, name: str | None = None, *, override: bool = False) -> Callable:
        """Decorator: ``@REG.register("name")`` (or bare ``@REG.register()``, using ``__name__``)."""

        def deco(factory: Callable[..., Any]) -> Callable[..., Any]:
            key = name or factory.__name__
            self.add(key, factory, override=override)
            return factory

        if callable(name):  # used as @REG.register without parentheses
            factory, name = name, None
            return deco(factory)
        return deco

    def add(self, name: str, factory: Callable[..., Any], *, override: bool = False) -> None:
        if not isinstance(name, str) or not name:
            raise ValueError(f"{self.kind} registry: entry name must be a non-empty string, got {name!r}")
        if not callable(factory):
            raise TypeError(f"{self.kind} registry: factory for {name!r} is not callable: {factory!r}")
        if not override and name in self._overrides:
            # an override=True entry (typically a plugin's) wins over a plain registration of the
            # same name, whichever comes first: plugins may load before a registry's built-ins
            return
        if override:
            self._overrides.add(name)
        if (name in self._factories and not override and self._factories[name] is not factory
                and _qualname(self._factories[name]) != _qualname(factory)):  # same qualname: a re-executed module
            raise ValueError(
                f"{self.kind} registry: {name!r} is already registered by "
                f"{_qualname(self._factories[name])}; pass override=True to replace it"
            )
        self._factories[name] = factory

    # -- lookup -------------------------------------------------------------------------------
    def _ensure_loaded(self) -> None:
        if self._loaded:
            return
        self._loaded = True  # set first: the modules below query this registry while registering
        try:
            for mod in self._modules:
                importlib.import_module(mod)
            load_plugins()
        except BaseException:
            # keep the failure visible on the next query too (not a silently empty registry)
            self._loaded = False
            raise

    def names(self) -> list[str]:
        self._ensure_loaded()
        return sorted(self._factories)

    def get(self, name: str) -> Callable[..., Any]:
        self._ensure_loaded()
        try:
            return self._factories[name]
        except KeyError:
            known = ", ".join(sorted(self._factories)) or "(none)"
            raise UnknownNameError(f"unknown {self.kind} {name!r}; known {self.kind}s: {known}") from None

    def build(self, name: str, **kwargs: Any) -> Any:
        factory = self.get(name)
        try:
            sig = inspect.signature(factory)
        except (TypeError, ValueError):  # builtins without signatures
            return factory(**kwargs)
        accepts_any = any(p.kind is p.VAR_KEYWORD for p in sig.parameters.values())
        if not accepts_any:
            unknown = sorted(set(kwargs) - set(sig.parameters))
            if unknown:
                allowed = ", ".join(p for p in sig.parameters if p != "self") or "(none)"
                raise TypeError(
                    f"{self.kind} {name!r} got unknown parameter(s) {', '.join(unknown)}; "
                    f"it accepts: {allowed}"
                )
        return factory(**kwargs)

    def __contains__(self, name: object) -> bool:
        self._ensure_loaded()
        return name in self._factories

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def __len__(self) -> int:
        return len(self.names())

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}, names={self.names()})"


def _qualname(obj: Any) -> str:
    return f"{getattr(obj, '__module__', '?')}.{getattr(obj, '__qualname__', repr(obj))}"


DESIGNATORS = Registry("designator", ("kpd6d.keypoints.designators",))
DETECTORS = Registry("detector", ("kpd6d.detection.detectors",))
BACKBONES = Registry("backbone", ("kpd6d.kpd.backbones",))
HEADS = Registry("KPD head", ("kpd6d.kpd.heads",))
BOX_AUGMENTS = Registry("box augmentation", ("kpd6d.kpd.box_augment",))
DECODERS = Registry("decoder", ("kpd6d.kpd.decoders",))
CODECS = Registry("codec", ("kpd6d.kpd.codec",))
PNP_SOLVERS = Registry("PnP solver", ("kpd6d.pnp",))
SYMMETRIES = Registry("symmetry handler", ("kpd6d.symmetry",))
REFINERS = Registry("pose refiner", ("kpd6d.refinement",))

# config group in conf/ -> the registry its files build. SYMMETRIES has no group: an object's handler
# follows from its models_info symmetries (kpd6d.symmetry.handler_for_model).
REGISTRIES: dict[str, Registry] = {
    "designator": DESIGNATORS,
    "detector": DETECTORS,
    "backbone": BACKBONES,
    "head": HEADS,
    "box_augment": BOX_AUGMENTS,
    "decoder": DECODERS,
    "codec": CODECS,
    "pnp": PNP_SOLVERS,
    "refiner": REFINERS,
}

_plugins_loaded = False


def load_plugins() -> list[str]:
    """Import every ``kpd6d.plugins`` entry point once; returns the entry-point names loaded."""
    global _plugins_loaded
    if _plugins_loaded:
        return []
    _plugins_loaded = True
    loaded = []
    for ep in metadata.entry_points(group=PLUGIN_GROUP):
        try:
            obj = ep.load()
            if callable(obj) and not inspect.ismodule(obj):
                obj()
        except Exception as exc:  # say which plugin broke; the next registry query raises again
            _plugins_loaded = False
            raise ImportError(f"kpd6d plugin entry point {ep.name!r} ({ep.value}) failed to load: {exc}") from exc
        loaded.append(ep.name)
    return loaded


def build_from_cfg(registry: Registry, cfg: Mapping[str, Any] | Any, **overrides: Any) -> Any:
    """Build ``registry`` entry ``cfg['name']`` with the remaining keys as parameters.

    ``cfg`` is a mapping or an OmegaConf ``DictConfig`` (converted to plain containers);
    ``overrides`` take precedence over the config's keys.
    """
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            cfg = OmegaConf.to_container(cfg, resolve=True)
    except ImportError:  # pragma: no cover - omegaconf is a dependency
        pass
    if not isinstance(cfg, Mapping):
        raise TypeError(f"{registry.kind} config must be a mapping with a 'name' key, got {type(cfg).__name__}")
    params = dict(cfg)
    if "name" not in params:
        raise KeyError(
            f"{registry.kind} config has no 'name' key (keys: {sorted(params)}); "
            f"known {registry.kind}s: {', '.join(registry.names())}"
        )
    name = params.pop("name")
    params.update(overrides)
    return registry.build(name, **params)
