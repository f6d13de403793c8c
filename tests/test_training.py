"""kpd6d.training: the one optimizer/scheduler schema, the detector recipes as a config group, the
shared trainer (best.ckpt + last.ckpt every epoch, resume) and metrics.json."""

from __future__ import annotations

import json
import math

import pytest
import torch
from hydra import compose, initialize_config_dir

from kpd6d.config import config_dir
from kpd6d.training import (
    build_optimizer,
    build_scheduler,
    build_trainer,
    check_optimizer,
    configure_optimization,
    fit,
    resolve_scheduler,
    write_metrics,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _params():
    return [torch.nn.Parameter(torch.zeros(3))]


def _lrs(optimizer, sched, steps):
    out = []
    for _ in range(steps):
        out.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        sched["scheduler"].step()
    return out


def test_optimizer_schema_builds_torch_optimizers_and_names_bad_settings():
    opt = build_optimizer(_params(), {"name": "sgd", "lr": 0.1, "momentum": 0.9, "weight_decay": 5e-4})
    assert isinstance(opt, torch.optim.SGD)
    g = opt.param_groups[0]
    assert (g["lr"], g["momentum"], g["weight_decay"]) == (0.1, 0.9, 5e-4)
    assert isinstance(build_optimizer(_params(), None), torch.optim.Adam)  # default: adam, lr 1e-3
    assert build_optimizer(_params(), None).param_groups[0]["lr"] == 1e-3
    assert isinstance(build_optimizer(_params(), {"name": "AdamW", "lr": 2e-3}), torch.optim.AdamW)
    # parameter groups keep their own learning rates (finetune.param_groups)
    groups = [{"params": _params(), "lr": 1e-3}, {"params": _params(), "lr": 5e-4}]
    assert [g["lr"] for g in build_optimizer(groups, {"name": "adam", "lr": 1e-3}).param_groups] == [1e-3, 5e-4]
    with pytest.raises(ValueError, match="unknown optimizer 'lion'; known: adam, adamw, rmsprop, sgd"):
        build_optimizer(_params(), {"name": "lion"})
    with pytest.raises(ValueError, match=r"unknown optimizer setting\(s\) \['momentum'\] for 'adam'"):
        check_optimizer({"name": "adam", "momentum": 0.9})


def test_scheduler_schema_values():
    # torch's step schedule, per epoch
    opt = build_optimizer(_params(), {"name": "sgd", "lr": 1.0})
    s = build_scheduler(opt, {"name": "step", "step_size": 2, "gamma": 0.1})
    assert s["interval"] == "epoch" and _lrs(opt, s, 5) == pytest.approx([1.0, 1.0, 0.1, 0.1, 0.01])
    # warm-up then constant, per step
    opt = build_optimizer(_params(), {"name": "sgd", "lr": 1.0})
    s = build_scheduler(opt, {"name": "constant", "warmup_steps": 4})
    assert s["interval"] == "step" and _lrs(opt, s, 6) == pytest.approx([0.25, 0.5, 0.75, 1.0, 1.0, 1.0])
    # warm-up + cosine over the run's steps, asked for only when needed
    opt = build_optimizer(_params(), {"name": "sgd", "lr": 1.0})
    asked = []
    s = build_scheduler(opt, {"name": "cosine_steps", "warmup_steps": 0, "min_factor": 0.0},
                        total_steps=lambda: asked.append(1) or 4)
    assert asked == [1] and s["interval"] == "step"
    assert _lrs(opt, s, 5) == pytest.approx([1.0, 0.5 * (1 + math.cos(math.pi / 4)), 0.5, 0.5 * (1 + math.cos(3 * math.pi / 4)), 0.0])
    # an unknown run length (max_epochs=-1 under max_time) does not crash the schedule
    opt = build_optimizer(_params(), {"name": "sgd", "lr": 1.0})
    assert build_scheduler(opt, {"name": "cosine_steps"}, total_steps=float("inf"))["scheduler"].lr_lambdas[0].total_steps > 0
    assert build_scheduler(opt, None) is None
    assert configure_optimization(_params(), {"name": "sgd", "lr": 1.0}, None).__class__ is torch.optim.SGD
    with pytest.raises(ValueError, match="unknown scheduler 'poly'"):
        build_scheduler(opt, {"name": "poly"})
    with pytest.raises(ValueError, match=r"scheduler constant: unknown option\(s\) \['min_factor'\]"):
        build_scheduler(opt, {"name": "constant", "min_factor": 0.1})
    with pytest.raises(ValueError, match="budget_s"):
        build_scheduler(opt, {"name": "cosine_time"})


def test_resolve_scheduler_takes_the_budget_from_trainer_max_time():
    assert resolve_scheduler({"name": "cosine_time", "warmup_steps": 5}, {"max_time": "00:00:02:30"}) == \
        {"name": "cosine_time", "warmup_steps": 5, "budget_s": 150.0}
    assert resolve_scheduler({"name": "step", "step_size": 3}, {}) == {"name": "step", "step_size": 3}
    assert resolve_scheduler(None, {}) is None
    with pytest.raises(ValueError, match=r"detector_stage\.trainer\.max_time"):
        resolve_scheduler({"name": "cosine_time"}, {"max_time": None}, where="detector_stage")


def test_legacy_detector_optimizer_converts_to_the_same_training():
    from kpd6d.detection.module import legacy_optimization

    assert legacy_optimization({"name": "sgd", "lr": 1e-3, "momentum": 0.9, "weight_decay": 5e-4, "schedule": "step",
                                "step_epochs": 100, "gamma": 0.1, "warmup_steps": 0}) == \
        ({"name": "sgd", "lr": 1e-3, "momentum": 0.9, "weight_decay": 5e-4},
         {"name": "step", "step_size": 100, "gamma": 0.1})
    # adam / adamw never took momentum; the default weight decay applied
    assert legacy_optimization({"name": "adamw", "lr": 2e-3, "schedule": "cosine", "warmup_steps": 100}) == \
        ({"name": "adamw", "lr": 2e-3, "weight_decay": 5e-4},
         {"name": "cosine_steps", "warmup_steps": 100, "min_factor": 0.02})
    assert legacy_optimization({"name": "adamw", "schedule": "cosine_time", "minutes": 2.5})[1]["budget_s"] == 150.0
    with pytest.raises(ValueError, match=r"optimizer\.minutes > 0"):
        legacy_optimization({"schedule": "cosine_time"})


def _compose(name, *overrides):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose(name, overrides=list(overrides))


@pytest.mark.parametrize("recipe, opt_cls, sched_name, epochs", [
    ("paper", torch.optim.SGD, "step", 300), ("fast", torch.optim.AdamW, "cosine_steps", 30),
    ("cpu_budget", torch.optim.AdamW, "cosine_time", 1000)])
def test_detector_recipes_are_a_config_group(recipe, opt_cls, sched_name, epochs):
    from kpd6d.detection.module import DetectorModule

    cfg = _compose("train", "stage=detector", f"detector_recipe@stage={recipe}", "stage.trainer.max_time=00:00:01:00")
    st = cfg.stage
    assert st.scheduler.name == sched_name and st.trainer.max_epochs == epochs
    assert st.trainer.devices == 1 and st.trainer.num_sanity_val_steps == 0  # the stage's own trainer settings
    sched = resolve_scheduler(st.scheduler, st.trainer)
    module = DetectorModule({"name": "centernet", "obj_ids": [1], "backbone": "resnet10t", "input_size": [64, 48]},
                            optimizer=dict(st.optimizer), scheduler=sched)
    out = configure_optimization([p for p in module.parameters() if p.requires_grad], module.opt_cfg, module.sched_cfg,
                                 total_steps=1000)
    assert type(out["optimizer"]) is opt_cls and out["optimizer"].defaults["lr"] == st.optimizer.lr
    assert out["optimizer"].defaults["weight_decay"] == st.optimizer.weight_decay
    assert out["lr_scheduler"]["interval"] == ("epoch" if sched_name == "step" else "step")
    # kpd6d-run spells it for the detector_stage node; the demo uses cpu_budget over a 2.5-minute cap
    demo = _compose("run", "experiment=demo")
    assert demo.detector_stage.scheduler.name == "cosine_time"
    assert resolve_scheduler(demo.detector_stage.scheduler, demo.detector_stage.trainer)["budget_s"] == 150.0


def test_old_detector_stage_spellings_name_the_new_ones():
    from kpd6d.config import check_stage_config, renamed_overrides

    assert renamed_overrides(["stage.recipe=fast", "stage.batch_size=4", "detector_stage.max_minutes=3"]) == [
        "stage.recipe is now the detector_recipe config group: detector_recipe@stage=NAME (paper, fast, cpu_budget)",
        "detector_stage.max_minutes is now detector_stage.trainer.max_time (DD:HH:MM:SS, e.g. 00:00:14:00)"]
    assert renamed_overrides(["stage.kpd.trainer.max_epochs=3", "detector=fcos"]) == []
    with pytest.raises(ValueError, match=r"detector_stage\.precision is now detector_stage\.trainer\.precision"):
        check_stage_config({"precision": "bf16-mixed", "batch_size": 8}, "detector_stage")
    check_stage_config(_compose("run").detector_stage, "detector_stage")  # the shipped configs are clean
    # an experiment file of an earlier version composes, and the run names the new spelling before any work
    from omegaconf import OmegaConf

    from kpd6d.workflow import run_experiment

    cfg = _compose("run")
    OmegaConf.set_struct(cfg, False)
    cfg.detector_stage.recipe = "cpu_budget"
    with pytest.raises(ValueError, match="detector_recipe@detector_stage=NAME"):
        run_experiment(cfg, "/nonexistent/never/made")


def _tiny_module():
    import pytorch_lightning as pl

    class Module(pl.LightningModule):
        def __init__(self):
            super().__init__()
            self.net = torch.nn.Linear(2, 1)

        def training_step(self, batch, batch_idx):
            loss = self.net(batch[0]).pow(2).mean()
            self.log("train/loss", loss, on_step=False, on_epoch=True)
            return loss

        def validation_step(self, batch, batch_idx):
            # a metric that only gets worse: best.ckpt stays at epoch 0
            self.log("val/score", -float(self.current_epoch), on_epoch=True, batch_size=1)

        def configure_optimizers(self):
            return configure_optimization(self.parameters(), {"name": "sgd", "lr": 0.1},
                                          {"name": "step", "step_size": 1, "gamma": 0.5})

    return Module()


def test_trainer_writes_best_and_last_every_epoch_resumes_and_writes_metrics(tmp_path):
    import time

    x = torch.randn(8, 2)
    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(x), batch_size=4)
    tcfg = {"max_epochs": 2, "accelerator": "cpu", "devices": 1, "log_every_n_steps": 1, "max_time": None,
            "enable_progress_bar": False, "num_sanity_val_steps": 0}
    trainer = build_trainer(tmp_path, tcfg, monitor="val/score", mode="max", ema_decay=0.9, log_versions=False)
    assert fit(trainer, _tiny_module(), loader, loader) is None
    ckpt = tmp_path / "checkpoints"
    assert sorted(p.name for p in ckpt.iterdir()) == ["best.ckpt", "last.ckpt"]
    assert torch.load(ckpt / "best.ckpt", weights_only=False)["epoch"] == 0
    last = torch.load(ckpt / "last.ckpt", weights_only=False)
    assert last["epoch"] == 1 and last["callbacks"]["WeightEMA"]["num_updates"] >= 1  # the last epoch, not the best's
    assert (tmp_path / "csv" / "metrics.csv").is_file()
    m = write_metrics(tmp_path, trainer, stage="toy", t0=time.time(), obj_ids=[1])
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved == m and saved["stage"] == "toy" and saved["obj_ids"] == [1] and saved["epochs"] == 2
    assert saved["best_checkpoint"] == str(ckpt / "best.ckpt") and saved["best_val_score"] == 0.0
    assert saved["last_checkpoint"] == str(ckpt / "last.ckpt") and "val/score" in saved["final_metrics"]
    # a rerun resumes from last.ckpt (its epoch and learning-rate schedule) and trains the missing epoch
    trainer = build_trainer(tmp_path, {**tcfg, "max_epochs": 3}, monitor="val/score", mode="max", ema_decay=0.9,
                            log_versions=False)
    module = _tiny_module()
    assert fit(trainer, module, loader, loader) == str(ckpt / "last.ckpt")
    assert trainer.current_epoch == 3 and torch.load(ckpt / "last.ckpt", weights_only=False)["epoch"] == 2
    assert trainer.optimizers[0].param_groups[0]["lr"] == pytest.approx(0.1 * 0.5 ** 3)
    with pytest.raises(ValueError, match="mode must be"):
        build_trainer(tmp_path, tcfg, monitor="val/score", mode="up")


