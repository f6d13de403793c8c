"""The whole method end to end in one run folder (``kpd6d-run``, ``kpd6d-demo``).

Steps, each skipped when its output already exists (so an interrupted run resumes):

1. designate keypoints for every object (``keypoints.json``, via :mod:`kpd6d.keypoints.designate`);
2. generate train / val / test render-and-paste data (``data/``, via :func:`kpd6d.synth.generate_dataset`);
3. train the detector (``detector/detector.pt``) unless ``detector_ckpt`` is given or ``"oracle"``;
4. train the KPD (``kpd/checkpoints/best.ckpt``, or ``last.ckpt`` with ``kpd_checkpoint=last``; with
   ``kpd_networks=per_object`` one network per object in ``kpd/obj_XXXXXX/`` and the manifest
   ``kpd/networks.json``) unless ``kpd_ckpt`` is given;
5. evaluate on the test split (``eval/``: metrics.json, results.csv, report.md, plots, overlays;
   :func:`run_evaluation`, also the work of ``kpd6d-evaluate``);
6. evaluate on each synthetic yardstick of ``evaluate.yardsticks`` (``yardsticks/<name>/eval``, ``eval_oracle``;
   :func:`yardstick_splits`): the run's own generated val split, or a split generated with other
   appearance settings — the splits settings are chosen on when the test data are real frames.

``timings.json`` (and ``metrics.json``'s ``run.timings``) holds the wall time spent in each stage summed over
every invocation in the folder, so a resumed run still reports what its stages cost.

Evaluations resume frame by frame (their ``predictions.jsonl``) and refuse a folder whose predictions
were made with other settings (:func:`kpd6d.evaluation.runner.evaluate`).

The stage configs are the same nodes ``kpd6d-train`` uses (``detector_stage`` = conf/stage/detector.yaml,
``kpd_stage`` = conf/stage/kpd.yaml), so a setting means the same thing in both tools.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from kpd6d.config import cfg_float, cfg_int, to_int
from kpd6d.data.bop_io import DEFAULT_BOX_FIELD
from kpd6d.io import to_plain

__all__ = ["YARDSTICK_KEYS", "run_evaluation", "run_experiment", "yardstick_line", "yardstick_splits"]


def _log(msg: str) -> None:
    print(f"[kpd6d-run {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def load_objects(objects_cfg) -> list:
    """The run's object models: a BOP models folder or the procedural set."""
    from kpd6d.objects import load_bop_models, procedural_objects

    ids = to_plain(objects_cfg.obj_ids)
    if objects_cfg.models_dir:
        return load_bop_models(objects_cfg.models_dir, ids)
    return procedural_objects(obj_ids=ids)


def designate_keypoints(models: list, designator_cfg, out_file: Path, per_object: dict | None = None
                        ) -> dict[int, np.ndarray]:
    """Keypoints of every model with the run's designator, cached in ``out_file`` (through
    :func:`kpd6d.keypoints.designate.designate_objects`; a run's file records no mesh fingerprints).

    ``per_object`` maps an object id to designator parameter overrides (the paper: 17 keypoints on
    the eggbox); they are recorded in the file's parameters.
    """
    from kpd6d.keypoints.designate import designate_objects, designator_name_params

    name, params = designator_name_params(to_plain(designator_cfg))
    points, _ = designate_objects(
        models, name, params, out_file, per_object=to_plain(per_object), fingerprints=False, progress=False,
        on_designated=lambda oid, pts, s: _log(f"designated {len(pts)} {name} keypoints on object {oid} ({s:.1f} s)"))
    return points


designate = designate_keypoints  # the old name (transition)


def generate(cfg, root: Path) -> None:
    """Train / val / test splits (seeds ``seed * 1000 + 0, 1, 2``) written resumably into ``root``."""
    from kpd6d.synth.prepare import generate_splits

    d = cfg.data
    options = dict(to_plain(d.options) or {})
    # keypoints live in the run (keypoints.json) so that runs with other designators share one dataset
    options.setdefault("designator", None)
    counts = [(split, cfg_int(cfg, f"data.{key}") if d[key] else 0)
              for split, key in (("train", "num_train"), ("val", "num_val"), (cfg.evaluate.split, "num_test"))]
    seed, workers = cfg_int(cfg, "seed"), cfg_int(cfg, "data.workers")
    generate_splits(root, [(s, n, seed * 1000 + i) for i, (s, n) in enumerate(counts)],
                    models_dir=cfg.objects.models_dir, obj_ids=cfg.objects.obj_ids, workers=workers,
                    progress=bool(cfg.progress), options=options, log=_log)


