"""conf/ mirrors the registries one to one, and every top-level config composes."""

from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from kpd6d.config import config_dir
from kpd6d.registry import REGISTRIES, build_from_cfg

CONF = config_dir()
# config group -> registry (the group names are the keys of kpd6d.registry.REGISTRIES)
GROUPS = sorted(REGISTRIES)
CHEAP_TO_BUILD = {"pnp", "decoder", "codec", "designator"}


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


@pytest.mark.parametrize("group", GROUPS)
def test_entry_configs_state_the_entry_defaults(group):
    """conf/<group>/<entry>.yaml names only parameters of <entry> and gives each the value the code
    defaults to, so `build(name)` in a notebook and `group=<entry>` in Hydra build the same thing
    (variants such as centernet_tiny.yaml are files named otherwise)."""
    import inspect

    from kpd6d.config import to_plain

    registry = REGISTRIES[group]
    for entry in registry.names():
        cfg = OmegaConf.to_container(OmegaConf.load(CONF / group / f"{entry}.yaml"))
        cfg.pop("name")
        params = inspect.signature(registry.get(entry)).parameters
        takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
        unknown = set(cfg) - set(params)
        assert takes_any or not unknown, f"conf/{group}/{entry}.yaml: {sorted(unknown)} are not parameters of {entry}"
        differ = {k: (v, to_plain(params[k].default)) for k, v in cfg.items()
                  if k in params and params[k].default is not inspect.Parameter.empty and to_plain(params[k].default) != v}
        assert not differ, f"conf/{group}/{entry}.yaml differs from the code's defaults (yaml, code): {differ}"


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


def test_one_pnp_setting_and_one_fallback_dataset_per_tool():
    """kpd6d-run: the KPD's validation PnP and top-l are the run's ``pnp`` and ``select.top_l`` (for
    every experiment); kpd6d-train: the PnP is the pnp group at ``stage.kpd.pnp`` and the fallback
    dataset is ``data.generate`` for both stages; the old ``generate`` spellings name the new one."""
    from hydra import compose, initialize_config_dir

    from kpd6d.config import check_stage_config, renamed_overrides

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        for exp in sorted(p.stem for p in (CONF / "experiment").glob("*.yaml")):
            cfg = compose(config_name="run", overrides=[f"experiment={exp}", "objects.models_dir=m",
                                                        "evaluate.data_root=d", "pnp=epnp", "select.top_l=7"])
            kpd = OmegaConf.to_container(cfg.kpd_stage.kpd, resolve=True)
            assert kpd["pnp"] == OmegaConf.to_container(cfg.pnp, resolve=True) and kpd["top_l"] == 7, exp
        cfg = compose(config_name="train", overrides=["stage=kpd", "pnp@stage.kpd.pnp=epnp_ransac"])
        assert cfg.stage.kpd.pnp.name == "epnp_ransac" and "generate" not in cfg.stage.kpd
        assert cfg.data.generate.num_train > 0
        assert "generate" not in compose(config_name="train", overrides=["stage=detector"]).stage
    assert renamed_overrides(["stage.kpd.generate.num_train=5", "stage.generate.obj_ids=[1]"]) == [
        "stage.kpd.generate is now data.generate (kpd6d-train; kpd6d-run: data.num_train, data.options, ...)",
        "stage.generate is now data.generate (kpd6d-train; kpd6d-run: data.num_train, data.options, ...)"]
    with pytest.raises(ValueError, match=r"data\.generate"):
        check_stage_config(OmegaConf.create({"kpd": {"generate": {"num_train": 3}}}))


def test_no_data_and_no_generate_node_is_a_clear_error(tmp_path):
    from kpd6d.synth.prepare import prepare_data

    with pytest.raises(ValueError, match=r"data\.generate"):
        prepare_data(None, tmp_path, None, ["train", "val"])
