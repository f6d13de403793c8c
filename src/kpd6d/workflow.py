"""The whole method end to end in one run folder (``kpd6d-run``, ``kpd6d-demo``).

Steps, each skipped when its output already exists (so an interrupted run resumes):

1. designate keypoints for every object (``keypoints.json``, via ``DESIGNATORS``);
2. generate train / val / test render-and-paste data (``data/``, via :func:`kpd6d.synth.generate_dataset`);
3. train the detector (``detector/detector.pt``) unless ``detector_ckpt`` is given or ``"oracle"``;
4. train the KPD (``kpd/checkpoints/best.ckpt``) unless ``kpd_ckpt`` is given;
5. evaluate on the test split (``eval/``: metrics.json, results.csv, report.md, plots, overlays).

The stage configs are the same nodes ``kpd6d-train`` uses (``detector_stage`` = conf/stage/detector.yaml,
``kpd_stage`` = conf/stage/kpd.yaml), so a setting means the same thing in both tools.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from kpd6d.config import to_plain

__all__ = ["run_experiment"]


def _log(msg: str) -> None:
    print(f"[kpd6d-run {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def load_objects(objects_cfg) -> list:
    """The run's object models: a BOP models folder or the procedural set."""
    from kpd6d.objects import load_bop_models, procedural_objects

    ids = to_plain(objects_cfg.obj_ids)
    if objects_cfg.models_dir:
        return load_bop_models(objects_cfg.models_dir, ids)
    return procedural_objects(obj_ids=ids)


def designate(models: list, designator_cfg, out_file: Path, per_object: dict | None = None) -> dict[int, np.ndarray]:
    """Keypoints of every model with the configured designator, cached in ``out_file``.

    ``per_object`` maps an object id to designator parameter overrides (the paper: 17 keypoints on
    the eggbox); they are recorded in the file's parameters.
    """
    from kpd6d.keypoints import read_keypoint_file, save_keypoints
    from kpd6d.registry import DESIGNATORS, build_from_cfg

    params = to_plain(designator_cfg)
    name, rest = params["name"], {k: v for k, v in params.items() if k != "name"}
    per_object = {int(k): dict(v) for k, v in (to_plain(per_object) or {}).items()}
    if per_object:
        rest["per_object"] = {str(k): v for k, v in sorted(per_object.items())}
    if out_file.is_file():
        cached = read_keypoint_file(out_file)
        if cached.designator == name and cached.params == rest and all(m.obj_id in cached.points for m in models):
            return cached.points
    kps = {}
    for m in models:
        t0 = time.time()
        designator = build_from_cfg(DESIGNATORS, {**params, **per_object.get(m.obj_id, {})})
        kps[m.obj_id] = designator(m)
        _log(f"designated {len(kps[m.obj_id])} {params['name']} keypoints on object {m.obj_id} ({time.time() - t0:.1f} s)")
    save_keypoints(out_file, kps, designator=name, params=rest)
    return kps


def generate(cfg, root: Path) -> None:
    """Train / val / test splits (different seeds) written resumably into ``root``."""
    from kpd6d.synth import generate_dataset

    d = cfg.data
    options = dict(to_plain(d.options) or {})
    # keypoints live in the run (keypoints.json) so that runs with other designators share one dataset
    options.setdefault("designator", None)
    for i, (split, n) in enumerate((("train", d.num_train), ("val", d.num_val), (cfg.evaluate.split, d.num_test))):
        if not n:
            continue
        _log(f"generating {n} {split} images into {root}")
        generate_dataset(root, models_dir=cfg.objects.models_dir, obj_ids=to_plain(cfg.objects.obj_ids), num_images=int(n),
                         split=split, seed=int(cfg.seed) * 1000 + i, workers=int(d.workers), progress=bool(cfg.progress),
                         **options)


def _stage_cfg(cfg, stage_key: str, run_dir: Path, root: Path, **extra):
    from omegaconf import OmegaConf

    node = {"seed": int(cfg.seed), "run_dir": str(run_dir), "stage": to_plain(cfg[stage_key]),
            "data": {"root": str(root), "train_split": "train", "val_split": "val"}}
    node.update(extra)
    return OmegaConf.create(node)


def train_detector_stage(cfg, run_dir: Path, root: Path) -> str:
    out = run_dir / "detector.pt"
    if out.is_file():
        _log(f"detector exists: {out}")
        return str(out)
    from kpd6d.detection.train import train_detector

    _log("training the detector")
    det_cfg = to_plain(cfg.detector)
    det_cfg["obj_ids"] = to_plain(cfg.objects.obj_ids)
    return str(train_detector(_stage_cfg(cfg, "detector_stage", run_dir, root, detector=det_cfg)))


