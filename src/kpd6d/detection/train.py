"""``train_detector(cfg)``: the detector stage of ``kpd6d-train stage=detector`` (conf/stage/detector.yaml).

Run folder (Hydra's output dir): ``data/`` (when ``data.root`` is null: a generated procedural
dataset), ``checkpoints/`` (Lightning, ``last.ckpt`` for resuming), ``tb/`` and ``csv/`` logs,
``box_stats.json`` (validation box errors for the KPD's ``pgpg`` augmentation) and ``detector.pt``
(the exported detector: ``kpd6d.detection.load_detector("detector.pt")``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from kpd6d.config import run_dir_of
from kpd6d.io import atomic_write_json, to_plain

__all__ = ["prepare_data", "train_detector"]


def _get(cfg: Any, key: str, default: Any = None) -> Any:
    cur = cfg
    for part in key.split("."):
        if cur is None:
            return default
        cur = cur.get(part) if hasattr(cur, "get") else getattr(cur, part, None)
    return default if cur is None else cur


def prepare_data(cfg: Any, run_dir: Path) -> Path:
    """``data.root``, or a procedural dataset generated (resumably) into ``<run_dir>/data``."""
    root = _get(cfg, "data.root")
    if root:
        root = Path(root)
        if not root.is_dir():
            raise FileNotFoundError(f"data.root {str(root)!r} does not exist")
        return root
    from kpd6d.synth import generate_dataset

    g = to_plain(_get(cfg, "stage.generate", {})) or {}
    out = run_dir / "data"
    seed = int(g.get("seed", 1))
    for split, n, s in ((_get(cfg, "data.train_split", "train"), g.get("num_train", 400), seed),
                        (_get(cfg, "data.val_split", "val"), g.get("num_val", 50), seed + 1000)):
        generate_dataset(out, obj_ids=g.get("obj_ids"), num_images=int(n), split=split, seed=s,
                         workers=int(g.get("workers", 1)), **(g.get("options") or {}))
    return out


def train_detector(cfg: Any) -> Path:
    """Train the configured detector; returns the path of the exported ``detector.pt``."""
    import pytorch_lightning as pl
    import torch
    from pytorch_lightning.callbacks import ModelCheckpoint
    from pytorch_lightning.loggers import CSVLogger, TensorBoardLogger
    from torch.utils.data import DataLoader

    from kpd6d.detection.dataset import DetectionDataset, collate_detection
    from kpd6d.detection.detectors import save_detector
    from kpd6d.detection.module import DetectorModule
    from kpd6d.ema import ema_callback

    st = to_plain(_get(cfg, "stage")) or {}
    det_cfg = dict(to_plain(_get(cfg, "detector")) or {})
    if not det_cfg.get("name"):
        raise KeyError("train_detector: config has no detector.name (use detector=centernet|fcos|faster_rcnn)")
    recipes = st.get("recipes") or {}
    recipe_name = st.get("recipe", "paper")
    if recipe_name not in recipes:
        raise KeyError(f"stage.recipe {recipe_name!r} is unknown; known recipes: {sorted(recipes)}")
    recipe = recipes[recipe_name]
    seed = int(_get(cfg, "seed", 0))
    if st.get("num_threads"):
        torch.set_num_threads(int(st["num_threads"]))
    pl.seed_everything(seed, workers=True)

    run_dir = run_dir_of(cfg)
    run_dir.mkdir(parents=True, exist_ok=True)
    root = prepare_data(cfg, run_dir)
    input_size = det_cfg.get("input_size")
    common = dict(box=st.get("box", "bbox_visib"), min_visib_fract=float(st.get("min_visib_fract", 0.1)),
                  input_size=input_size)
    train_ds = DetectionDataset(root, _get(cfg, "data.train_split", "train"), obj_ids=st.get("obj_ids"), **common)
    obj_ids = det_cfg.get("obj_ids") or train_ds.obj_ids
    if det_cfg.get("obj_ids") and sorted(det_cfg["obj_ids"]) != train_ds.obj_ids and not st.get("obj_ids"):
        train_ds = DetectionDataset(root, _get(cfg, "data.train_split", "train"), obj_ids=obj_ids, **common)
    det_cfg["obj_ids"] = [int(o) for o in obj_ids]
    val_split = _get(cfg, "data.val_split")
    val_ds = None
    if val_split and (Path(root) / val_split).is_dir():
        val_ds = DetectionDataset(root, val_split, obj_ids=det_cfg["obj_ids"], **common)

    optimizer = dict(recipe.get("optimizer") or {})
    if optimizer.get("schedule") == "cosine_time":
        if not st.get("max_minutes"):
            raise ValueError("stage.recipe uses schedule cosine_time: set stage.max_minutes (the time budget)")
        optimizer["minutes"] = float(st["max_minutes"])
    stats_path = run_dir / "box_stats.json"
    module = DetectorModule(det_cfg, optimizer=optimizer, augment=st.get("augment"),
                            eval_score_threshold=float(st.get("eval_score_threshold", 0.01)),
                            box_stats_iou=float(st.get("box_stats_iou", 0.5)), stats_path=str(stats_path), seed=seed,
                            channels_last=bool(st.get("channels_last", True)), finetune=st.get("finetune"))
    bs, workers = int(st.get("batch_size", 8)), int(st.get("num_workers", 0))
    train_dl = DataLoader(train_ds, batch_size=bs, shuffle=True, num_workers=workers, collate_fn=collate_detection,
                          drop_last=len(train_ds) > bs, persistent_workers=workers > 0)
    val_dl = (DataLoader(val_ds, batch_size=bs, shuffle=False, num_workers=workers, collate_fn=collate_detection)
              if val_ds is not None else None)
    ckpt_dir = run_dir / "checkpoints"
    callbacks = [ModelCheckpoint(dirpath=ckpt_dir, filename="last", monitor=None, save_top_k=1,
                                 enable_version_counter=False)]  # every epoch: resume point
    if val_dl is not None:
        callbacks.append(ModelCheckpoint(dirpath=ckpt_dir, filename="best-{epoch}", monitor="val/map_50", mode="max",
                                         save_top_k=1))
    ema = ema_callback(st.get("ema_decay"))
    callbacks = ema + callbacks
    max_minutes = st.get("max_minutes")
    trainer = pl.Trainer(
        default_root_dir=str(run_dir),
        max_epochs=int(st.get("max_epochs") or recipe.get("max_epochs", 100)),
        max_time={"minutes": float(max_minutes)} if max_minutes else None,
        accelerator=st.get("accelerator", "auto"),
        devices=1,
        precision=st.get("precision") or "32-true",
        logger=[TensorBoardLogger(str(run_dir), name="tb", version=""), CSVLogger(str(run_dir), name="csv", version="")],
        callbacks=callbacks,
        check_val_every_n_epoch=int(st.get("val_every_n_epochs", 1)),
        log_every_n_steps=int(st.get("log_every_n_steps", 10)),
        num_sanity_val_steps=0,
        enable_progress_bar=True,
    )
    last = ckpt_dir / "last.ckpt"
    ckpt_path = str(last) if st.get("resume", True) and last.is_file() else None
    t0 = time.time()
    trainer.fit(module, train_dl, val_dl, ckpt_path=ckpt_path)
    wall = time.time() - t0
    for cb in ema:  # export the weight average
        cb.apply_to(module)
    det = module.detector.cpu().eval()
    out = save_detector(det, run_dir / "detector.pt")
    summary = {"detector": str(out), "obj_ids": det_cfg["obj_ids"], "train_wall_s": wall,
               "epochs": trainer.current_epoch, **getattr(module, "last_metrics", {})}
    atomic_write_json(run_dir / "summary.json", summary)
    print(f"detector saved to {out}; " + ", ".join(f"{k}={v}" for k, v in summary.items() if k != "detector"))
    torch.set_grad_enabled(True)
    return out
