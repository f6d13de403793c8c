"""``train_kpd(cfg)``: train the keypoint detector (``kpd6d-train stage=kpd ...``).

Reads ``cfg.stage.backbone`` (conf/backbone/), ``cfg.stage.kpd.codec`` (conf/codec/ + conf/decoder/) and
``cfg.stage.kpd`` (conf/kpd/: model, loss, optimiser, augmentation, selection, data loader and
``trainer`` settings) plus the top-level ``seed`` and ``data`` nodes of conf/train.yaml. With
``data.root: null`` a small procedural dataset (train and val generated with different seeds) is
written into ``<run dir>/data`` first. Writes TensorBoard (``tb/``) and CSV (``csv/metrics.csv``)
logs, checkpoints (``checkpoints/best.ckpt``, ``checkpoints/last.ckpt``; a rerun in the same run
directory resumes from ``last.ckpt``) and ``metrics.json`` (final validation metrics) into the run
directory.
"""

from __future__ import annotations

import time
from pathlib import Path

from kpd6d.config import check_stage_config, run_dir_of
from kpd6d.io import to_plain

__all__ = ["build_datasets", "scheduler_config", "train_kpd"]


def build_datasets(cfg, root: Path):
    """(train, val or None) :class:`~kpd6d.kpd.crops.KPDCropDataset` s from the stage config."""
    from kpd6d.kpd.box_augment import build_box_augment
    from kpd6d.kpd.crops import KPDCropDataset

    k = cfg.stage.kpd
    common = dict(obj_ids=to_plain(k.obj_ids), codec=to_plain(k.codec), box_source=k.box_source,
                  detections=k.detections, visibility=k.visibility, min_visib_fract=float(k.min_visib_fract),
                  symmetry_boundary=str(k.get("symmetry_boundary", "model_x")))
    keypoints = None
    if k.get("keypoints"):  # a keypoint file other than the dataset's (e.g. another designator)
        from kpd6d.keypoints import load_keypoints

        keypoints = load_keypoints(k.keypoints)
    train = KPDCropDataset(root, split=cfg.data.train_split, box_augment=build_box_augment(to_plain(k.box_augment)),
                           keypoints=keypoints, image_cache_mb=float(k.get("image_cache_mb", 0) or 0),
                           negative_fraction=float(k.get("negative_fraction", 0) or 0),
                           full_box_p=float(k.get("full_box_p", 0) or 0),
                           return_heatmaps=not (k.augment and (k.augment.get("rotation_deg") or k.augment.get("translate")
                                                                or k.augment.get("scale"))),
                           **common)
    val = None
    if cfg.data.val_split:
        vc = dict(common, obj_ids=train.obj_ids)
        if vc["box_source"] == "detections":
            vc["box_source"] = "visib"  # validation is defined on GT boxes
        val = KPDCropDataset(root, split=cfg.data.val_split, keypoints=train.keypoints_3d, models=list(train.models.values()),
                             max_instances=k.val_max_instances, **vc)
    return train, val


def scheduler_config(k) -> dict | None:
    """``stage.kpd.scheduler`` as a dict; ``cosine_time`` gets its budget from ``trainer.max_time``
    (:func:`kpd6d.training.resolve_scheduler`)."""
    from kpd6d.training import resolve_scheduler

    return resolve_scheduler(k.scheduler, k.trainer, where="stage.kpd")


def train_kpd(cfg) -> Path:
    """Train the KPD stage; returns the run directory."""
    import torch

    from kpd6d.kpd.module import KPDModule
    from kpd6d.training import build_trainer, fit, seed_and_threads, write_metrics

    t0 = time.time()
    check_stage_config(cfg.stage)
    k = cfg.stage.kpd
    scheduler = scheduler_config(k)  # config errors before any data is generated
    from kpd6d.kpd.codec import build_codec

    build_codec(to_plain(k.codec))  # a bad crop size / stride / sigma, too
    run_dir = run_dir_of(cfg)
    run_dir.mkdir(parents=True, exist_ok=True)
    seed_and_threads(cfg.seed, k.get("num_threads"), k.get("malloc"), where="stage.kpd")
    from kpd6d.synth.prepare import prepare_data

    root = prepare_data(cfg.data.root, run_dir, to_plain(cfg.data.get("generate")), [cfg.data.train_split, cfg.data.val_split])
    train_ds, val_ds = build_datasets(cfg, root)

    module = KPDModule.from_models(
        [train_ds.models[o] for o in train_ds.obj_ids], train_ds.keypoints_3d,
        backbone=to_plain(cfg.stage.backbone), head=to_plain(k.head), grouping=k.grouping,
        codec=to_plain(k.codec), loss=to_plain(k.loss),
        optimizer=to_plain(k.optimizer), scheduler=scheduler, augment=to_plain(k.augment),
        top_l=k.top_l, pnp=to_plain(k.pnp), channels_last=bool(k.get("channels_last", True)),
        finetune=to_plain(k.get("finetune")),
    )
    nw = int(k.num_workers)
    loader_kw = dict(batch_size=int(k.batch_size), num_workers=nw, persistent_workers=nw > 0, pin_memory=False)
    train_loader = torch.utils.data.DataLoader(train_ds, shuffle=True, drop_last=len(train_ds) > int(k.batch_size),
                                               **loader_kw)
    from kpd6d.distributed import EvalShardSampler

    val_loader = (torch.utils.data.DataLoader(val_ds, sampler=EvalShardSampler(val_ds), **loader_kw)
                  if val_ds is not None else None)  # every sample once under DDP (no padding)

    trainer = build_trainer(run_dir, k.trainer, monitor="val/proj2d_acc_5px" if val_ds is not None else "train/loss_epoch",
                            mode="max" if val_ds is not None else "min", ema_decay=k.get("ema_decay"),
                            progress_refresh=int(k.get("progress_refresh", 1)))
    fit(trainer, module, train_loader, val_loader, resume=bool(k.get("resume", True)))
    if not trainer.is_global_zero:  # under DDP, rank 0 alone writes metrics.json
        return run_dir
    write_metrics(run_dir, trainer, stage="kpd", t0=t0, data_root=str(root), obj_ids=train_ds.obj_ids,
                  train_instances=len(train_ds), val_instances=len(val_ds) if val_ds is not None else 0)
    return run_dir
