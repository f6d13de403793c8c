"""KPD accuracy benchmark: train on a procedural single-object dataset, test on a differently seeded one.

``kpd6d-benchmark kpd [--out DIR] [--minutes 15] [--backbone resnet18] [--obj-id 1] [--num-train 4000]
[--num-val 50] [--num-test 100] [HYDRA_OVERRIDE ...]`` generates ``train`` (seed 1), ``val`` (seed 2,
checkpoint selection) and ``test`` (seed 3) splits of procedural object ``--obj-id`` (resumable), trains
with ``kpd@stage.kpd=cpu_small`` under a ``--minutes`` wall-clock cap, then evaluates the best checkpoint
on ``test`` with GT boxes and prints 2-D projection accuracy at 5 px, ADD(-S) at 0.1 d and the mean
keypoint error. Rerunning with the same ``--out`` reuses the data and resumes training from last.ckpt.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="kpd6d-benchmark kpd", description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="outputs/benchmarks/kpd")
    ap.add_argument("--minutes", type=float, default=15.0)
    ap.add_argument("--backbone", default="resnet18")
    ap.add_argument("--preset", default="cpu_small", help="conf/kpd/ preset")
    ap.add_argument("--obj-id", type=int, default=1)
    ap.add_argument("--num-train", type=int, default=4000, help="training images (800 over-fits within 15 min)")
    ap.add_argument("--num-val", type=int, default=50)
    ap.add_argument("--num-test", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2, help="rendering processes")
    ap.add_argument("overrides", nargs="*", help="extra Hydra overrides of conf/train.yaml")
    args = ap.parse_args(argv)

    import pytorch_lightning as pl
    import torch
    from hydra import compose, initialize_config_dir

    from kpd6d.config import config_dir
    from kpd6d.kpd.crops import KPDCropDataset
    from kpd6d.kpd.module import KPDModule
    from kpd6d.kpd.train import train_kpd
    from kpd6d.synth import generate_dataset

    out = Path(args.out).resolve()
    data = out / "data"
    t0 = time.time()
    for split, n, seed in (("train", args.num_train, 1), ("val", args.num_val, 2), ("test", args.num_test, 3)):
        generate_dataset(data, obj_ids=[args.obj_id], num_images=n, split=split, seed=seed, workers=args.workers)
    t_gen = time.time() - t0
    total_s = round(args.minutes * 60)
    hours, rest = divmod(total_s, 3600)
    mins, secs = divmod(rest, 60)
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("train", overrides=[
            "stage=kpd", f"backbone@stage.backbone={args.backbone}", f"kpd@stage.kpd={args.preset}",
            f"data.root={data}", "data.train_split=train", "data.val_split=val",
            f"stage.kpd.trainer.max_time=00:{hours:02d}:{mins:02d}:{secs:02d}", f"+run_dir={out / 'run'}", *args.overrides,
        ])
    t1 = time.time()
    run = train_kpd(cfg)
    t_train = time.time() - t1
    summary = json.loads((run / "metrics.json").read_text())
    ckpt = summary["best_checkpoint"] or summary["last_checkpoint"]
    module = KPDModule.load_checkpoint(ckpt)
    k = cfg.stage.kpd
    test = KPDCropDataset(data, split="test", keypoints=module.keypoints_3d, codec=module.codec, box_source="visib",
                          visibility=k.visibility, min_visib_fract=float(k.min_visib_fract))
    loader = torch.utils.data.DataLoader(test, batch_size=32, num_workers=int(k.num_workers))
    trainer = pl.Trainer(accelerator=k.trainer.accelerator, devices=1, logger=False, enable_checkpointing=False,
                         enable_model_summary=False)
    res = trainer.validate(module, loader, verbose=False)[0]
    figures = {
        "test_instances": len(test), "train_instances": summary["train_instances"], "epochs": summary["epochs"],
        "steps": summary["global_step"], "generate_s": round(t_gen, 1), "train_s": round(t_train, 1),
        "proj2d_acc_5px": res["val/proj2d_acc_5px"], "add_acc_0.1d": res["val/add_acc_0.1d"],
        "kp_err_px": res["val/kp_err_px"], "pnp_fail_rate": res["val/pnp_fail_rate"], "checkpoint": ckpt,
        "backbone": args.backbone, "preset": args.preset, "torch_threads": torch.get_num_threads(),
    }
    (out / "benchmark.json").write_text(json.dumps(figures, indent=1))
    print("kpd benchmark (GT boxes, test split seed 3):")
    for key, v in figures.items():
        print(f"  {key}: {v:.4f}" if isinstance(v, float) else f"  {key}: {v}")
    return 0
