"""train_kpd end to end on a tiny generated procedural dataset (Hydra config as kpd6d-train composes it)."""

import json

import pytest
from hydra import compose, initialize_config_dir

from kpd6d.config import config_dir

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _cfg(tmp_path, *extra):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("train", overrides=[
            "stage=kpd", "backbone@stage.backbone=tiny", "stage.kpd.head.deconv_channels=16",
            "stage.kpd.codec.input_size=64", "stage.kpd.batch_size=4", "stage.kpd.num_workers=0",
            "data.generate.num_train=6", "data.generate.num_val=3", "data.generate.obj_ids=[2]",
            "stage.kpd.trainer.max_epochs=1", "stage.kpd.trainer.accelerator=cpu", "stage.kpd.trainer.devices=1",
            "stage.kpd.trainer.log_every_n_steps=1", f"+run_dir={tmp_path}", *extra,
        ])
    return cfg


def test_train_kpd_generates_data_trains_and_writes_outputs(tmp_path):
    from kpd6d.kpd.module import KPDModule
    from kpd6d.kpd.train import train_kpd

    run = train_kpd(_cfg(tmp_path))
    assert (run / "data" / "train").is_dir() and (run / "data" / "val").is_dir()
    summary = json.loads((run / "metrics.json").read_text())
    assert summary["obj_ids"] == [2] and summary["epochs"] == 1 and summary["global_step"] >= 1
    for key in ("val/proj2d_acc_5px", "val/add_acc_0.1d", "val/kp_err_px", "val/loss"):
        assert key in summary["final_metrics"], key
    assert (run / "csv" / "version_0" / "metrics.csv").is_file()
    assert any((run / "tb").glob("version_0/events.out.tfevents.*"))
    last = run / "checkpoints" / "last.ckpt"
    assert last.is_file() and (run / "checkpoints" / "best.ckpt").is_file()
    m = KPDModule.load_checkpoint(last)
    assert m.obj_ids == [2] and m.codec.input_size == 64 and m.hparams.backbone["name"] == "tiny"

    # a rerun in the same run directory resumes from last.ckpt and trains one more epoch
    train_kpd(_cfg(tmp_path, "stage.kpd.trainer.max_epochs=2"))
    assert json.loads((run / "metrics.json").read_text())["epochs"] == 2
    assert (run / "csv" / "version_0" / "metrics.csv").is_file() and (run / "csv" / "version_1" / "metrics.csv").is_file()


def test_missing_data_root_is_named(tmp_path):
    from kpd6d.kpd.train import train_kpd

    with pytest.raises(FileNotFoundError, match="nowhere"):
        train_kpd(_cfg(tmp_path, f"data.root={tmp_path / 'nowhere'}"))


def test_allocator_setting_reaches_the_stage(tmp_path):
    """stage.kpd.malloc goes to kpd6d.training.configure_malloc (a value glibc cannot take is named
    before any data is generated)."""
    from kpd6d.kpd.train import train_kpd

    with pytest.raises(ValueError, match=r"stage.kpd.malloc.mmap_threshold_mb must be in \[0, 32\] MiB, got 64"):
        train_kpd(_cfg(tmp_path, "stage.kpd.malloc.mmap_threshold_mb=64"))
    assert not (tmp_path / "data").exists()


def test_cosine_time_scheduler_takes_its_budget_from_max_time(tmp_path):
    from kpd6d.kpd.module import KPDModule
    from kpd6d.kpd.train import scheduler_config, train_kpd

    cfg = _cfg(tmp_path, "stage.kpd.scheduler={name:cosine_time,warmup_steps:0}", "stage.kpd.trainer.max_time=00:00:02:30")
    sched = scheduler_config(cfg.stage.kpd)
    assert sched == {"name": "cosine_time", "warmup_steps": 0, "budget_s": 150.0}
    # the module turns it into a LambdaLR over the budget, stepped every optimiser step
    m = KPDModule(obj_ids=[1], keypoints_3d=[[[0, 0, 0]] * 4], diameters=[100.0], backbone={"name": "tiny"},
                  head={"name": "deconv", "deconv_channels": 8}, input_size=32, scheduler=sched)
    opt = m.configure_optimizers()
    assert opt["lr_scheduler"]["interval"] == "step"
    assert opt["lr_scheduler"]["scheduler"].lr_lambdas[0].budget_s == 150.0
    # no budget: named, before any data is generated
    with pytest.raises(ValueError, match=r"trainer\.max_time"):
        train_kpd(_cfg(tmp_path, "stage.kpd.scheduler={name:cosine_time}"))
    assert not (tmp_path / "data").exists()


def test_ema_decay_adds_the_weight_average(tmp_path):
    import torch

    from kpd6d.kpd.module import KPDModule
    from kpd6d.kpd.train import train_kpd

    run = train_kpd(_cfg(tmp_path, "stage.kpd.ema_decay=0.9"))
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)
    state = ckpt["callbacks"]["WeightEMA"]
    assert state["decay"] == 0.9 and state["num_updates"] >= 1
    # the checkpoint's weights are the average, the raw ones ride along for resuming
    key = next(k for k in state["raw"] if k.endswith("weight"))
    assert not torch.equal(ckpt["state_dict"][key], state["raw"][key])
    assert KPDModule.load_checkpoint(run / "checkpoints" / "best.ckpt").obj_ids == [2]
