"""``train_detector(cfg)``: the detector stage of ``kpd6d-train stage=detector`` (conf/stage/detector.yaml).

Settings: ``cfg.detector`` (conf/detector/), ``cfg.stage`` (conf/stage/detector.yaml, with the
recipe, conf/detector_recipe/: ``optimizer``, ``scheduler`` and ``trainer.max_epochs``, and the
``trainer:`` node of conf/trainer/default.yaml) and the top-level ``seed`` and ``data`` nodes.
Trainer, checkpoints, logs, resuming and the metrics file are :mod:`kpd6d.training`'s, as for the
KPD stage. Run folder (Hydra's output dir): ``data/`` (when ``data.root`` is null: a generated
procedural dataset), ``checkpoints/`` (``best.ckpt``: best ``val/map_50``; ``last.ckpt``: resume
point), ``tb/`` and ``csv/`` logs, ``metrics.json``, ``box_stats.json`` (validation box errors for
the KPD's ``pgpg`` augmentation) and ``detector.pt`` (the exported detector:
``kpd6d.detection.load_detector("detector.pt")``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from kpd6d.config import check_stage_config, run_dir_of
from kpd6d.io import to_plain

__all__ = ["train_detector"]

def train_detector(cfg: Any) -> Path:
    """Train the configured detector; returns the path of the exported ``detector.pt``."""
    import torch
    from torch.utils.data import DataLoader

    from kpd6d.detection.dataset import DetectionDataset, collate_detection
    from kpd6d.detection.detectors import save_detector
    from kpd6d.detection.module import DetectorModule
    from kpd6d.training import (
        build_trainer,
        ema_callbacks,
        fit,
        resolve_scheduler,
        seed_and_threads,
        write_metrics,
    )

    t_start = time.time()
    st = cfg.stage
    check_stage_config(st)
    det_cfg = dict(to_plain(cfg.detector) or {})
    if not det_cfg.get("name"):
        raise KeyError("train_detector: config has no detector.name (use detector=centernet|fcos|faster_rcnn)")
    scheduler = resolve_scheduler(st.scheduler, st.trainer, where="stage")  # config errors before any data
    seed = int(cfg.seed)
    seed_and_threads(seed, st.num_threads, st.get("malloc"))

    run_dir = run_dir_of(cfg)
    run_dir.mkdir(parents=True, exist_ok=True)
    from kpd6d.distributed import EvalShardSampler
    from kpd6d.synth.prepare import prepare_data

    root = prepare_data(cfg.data.root, run_dir, to_plain(cfg.data.get("generate")), [cfg.data.train_split, cfg.data.val_split])
    common = dict(box=st.box, min_visib_fract=float(st.min_visib_fract), input_size=det_cfg.get("input_size"))
    stage_ids = to_plain(st.obj_ids)
    train_kw = dict(common, train_crop=to_plain(st.get("train_crop")))  # windows of the network input (training only)
    train_ds = DetectionDataset(root, cfg.data.train_split, obj_ids=stage_ids, **train_kw)
    obj_ids = det_cfg.get("obj_ids") or train_ds.obj_ids
    if det_cfg.get("obj_ids") and sorted(det_cfg["obj_ids"]) != train_ds.obj_ids and not stage_ids:
        train_ds = DetectionDataset(root, cfg.data.train_split, obj_ids=obj_ids, **train_kw)
    det_cfg["obj_ids"] = [int(o) for o in obj_ids]
    val_split = cfg.data.val_split
    val_ds = None
    if val_split and (Path(root) / val_split).is_dir():
        val_ds = DetectionDataset(root, val_split, obj_ids=det_cfg["obj_ids"], **common)

    stats_path = run_dir / "box_stats.json"
    module = DetectorModule(det_cfg, optimizer=to_plain(st.optimizer), scheduler=scheduler, augment=to_plain(st.augment),
                            eval_score_threshold=float(st.eval_score_threshold),
                            box_stats_iou=float(st.box_stats_iou), stats_path=str(stats_path), seed=seed,
                            channels_last=bool(st.channels_last), finetune=to_plain(st.finetune))
    module.detector.box_field = str(st.box)  # recorded in every checkpoint: what its boxes mean
    bs, workers = int(st.batch_size), int(st.num_workers)
    train_dl = DataLoader(train_ds, batch_size=bs, shuffle=True, num_workers=workers, collate_fn=collate_detection,
                          drop_last=len(train_ds) > bs, persistent_workers=workers > 0)
    val_dl = (DataLoader(val_ds, batch_size=bs, sampler=EvalShardSampler(val_ds), num_workers=workers,
                         collate_fn=collate_detection) if val_ds is not None else None)
    trainer = build_trainer(run_dir, st.trainer, monitor="val/map_50" if val_dl is not None else "train/loss_epoch",
                            mode="max" if val_dl is not None else "min", ema_decay=st.ema_decay,
                            log_versions=False)
    t0 = time.time()
    fit(trainer, module, train_dl, val_dl, resume=bool(st.resume))
    wall = time.time() - t0
    out = run_dir / "detector.pt"
    if not trainer.is_global_zero:  # under DDP, rank 0 alone writes the exported detector and metrics.json
        return out
    for cb in ema_callbacks(trainer):  # export the weight average
        cb.apply_to(module)
    det = module.detector.cpu().eval()
    out = save_detector(det, out)
    write_metrics(run_dir, trainer, stage="detector", t0=t_start, detector=str(out), data_root=str(root),
                  obj_ids=det_cfg["obj_ids"], train_images=len(train_ds), val_images=len(val_ds) if val_ds is not None else 0,
                  train_wall_s=wall, **getattr(module, "last_metrics", {}))
    print(f"detector saved to {out}")
    torch.set_grad_enabled(True)
    return out
