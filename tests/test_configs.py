"""conf/ mirrors the registries one to one, and every top-level config composes."""

from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from kpd6d.paths import config_dir
from kpd6d.registry import REGISTRIES, build_from_cfg

CONF = config_dir()
# config group -> registry (the group names are the keys of kpd6d.registry.REGISTRIES)
GROUPS = sorted(REGISTRIES)
CHEAP_TO_BUILD = {"pnp", "decoder", "symmetry", "designator"}


def _group_files(group: str) -> list[Path]:
    return sorted((CONF / group).glob("*.yaml"))


@pytest.mark.parametrize("group", GROUPS)
def test_group_names_registry_entries_one_to_one(group):
    registry = REGISTRIES[group]
    files = _group_files(group)
    assert files, f"conf/{group}/ is empty"
    named = {}
    for f in files:
        cfg = OmegaConf.load(f)
        assert "name" in cfg, f"{f} has no 'name'"
        assert cfg.name in registry, f"{f}: name {cfg.name!r} is not a {registry.kind}; known: {registry.names()}"
        named.setdefault(cfg.name, []).append(f.stem)
    # every registry entry has a config file named after it
    for entry in registry.names():
        assert (CONF / group / f"{entry}.yaml").is_file(), f"registry entry {entry!r} has no conf/{group}/{entry}.yaml"
    # a file named after an entry configures that entry
    for f in files:
        if f.stem in registry:
            assert OmegaConf.load(f).name == f.stem, f"{f} is named after entry {f.stem!r} but configures another"


@pytest.mark.parametrize("group", sorted(CHEAP_TO_BUILD))
def test_group_configs_build_through_registry(group):
    for f in _group_files(group):
        obj = build_from_cfg(REGISTRIES[group], OmegaConf.load(f))
        assert obj is not None, f


@pytest.mark.parametrize("name", sorted(p.stem for p in CONF.glob("*.yaml")))
def test_top_level_configs_compose(name):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name=name)
    assert cfg is not None
    OmegaConf.to_container(cfg, resolve=False)


def test_unknown_group_option_is_a_clear_error():
    from hydra import compose, initialize_config_dir
    from hydra.errors import MissingConfigException

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        with pytest.raises(MissingConfigException) as exc:
            compose(config_name="train", overrides=["stage=nonexistent"])
    assert "nonexistent" in str(exc.value) and "kpd" in str(exc.value)
