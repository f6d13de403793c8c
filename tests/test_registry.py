"""kpd6d.registry: Registry behaviour, build_from_cfg, lazy built-ins and kpd6d.plugins entry points."""

from __future__ import annotations

import sys
import types
from importlib import metadata

import pytest
from omegaconf import OmegaConf

from kpd6d import registry as reg
from kpd6d.registry import PNP_SOLVERS, REGISTRIES, SYMMETRIES, Registry, UnknownNameError, build_from_cfg


def _fresh(modules=()):
    return Registry("widget", modules)


def test_register_build_and_names():
    r = _fresh()

    @r.register("double")
    def double(x: int = 1):
        return 2 * x

    @r.register
    def triple(x: int = 1):
        return 3 * x

    @r.register()
    class Box:
        def __init__(self, size: float = 1.0):
            self.size = size

    assert r.names() == ["Box", "double", "triple"]
    assert list(r) == r.names() and len(r) == 3 and "double" in r and "nope" not in r
    assert r.build("double", x=5) == 10
    assert r.build("triple") == 3
    assert r.build("Box", size=2.5).size == 2.5
    assert r.get("double") is double
    assert "double" in repr(r)


def test_unknown_name_lists_known_names():
    r = _fresh()
    r.add("alpha", dict)
    r.add("beta", dict)
    with pytest.raises(UnknownNameError) as exc:
        r.build("gamma")
    msg = str(exc.value)
    assert "gamma" in msg and "alpha" in msg and "beta" in msg and "widget" in msg
    assert isinstance(exc.value, KeyError)  # still a KeyError for callers that catch that


def test_unknown_parameter_names_accepted_ones():
    r = _fresh()
    r.add("f", lambda a=1, b=2: a + b)
    with pytest.raises(TypeError, match=r"unknown parameter\(s\) c.*accepts: a, b"):
        r.build("f", c=3)
    r.add("g", lambda **kw: kw)
    assert r.build("g", anything=1) == {"anything": 1}  # **kwargs factories take anything


def test_duplicate_and_invalid_registrations():
    r = _fresh()

    def f():
        return 1

    def g():
        return 2

    r.add("x", f)
    r.add("x", f)  # the same factory again is harmless
    with pytest.raises(ValueError, match="already registered"):
        r.add("x", g)
    r.add("x", g, override=True)
    assert r.build("x") == 2
    with pytest.raises(ValueError, match="non-empty string"):
        r.add("", f)
    with pytest.raises(TypeError, match="not callable"):
        r.add("y", 42)


def test_override_wins_whichever_registers_first():
    """A plugin's override=True entry is not undone by the built-in registering later."""
    r = _fresh()

    def plugin_version():
        return "plugin"

    def builtin_version():
        return "builtin"

    r.add("thing", plugin_version, override=True)
    r.add("thing", builtin_version)  # e.g. the built-in module imported after the plugins
    assert r.build("thing") == "plugin"


def test_build_from_cfg_dict_and_dictconfig():
    r = _fresh()
    r.add("lin", lambda a=1.0, b=0.0: (a, b))
    assert build_from_cfg(r, {"name": "lin", "a": 2.0}) == (2.0, 0.0)
    assert build_from_cfg(r, OmegaConf.create({"name": "lin", "a": 3.0, "b": "${a}"})) == (3.0, 3.0)
    assert build_from_cfg(r, {"name": "lin", "a": 2.0}, a=5.0) == (5.0, 0.0)  # overrides win
    with pytest.raises(KeyError, match=r"no .name. key.*known widgets: lin"):
        build_from_cfg(r, {"a": 1})
    with pytest.raises(TypeError, match="mapping"):
        build_from_cfg(r, ["lin"])
    with pytest.raises(UnknownNameError, match="known widgets: lin"):
        build_from_cfg(r, {"name": "nope"})