_FAULTS_SCRIPT = r"""
import resource, sys
from kpd6d.training import configure_malloc
if sys.argv[1] == "tuned":
    print("SET", configure_malloc({"mmap_threshold_mb": 32, "trim_threshold_mb": 1024}))
def step():  # a training step's pattern: many MiB-sized blocks allocated, touched, all freed
    blocks = [bytearray(1 << 20) for _ in range(64)]
    del blocks
step(); step()  # warm-up (glibc's dynamic thresholds adapt after the first frees)
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    step()
print("FAULTS", (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / 10)
"""


def _faults_per_step(mode):
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _FAULTS_SCRIPT, mode], capture_output=True, text=True, check=True).stdout
    return out, float(out.split("FAULTS")[1])


def test_configure_malloc_keeps_freed_memory_in_the_heap():
    """glibc's default trims the heap after a step frees its 64 MiB (the next step faults every page
    in again, ~16,000 faults at 4 KiB pages); with the thresholds the pages stay mapped."""
    import platform

    if platform.libc_ver()[0] != "glibc":
        pytest.fail(f"configure_malloc is glibc-only; this test needs glibc, found {platform.libc_ver()}")
    _, default = _faults_per_step("default")
    out, tuned = _faults_per_step("tuned")
    assert "SET {'mmap_threshold': 33554432, 'trim_threshold': 1073741824}" in out
    assert default > 1000, default  # 64 MiB / 4 KiB = 16,384 pages (fewer with transparent huge pages)
    assert tuned < default / 20, (tuned, default)


def test_configure_malloc_names_bad_settings():
    from kpd6d.training import configure_malloc

    assert configure_malloc(None) == {} and configure_malloc({"mmap_threshold_mb": None}) == {}
    with pytest.raises(ValueError, match=r"stage.malloc.mmap_threshold_mb must be in \[0, 32\] MiB, got 64"):
        configure_malloc({"mmap_threshold_mb": 64}, where="stage.malloc")
    with pytest.raises(ValueError, match=r"malloc.trim_threshold_mb must be in \[0, 2047\] MiB, got 2048"):
        configure_malloc({"trim_threshold_mb": 2048})  # a C int of bytes
    with pytest.raises(ValueError, match=r"stage.kpd.malloc: unknown key\(s\) \['trim_mb'\]"):
        configure_malloc({"trim_mb": 8}, where="stage.kpd.malloc")
    with pytest.raises(ValueError, match=r"malloc\.trim_threshold_mb"):
        configure_malloc({"trim_threshold_mb": "lots"})