def train_kpd_stage(cfg, run_dir: Path, root: Path, keypoints_file: Path) -> str:
    best = run_dir / "checkpoints" / "best.ckpt"
    if (run_dir / "metrics.json").is_file() and best.is_file():
        _log(f"KPD exists: {best}")
        return str(best)
    from kpd6d.kpd.train import train_kpd

    _log("training the KPD")
    kcfg = _stage_cfg(cfg, "kpd_stage", run_dir, root)
    kcfg.stage.kpd.keypoints = str(keypoints_file)
    kcfg.stage.kpd.obj_ids = to_plain(cfg.objects.obj_ids)
    train_kpd(kcfg)
    return str(best if best.is_file() else run_dir / "checkpoints" / "last.ckpt")


def evaluate_detector_on(det_ckpt, root: Path, split: str, obj_ids, max_frames=None) -> dict:
    """AP@0.5 (overall and per object), AP@0.5:0.95 and recall of a trained detector on a BOP split."""
    from kpd6d.detection import load_detector
    from kpd6d.detection.dataset import DetectionDataset
    from kpd6d.detection.evaluate import evaluate_detector

    det = load_detector(det_ckpt)
    ds = DetectionDataset(root, split, obj_ids=obj_ids or det.obj_ids, input_size=det.input_size)
    if max_frames:
        import torch

        ds = torch.utils.data.Subset(ds, range(min(int(max_frames), len(ds))))
    res = evaluate_detector(det, ds, progress=False, per_object=True)
    res.pop("box_stats", None)
    res["images"] = len(ds)
    return res


def _evaluate(cfg, root: Path, det, kpd, out_dir: Path) -> dict:
    from omegaconf import OmegaConf

    from kpd6d.cli.evaluate import run_evaluation

    _log(f"evaluating on {root}/{cfg.evaluate.split} (detector: {det})")
    ecfg = OmegaConf.create({
        "data": {"root": str(root), "split": cfg.evaluate.split, "targets": "auto", "obj_ids": to_plain(cfg.objects.obj_ids),
                 "max_frames": cfg.evaluate.max_frames},
        "pnp": to_plain(cfg.pnp), "select": {"top_l": cfg.select.top_l}, "detector_ckpt": det, "kpd_ckpt": kpd,
        "batch_size": int(cfg.evaluate.batch_size), "refine_boxes": int(cfg.evaluate.get("refine_boxes", 0) or 0),
        "device": None, "overlays": int(cfg.evaluate.overlays), "progress": bool(cfg.progress),
    })
    extra = None
    if str(det) != "oracle":  # the detector's own AP on the same frames, per object
        _log(f"evaluating the detector on {root}/{cfg.evaluate.split}")
        extra = {"detector": evaluate_detector_on(det, root, cfg.evaluate.split, to_plain(cfg.objects.obj_ids),
                                                  cfg.evaluate.max_frames)}
    return run_evaluation(ecfg, out_dir, extra_metrics=extra)


def run_experiment(cfg, run_dir: str | Path) -> dict:
    """Run every step into ``run_dir``; returns the evaluation metrics (also in ``run_dir/metrics.json``)."""
    from omegaconf import OmegaConf

    from kpd6d.data import atomic_write_text

    t_start = time.time()
    if not cfg.detector_ckpt:  # settings of an earlier version: named before any data is made
        from kpd6d.detection.train import check_stage_config

        check_stage_config(cfg.detector_stage, "detector_stage")
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    models = load_objects(cfg.objects)
    keypoints_file = run_dir / "keypoints.json"
    designate(models, cfg.designator, keypoints_file, cfg.get("designator_per_object"))

    root = Path(cfg.data.root) if cfg.data.root else run_dir / "data"
    generate(cfg, root)
    timings = {"prepare_s": time.time() - t_start}

    t0 = time.time()
    det = cfg.detector_ckpt or train_detector_stage(cfg, run_dir / "detector", root)
    timings["detector_s"] = time.time() - t0
    t0 = time.time()
    kpd = cfg.kpd_ckpt or train_kpd_stage(cfg, run_dir / "kpd", root, keypoints_file)
    timings["kpd_s"] = time.time() - t0

    # evaluation data: the generated test split, or a BOP dataset of real images (evaluate.data_root)
    eval_root = Path(cfg.evaluate.data_root) if cfg.evaluate.get("data_root") else root
    t0 = time.time()
    metrics = _evaluate(cfg, eval_root, det, kpd, run_dir / "eval")
    if cfg.evaluate.get("oracle") and str(det) != "oracle":  # also with ground-truth boxes: the KPD alone
        oracle = _evaluate(cfg, eval_root, "oracle", kpd, run_dir / "eval_oracle")
        metrics["oracle_boxes"] = {"mean": oracle["mean"], "report": str(run_dir / "eval_oracle" / "report.md")}
    timings["evaluate_s"] = time.time() - t0
    timings["total_s"] = time.time() - t_start
    metrics["run"] = {**metrics.get("run", {}), "timings": timings,
                      "config": OmegaConf.to_container(cfg, resolve=True)}
    atomic_write_text(run_dir / "metrics.json", json.dumps(metrics, indent=1, default=float))
    return metrics