def test_builtin_modules_are_imported_lazily_and_failures_stay_visible(monkeypatch):
    r = Registry("gadget", ("fake_kpd6d_builtins",))
    calls = []

    def exec_module():
        calls.append(1)
        if len(calls) == 1:
            raise ImportError("optional dependency missing")
        r.add("g1", dict)

    class Finder:
        @staticmethod
        def find_spec(name, path=None, target=None):
            if name != "fake_kpd6d_builtins":
                return None
            from importlib.machinery import ModuleSpec

            loader = types.SimpleNamespace(create_module=lambda spec: None,
                                           exec_module=lambda mod: exec_module())
            return ModuleSpec(name, loader)

    monkeypatch.setattr(sys, "meta_path", [Finder(), *sys.meta_path])
    monkeypatch.setattr(reg, "_plugins_loaded", True)
    assert not calls  # nothing imported at construction
    with pytest.raises(ImportError, match="optional dependency missing"):
        r.names()
    assert r.names() == ["g1"]  # the second query retries instead of showing an empty registry
    sys.modules.pop("fake_kpd6d_builtins", None)


class _FakeEntryPoint:
    def __init__(self, name, value, obj=None, error=None):
        self.name, self.value, self._obj, self._error = name, value, obj, error

    def load(self):
        if self._error:
            raise self._error
        return self._obj


def _patch_entry_points(monkeypatch, eps):
    seen = []

    def entry_points(**kw):
        seen.append(kw)
        return [ep for ep in eps if kw.get("group") == reg.PLUGIN_GROUP]

    monkeypatch.setattr(metadata, "entry_points", entry_points)
    monkeypatch.setattr(reg, "_plugins_loaded", False)
    return seen


def test_load_plugins_module_and_callable_entry_points(monkeypatch):
    r = _fresh()
    module = types.ModuleType("my_plugin_module")  # a module entry point registers on import
    r.add("from_module", dict)

    def register_more():
        r.add("from_callable", list)

    seen = _patch_entry_points(monkeypatch, [
        _FakeEntryPoint("mod", "my_plugin_module", module),
        _FakeEntryPoint("fn", "my_plugin:register_more", register_more),
    ])
    assert reg.load_plugins() == ["mod", "fn"]
    assert seen == [{"group": "kpd6d.plugins"}]
    assert r.names() == ["from_callable", "from_module"]
    assert reg.load_plugins() == []  # only once


def test_plugin_adds_a_pnp_solver_through_the_real_registry(monkeypatch):
    PNP_SOLVERS.names()  # built-ins first, as in a session that already used the registry

    class MySolver:
        def __init__(self, gain: float = 1.0):
            self.gain = gain

    def register():
        PNP_SOLVERS.add("my_solver", MySolver, override=True)

    _patch_entry_points(monkeypatch, [_FakeEntryPoint("acme", "acme.pnp:register", register)])
    try:
        assert reg.load_plugins() == ["acme"]
        assert "my_solver" in PNP_SOLVERS.names() and "epnp" in PNP_SOLVERS.names()
        assert build_from_cfg(PNP_SOLVERS, {"name": "my_solver", "gain": 2.0}).gain == 2.0
    finally:
        PNP_SOLVERS._factories.pop("my_solver", None)
        PNP_SOLVERS._overrides.discard("my_solver")


def test_broken_plugin_names_itself_and_is_retried(monkeypatch):
    _patch_entry_points(monkeypatch, [_FakeEntryPoint("bad", "bad_pkg.mod", error=ModuleNotFoundError("No module named 'bad_pkg'"))])
    with pytest.raises(ImportError, match=r"'bad' \(bad_pkg.mod\) failed to load.*bad_pkg"):
        reg.load_plugins()
    with pytest.raises(ImportError, match="'bad'"):
        reg.load_plugins()  # still loud on the next attempt


def test_the_ten_registries_exist():
    assert set(REGISTRIES) == {"designator", "detector", "backbone", "head", "box_augment", "decoder", "codec",
                               "pnp", "refiner"}  # the conf/ groups
    assert isinstance(SYMMETRIES, Registry)  # the tenth, without a group (handlers follow models_info)
    from kpd6d.kpd.box_augment import BoxJitter
    from kpd6d.kpd.heads import FPNHead
    from kpd6d.registry import BOX_AUGMENTS, HEADS

    assert HEADS.names() == ["deconv", "fpn"] and HEADS.get("fpn") is FPNHead
    assert BOX_AUGMENTS.names() == ["jitter", "none", "pgpg"]
    assert isinstance(build_from_cfg(BOX_AUGMENTS, {"name": "jitter", "shift": 0.2}), BoxJitter)
    assert REGISTRIES["pnp"] is PNP_SOLVERS
    assert {"epnp", "iterative", "sqpnp", "epnp_ransac", "dlt", "weighted_lm"} <= set(PNP_SOLVERS.names())