def _stage_cfg(cfg, stage_key: str, run_dir: Path, root: Path, **extra):
    from omegaconf import OmegaConf

    node = {"seed": cfg_int(cfg, "seed"), "run_dir": str(run_dir), "stage": to_plain(cfg[stage_key]),
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


KPD_NETWORKS = ("shared", "per_object")
KPD_CHECKPOINTS = ("best", "last")


def _choice(cfg, key: str, known: tuple[str, ...]) -> str:
    """The run setting ``key``, one of ``known`` (null / empty: the first); else a ConfigError listing them."""
    value = str(cfg.get(key, known[0]) or known[0])
    if value not in known:
        from kpd6d.config import ConfigError

        raise ConfigError(f"{key}={value!r} unknown; known: {', '.join(known)}")
    return value


def _kpd_networks(cfg) -> str:
    return _choice(cfg, "kpd_networks", KPD_NETWORKS)


def _kpd_checkpoint(cfg) -> str:
    return _choice(cfg, "kpd_checkpoint", KPD_CHECKPOINTS)


def _kpd_checkpoint_file(cfg, run_dir: Path) -> Path:
    """The trained KPD's checkpoint the run uses (``kpd_checkpoint``: best or last; the other when it is
    missing, e.g. no validation ran)."""
    choice = _kpd_checkpoint(cfg)
    files = [run_dir / "checkpoints" / f"{n}.ckpt" for n in (choice, *(n for n in KPD_CHECKPOINTS if n != choice))]
    return next((f for f in files if f.is_file()), files[0])


def _train_one_kpd(cfg, run_dir: Path, root: Path, keypoints_file: Path, obj_ids, max_time=None,
                   what: str = "the KPD") -> str:
    ckpt = _kpd_checkpoint_file(cfg, run_dir)
    if (run_dir / "metrics.json").is_file() and ckpt.is_file():
        _log(f"KPD exists: {ckpt}")
        return str(ckpt)
    from kpd6d.kpd.train import train_kpd

    _log(f"training {what}")
    kcfg = _stage_cfg(cfg, "kpd_stage", run_dir, root)
    kcfg.stage.kpd.keypoints = str(keypoints_file)
    kcfg.stage.kpd.obj_ids = to_plain(obj_ids)
    if max_time is not None:
        kcfg.stage.kpd.trainer.max_time = max_time
    train_kpd(kcfg)
    return str(_kpd_checkpoint_file(cfg, run_dir))


def _split_max_time(value, n: int) -> str | None:
    """Lightning ``max_time`` divided by ``n``, as ``DD:HH:MM:SS`` (whole seconds, at least 1); None
    stays None (an epoch budget applies to each network as it is)."""
    from kpd6d.schedules import parse_max_time

    total = parse_max_time(to_plain(value))
    if total is None:
        return None
    s = max(1, int(total // n))
    return f"{s // 86400:02d}:{s // 3600 % 24:02d}:{s // 60 % 60:02d}:{s % 60:02d}"


def train_kpd_stage(cfg, run_dir: Path, root: Path, keypoints_file: Path) -> str:
    """The run's KPD: one network for all objects (``kpd_networks=shared``; returns its checkpoint) or
    one per object (``per_object``: each trained on its object's crops for ``max_time`` / objects, or
    for the epoch budget when there is no ``max_time``, in
    ``run_dir/obj_XXXXXX``; returns the ``networks.json`` manifest, :mod:`kpd6d.kpd.ensemble`)."""
    obj_ids = [int(o) for o in to_plain(cfg.objects.obj_ids)]
    if _kpd_networks(cfg) == "shared":
        return _train_one_kpd(cfg, run_dir, root, keypoints_file, obj_ids)
    from kpd6d.kpd.ensemble import write_manifest

    manifest = run_dir / "networks.json"
    if manifest.is_file():
        _log(f"KPD networks exist: {manifest}")
        return str(manifest)
    budget = _split_max_time(cfg.kpd_stage.kpd.trainer.get("max_time"), len(obj_ids))
    members = {o: _train_one_kpd(cfg, run_dir / f"obj_{o:06d}", root, keypoints_file, [o], budget,
                                 what=f"the KPD of object {o} ({i + 1}/{len(obj_ids)}, max_time {budget})")
               for i, o in enumerate(obj_ids)}
    return str(write_manifest(manifest, members))


def evaluate_detector_on(det_ckpt, root: Path, split: str, obj_ids, max_frames=None) -> dict:
    """AP@0.5 (overall and per object), AP@0.5:0.95 and recall of a trained detector on a BOP split."""
    from kpd6d.detection import load_detector
    from kpd6d.detection.dataset import DetectionDataset
    from kpd6d.detection.metrics import evaluate_detector

    det = load_detector(det_ckpt)
    ds = DetectionDataset(root, split, obj_ids=obj_ids or det.obj_ids, input_size=det.input_size,
                          box=det.box_field)  # scored on the boxes it was trained to give
    if max_frames:
        import torch

        ds = torch.utils.data.Subset(ds, range(min(int(max_frames), len(ds))))
    res = evaluate_detector(det, ds, progress=False, per_object=True)
    res.pop("box_stats", None)
    res["images"] = len(ds)
    return res


def run_evaluation(cfg, out_dir: str | Path, extra_metrics: dict | None = None) -> dict:
    """Evaluate a detector + KPD checkpoint pair on a BOP split (the work of ``kpd6d-evaluate``, step 5
    of :func:`run_experiment`); ``cfg`` is a composed conf/evaluate.yaml. Writes metrics.json,
    results.csv, report.md, plots and overlays into ``out_dir`` and returns the metrics. With
    ``num_shards`` > 1 only shard ``shard``'s predictions (returns the shard's summary), or with
    ``merge=true`` the merge of the finished shards (:func:`kpd6d.evaluation.runner.evaluate`)."""
    from omegaconf import OmegaConf

    from kpd6d.data import BopDataset
    from kpd6d.detection.detectors import check_detector_overrides
    from kpd6d.evaluation.runner import check_oracle_box, evaluate
    from kpd6d.pipeline import PosePipeline
    from kpd6d.pnp.estimator import candidate_options, candidates_record, crop_tta_record
    from kpd6d.refinement import build_refiner

    root = Path(cfg.data.root)
    if not root.is_dir():
        raise FileNotFoundError(f"data.root={str(root)!r}: BOP dataset root does not exist")
    targets = cfg.data.targets
    if targets == "auto":
        targets = "test_targets_bop19.json" if (root / "test_targets_bop19.json").is_file() else None
    pnp_cfg = OmegaConf.to_container(cfg.pnp, resolve=True)
    top_l = cfg.select.top_l
    obj_ids = list(cfg.data.obj_ids) if cfg.data.obj_ids else None
    backend = str(cfg.get("backend") or "torch")
    kpd_ckpt = OmegaConf.select(cfg, "kpd_ckpt", default=None, throw_on_missing=backend == "torch")
    det_over = check_detector_overrides(to_plain(cfg.get("detector_overrides")), ValueError)
    det_opts = candidate_options(cfg.get("candidates", 1), cfg.detector_ckpt, ValueError, det_over)
    pipeline = PosePipeline.for_backend(backend, detector_ckpt=cfg.detector_ckpt, kpd_ckpt=kpd_ckpt,
                                        export_dir=cfg.get("export_dir"), pnp=pnp_cfg, top_l=top_l,
                                        device=cfg.device, obj_ids=obj_ids,
                                        refine_boxes=to_int(cfg.get("refine_boxes", 0) or 0, "refine_boxes"),
                                        box_scale=cfg_float(cfg, "box_scale", 1.0),
                                        crop_tta=to_plain(cfg.get("crop_tta", 1)),
                                        depth_calibration=_depth_calibration(cfg.get("depth_calibration", 1.0)),
                                        **det_opts)
    covered = sorted(int(o) for o in pipeline.kpd.keypoints_3d)
    wanted = obj_ids if obj_ids is not None else covered
    missing = sorted(set(wanted) - set(covered))
    if missing:
        raise ValueError(f"data.obj_ids {missing} are not covered by the KPD checkpoint {kpd_ckpt or cfg.export_dir} "
                         f"(it covers {covered})")
    ds = BopDataset(root, cfg.data.split, obj_ids=wanted, targets=targets)
    pipeline.set_refiner(build_refiner(to_plain(cfg.get("refiner")), lambda: ds.load_models(wanted),
                                       source=f"{ds.models_dir}"))
    oracle = str(cfg.detector_ckpt) == "oracle"
    oracle_box = check_oracle_box(cfg.get("oracle_box"))
    info = {"targets": targets, "detector": str(cfg.detector_ckpt), "kpd": str(kpd_ckpt), "pnp": pnp_cfg,
            "top_l": top_l, "refine_boxes": pipeline.refine_boxes, "box_scale": pipeline.box_scale,
            **({"crop_tta": crop_tta_record(pipeline.crop_tta, pipeline.crop_tta_stability)} if pipeline.crop_tta > 1 else {}),
            **({"candidates": candidates_record(*pipeline.candidate_spec)} if pipeline.candidate_spec.verifies else {}),
            "depth_calibration": _depth_calibration(cfg.get("depth_calibration", 1.0)), "device": str(pipeline.device),
            **({"refiner": pipeline.refiner.settings()} if pipeline.refiner is not None else {}),
            **({"detector_overrides": det_over} if det_over and str(cfg.detector_ckpt) != "oracle" else {}),
            **({"oracle_box": oracle_box} if oracle and oracle_box != DEFAULT_BOX_FIELD else {})}
    if backend != "torch":
        info.update(backend=backend, export_dir=str(cfg.export_dir))
    metrics = evaluate(pipeline, ds, out_dir, oracle=oracle, oracle_box=oracle_box,
                       batch_size=cfg_int(cfg, "batch_size"), max_frames=cfg.data.max_frames,
                       n_overlays=cfg_int(cfg, "overlays"), run_info=info, progress=bool(cfg.progress),
                       extra_metrics=extra_metrics, shard=to_int(cfg.get("shard", 0), "shard"),
                       num_shards=to_int(cfg.get("num_shards", 1), "num_shards"), merge=bool(cfg.get("merge", False)),
                       refiner_ceiling=bool(cfg.get("refiner_ceiling", False)))
    if bool(cfg.get("fit_depth_calibration", False)) and "mean" in metrics:
        from kpd6d.evaluation.calibration import fit_depth_calibration, write_depth_calibration

        applied = _depth_calibration(cfg.get("depth_calibration", 1.0))
        try:
            fit = fit_depth_calibration(Path(out_dir) / "results.csv", root, cfg.data.split, applied=applied)
        except ValueError as exc:  # nothing to pair (e.g. an untrained KPD): keep what was applied, say why
            from kpd6d.pnp.estimator import parse_depth_calibration

            default, per = parse_depth_calibration(applied)
            fit = {"global": default, "per_object": per, "instances": {}, "fitted": False, "reason": str(exc)}
            _log(f"WARNING: depth calibration not fitted ({exc}); the record keeps the factors applied")
        path = write_depth_calibration(fit, Path(out_dir) / "depth_calibration.json")
        _log(f"depth calibration of {root}/{cfg.data.split}: {path} (all objects: {fit['global']:.4f})")
    return metrics


def _depth_calibration(value):
    """A config's ``depth_calibration`` as the pipelines take it (a number, a mapping or a file path)."""
    return 1.0 if value is None else to_plain(value)


def _eval_cfg(cfg, root: Path, split: str, det, kpd, max_frames="run", **over):
    """A conf/evaluate.yaml-shaped config from a kpd6d-run config (``over`` replaces entries;
    ``max_frames``: the run's ``evaluate.max_frames`` unless given)."""
    from omegaconf import OmegaConf

    from kpd6d.config import ConfigError
    from kpd6d.detection.detectors import check_detector_overrides
    from kpd6d.pnp.estimator import candidates_record, check_candidates, check_crop_tta, crop_tta_record

    return OmegaConf.create({
        "data": {"root": str(root), "split": split, "targets": "auto", "obj_ids": to_plain(cfg.objects.obj_ids),
                 "max_frames": cfg.evaluate.max_frames if max_frames == "run" else max_frames},
        "pnp": to_plain(cfg.pnp), "select": {"top_l": cfg.select.top_l}, "detector_ckpt": det, "kpd_ckpt": kpd,
        "batch_size": cfg_int(cfg, "evaluate.batch_size"), "refine_boxes": to_int(cfg.evaluate.get("refine_boxes", 0) or 0, "evaluate.refine_boxes"),
        "box_scale": cfg_float(cfg, "evaluate.box_scale", 1.0),
        "crop_tta": crop_tta_record(*check_crop_tta(to_plain(cfg.evaluate.get("crop_tta", 1)), ConfigError, "evaluate.crop_tta")),
        "candidates": candidates_record(*check_candidates(to_plain(cfg.evaluate.get("candidates", 1)), ConfigError,
                                                          "evaluate.candidates")),
        "detector_overrides": check_detector_overrides(to_plain(cfg.evaluate.get("detector_overrides")), ConfigError,
                                                       "evaluate.detector_overrides"),
        "depth_calibration": _depth_calibration(cfg.evaluate.get("depth_calibration", 1.0)),
        "refiner": to_plain(cfg.evaluate.get("refiner")),
        "oracle_box": str(cfg.evaluate.get("oracle_box") or DEFAULT_BOX_FIELD),
        "refiner_ceiling": bool(cfg.evaluate.get("refiner_ceiling", False)),
        "device": None, "overlays": cfg_int(cfg, "evaluate.overlays"), "progress": bool(cfg.progress), **over,
    })


def _evaluate(cfg, root: Path, det, kpd, out_dir: Path, depth_calibration=None, split: str | None = None) -> dict:
    """The run's evaluation of ``det`` + ``kpd`` on ``root``/``split`` (default ``evaluate.split``) into
    ``out_dir``, with the detector's own AP unless ``det`` is the oracle (resumes frame by frame:
    :func:`kpd6d.evaluation.runner.evaluate`)."""
    split = cfg.evaluate.split if split is None else split
    _log(f"evaluating on {root}/{split} (detector: {det})")
    over = {} if depth_calibration is None else {"depth_calibration": depth_calibration}
    ecfg = _eval_cfg(cfg, root, split, det, kpd, **over)
    extra = None
    if str(det) != "oracle":  # the detector's own AP on the same frames, per object
        _log(f"evaluating the detector on {root}/{split}")
        extra = {"detector": evaluate_detector_on(det, root, split, to_plain(cfg.objects.obj_ids),
                                                  cfg.evaluate.max_frames)}
    return run_evaluation(ecfg, out_dir, extra_metrics=extra)


YARDSTICK_KEYS = ("split", "root", "num_images", "seed", "options")


def yardstick_splits(cfg, run_dir: Path, root: Path) -> dict[str, tuple[Path, str]]:
    """``evaluate.yardsticks`` (``{name: spec}``) as ``{name: (BOP root, split)}``, generating what is to be
    generated (resumably). A spec is either ``{split: S}`` (a split of the run's data, e.g. its generated
    ``val``; with ``root: R``, of the BOP dataset at R), or ``{num_images: n, seed: s, options: {...}}``: n
    images generated into ``<run dir>/yardsticks/<name>/data/val`` with the run's ``data.options`` updated
    by ``options`` (e.g. appearance settings its training data never use) and seed s."""
    from omegaconf import OmegaConf

    from kpd6d.config import ConfigError
    from kpd6d.synth.prepare import generate_splits

    specs = to_plain(cfg.evaluate.get("yardsticks")) or {}
    if not isinstance(specs, dict):
        raise ConfigError(f"evaluate.yardsticks must map names to specs, got {specs!r}")
    out: dict[str, tuple[Path, str]] = {}
    for name, spec in specs.items():
        where = f"evaluate.yardsticks.{name}"
        if spec is None:  # a yardstick switched off (evaluate.yardsticks.NAME=null)
            continue
        if not isinstance(spec, dict):
            raise ConfigError(f"{where} must be a mapping ({', '.join(YARDSTICK_KEYS)}), got {spec!r}")
        unknown = sorted(set(spec) - set(YARDSTICK_KEYS))
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {unknown}; known: {', '.join(YARDSTICK_KEYS)}")
        generated = "num_images" in spec
        if generated and ("split" in spec or "root" in spec):
            raise ConfigError(f"{where}: either num_images (a generated split) or split / root (an existing one)")
        if not generated:
            if "seed" in spec or "options" in spec:
                raise ConfigError(f"{where}: seed and options need num_images (a generated split)")
            yroot = Path(spec["root"]) if spec.get("root") else root
            split = str(spec.get("split") or "val")
            if not (yroot / split).is_dir():
                raise ConfigError(f"{where}: split {split!r} not found in {yroot}")
            out[name] = (yroot, split)
            continue
        n = to_int(spec["num_images"], f"{where}.num_images")
        if n <= 0:
            raise ConfigError(f"{where}.num_images must be > 0, got {n}")
        options = OmegaConf.to_container(OmegaConf.merge(OmegaConf.create(to_plain(cfg.data.options) or {}),
                                                         OmegaConf.create(spec.get("options") or {})), resolve=True)
        options.setdefault("designator", None)
        yroot = Path(run_dir) / "yardsticks" / str(name) / "data"
        generate_splits(yroot, [("val", n, to_int(spec.get("seed", 0), f"{where}.seed"))],
                        models_dir=cfg.objects.models_dir, obj_ids=cfg.objects.obj_ids,
                        workers=cfg_int(cfg, "data.workers"), progress=bool(cfg.progress), options=options, log=_log)
        out[name] = (yroot, "val")
    return out


def _scores(mean: dict) -> dict:
    return {k: mean[k] for k in ("ar_mssd", "ar_mspd", "add_s_01d", "proj2d_5px") if k in mean}


def yardstick_line(name: str, entry: dict) -> str:
    """One line of a yardstick's scores (``metrics["yardsticks"][name]``): AR_MSSD / AR_MSPD per box source, %."""
    return f"yardstick {name}: " + "; ".join(
        f"{who} AR_MSSD {100 * v.get('ar_mssd', float('nan')):.1f} % AR_MSPD {100 * v.get('ar_mspd', float('nan')):.1f} %"
        for who, v in entry.items() if isinstance(v, dict))


def _auto_depth_calibration(cfg, root: Path, det, kpd, out_dir: Path) -> str:
    """``evaluate.depth_calibration=auto``: fit it on the run's synthetic validation split with the
    run's own detector and evaluation settings (``out_dir``: that evaluation and depth_calibration.json;
    a finished fit is reused)."""
    out = out_dir / "depth_calibration.json"
    if out.is_file():
        return str(out)
    if not (root / "val").is_dir():
        raise ValueError(f"evaluate.depth_calibration=auto fits on the generated validation split, and {root}/val "
                         f"does not exist (data.num_val > 0)")
    _log(f"fitting the depth calibration on {root}/val (detector: {det})")
    # fitted on the PnP poses (the refiner, which comes after the calibration, is left out)
    run_evaluation(_eval_cfg(cfg, root, "val", det, kpd, max_frames=None, depth_calibration=1.0,
                             fit_depth_calibration=True, overlays=0, refiner=None), out_dir)
    return str(out)


class _StageClock:
    """Wall time spent in each stage of a run folder, summed over every invocation that worked in it (an
    interrupted stage's time counts with its resumption's; a stage skipped because its output exists adds
    ~0): ``timings.json``, written atomically after each stage, so an interruption keeps what came before."""

    def __init__(self, path: Path, t_start: float) -> None:
        from kpd6d.io import read_json

        self.path, self.t_start, self.t0 = path, t_start, t_start
        try:
            old = read_json(path, what="stage timings") if path.is_file() else {}
        except ValueError:  # a broken record loses only the earlier invocations' times
            old = {}
        self.spent = {k: float(v) for k, v in old.items() if isinstance(v, (int, float))}  # only stages are written

    def done(self, key: str) -> None:
        from kpd6d.io import atomic_write_text

        now = time.time()
        self.spent[key] = self.spent.get(key, 0.0) + (now - self.t0)
        self.t0 = now
        atomic_write_text(self.path, json.dumps(self.spent, indent=1))

    def summary(self) -> dict:
        """The stages' summed times, ``total_s`` (their sum) and ``invocation_s`` (this invocation's wall time)."""
        return {**self.spent, "total_s": sum(self.spent.values()), "invocation_s": time.time() - self.t_start}


def run_experiment(cfg, run_dir: str | Path) -> dict:
    """Run every step into ``run_dir``; returns the evaluation metrics (also in ``run_dir/metrics.json``)."""
    from omegaconf import OmegaConf

    from kpd6d.io import atomic_write_text

    t_start = time.time()
    from kpd6d.config import check_stage_config

    if not cfg.detector_ckpt:  # settings of an earlier version: named before any data is made
        check_stage_config(cfg.detector_stage, "detector_stage")
    if not cfg.kpd_ckpt:
        check_stage_config(cfg.kpd_stage, "kpd_stage")
        _kpd_networks(cfg)  # unknown names stop the run before any data is made
        _kpd_checkpoint(cfg)
    from kpd6d.evaluation.runner import check_oracle_box

    check_oracle_box(cfg.evaluate.get("oracle_box"), "evaluate.oracle_box")
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    models = load_objects(cfg.objects)
    keypoints_file = run_dir / "keypoints.json"
    designate_keypoints(models, cfg.designator, keypoints_file, cfg.get("designator_per_object"))

    root = Path(cfg.data.root) if cfg.data.root else run_dir / "data"
    clock = _StageClock(run_dir / "timings.json", t_start)
    generate(cfg, root)
    clock.done("prepare_s")

    det = cfg.detector_ckpt or train_detector_stage(cfg, run_dir / "detector", root)
    clock.done("detector_s")
    kpd = cfg.kpd_ckpt or train_kpd_stage(cfg, run_dir / "kpd", root, keypoints_file)
    clock.done("kpd_s")

    # evaluation data: the generated test split, or a BOP dataset of real images (evaluate.data_root)
    eval_root = Path(cfg.evaluate.data_root) if cfg.evaluate.get("data_root") else root
    cal = None
    if str(cfg.evaluate.get("depth_calibration", 1.0)) == "auto":
        cal = _auto_depth_calibration(cfg, root, det, kpd, run_dir / "calibration")
        clock.done("calibration_s")
    metrics = _evaluate(cfg, eval_root, det, kpd, run_dir / "eval", cal)
    with_oracle = bool(cfg.evaluate.get("oracle")) and str(det) != "oracle"  # also with GT boxes: the KPD alone
    if with_oracle:
        oracle = _evaluate(cfg, eval_root, "oracle", kpd, run_dir / "eval_oracle", cal)
        metrics["oracle_boxes"] = {"mean": oracle["mean"], "report": str(run_dir / "eval_oracle" / "report.md")}
    clock.done("evaluate_s")
    yardsticks = {}
    for name, (yroot, ysplit) in yardstick_splits(cfg, run_dir, root).items():
        ydir = run_dir / "yardsticks" / name
        entry = {"root": str(yroot), "split": ysplit,
                 "own": _scores(_evaluate(cfg, yroot, det, kpd, ydir / "eval", cal, split=ysplit)["mean"])}
        if with_oracle:
            entry["oracle"] = _scores(_evaluate(cfg, yroot, "oracle", kpd, ydir / "eval_oracle", cal, split=ysplit)["mean"])
        yardsticks[name] = entry
        _log(yardstick_line(name, entry))
    if yardsticks:
        metrics["yardsticks"] = yardsticks
        clock.done("yardsticks_s")
    metrics["run"] = {**metrics.get("run", {}), "timings": clock.summary(),
                      "config": OmegaConf.to_container(cfg, resolve=True)}
    atomic_write_text(run_dir / "metrics.json", json.dumps(metrics, indent=1, default=float))
    return metrics
