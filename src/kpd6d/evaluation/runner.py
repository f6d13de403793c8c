"""The evaluation loop: run a :class:`~kpd6d.pipeline.PosePipeline` over a BOP dataset and write
``metrics.json``, ``results.csv`` (BOP format), ``report.md``, accuracy plots and overlays.

Per evaluated GT instance (all instances of a frame, or with a targets file the ``inst_count`` most
visible instances of each target object): ADD(-S) (ADD-S for symmetric objects) and the 2D
projection error of the matched prediction (for symmetric objects its minimum over the object's
symmetry transforms, as BOP's MSPD treats symmetries); an instance with no prediction (not detected, or PnP
not ok) gets infinite errors, i.e. counts as a failure. Predictions are matched to instances of the
same object greedily in score order, each taking the free instance with the lowest ADD(-S).

Predictions are appended to ``predictions.jsonl`` frame by frame; running again on the same
``out_dir`` skips the frames already there (resume after interruption).

In shards (``shard=i, num_shards=n``): the frames are cut into the single job's batches and batch
``b`` goes to shard ``b % n`` (:func:`frame_shards`), so every frame is predicted in the same batch
as in the single job. A shard writes only its predictions, into
``<out_dir>/shards/shard-i-of-n/`` (``predictions.jsonl``, ``settings.json``, and once finished the
marker ``shard.json``, atomically); it resumes like a single job. ``merge=True`` checks that every
shard finished with the same settings and that every frame was predicted exactly once, writes the
union as ``<out_dir>/predictions.jsonl`` and computes everything else from it as the single job does:
the same results.csv rows and metrics (all but the measured times).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from kpd6d.data.bop_io import BOX_FIELDS, DEFAULT_BOX_FIELD
from kpd6d.evaluation.errors import (
    add_error,
    adds_error,
    depth_ratio,
    keypoint_errors,
    proj2d_error,
    symmetry_transforms,
)
from kpd6d.evaluation.recall import add_s_accuracy, auc, proj2d_accuracy, recall_at
from kpd6d.evaluation.results_io import PoseResult, read_bop_results, write_bop_results
from kpd6d.geometry import clip_xywh_to_image
from kpd6d.io import atomic_write_image, atomic_write_json, atomic_write_text, read_json

__all__ = ["ADD_THRESHOLDS", "DEPTH_VISIBILITY_BANDS", "PX_THRESHOLDS", "ShardMergeError", "compute_metrics",
           "depth_by_visibility", "eval_instances", "evaluate", "frame_shards", "match_predictions"]

PX_THRESHOLDS = np.linspace(0.0, 50.0, 51)  # 2D projection accuracy curve (px)
ADD_THRESHOLDS = np.linspace(0.0, 0.5, 51)  # ADD(-S) accuracy curve (fraction of the diameter)
MAX_EVAL_POINTS = 5000



def eval_instances(frame) -> list:
    """The GT instances a frame is evaluated on (targets: the inst_count most visible per target object)."""
    if not frame.targets:
        return list(frame.instances)
    out = []
    for oid, count in frame.targets.items():
        insts = [i for i in frame.instances if i.obj_id == oid]
        insts.sort(key=lambda i: -(i.visib_fract if i.visib_fract is not None else 1.0))
        out.extend(insts[:count])
    return out


def check_oracle_box(value, key: str = "oracle_box") -> str:
    """``value`` (None: :data:`~kpd6d.data.bop_io.DEFAULT_BOX_FIELD`) as a GT box field (:data:`~kpd6d.data.bop_io.BOX_FIELDS`); a ValueError names ``key`` otherwise."""
    box = str(value or DEFAULT_BOX_FIELD)
    if box not in BOX_FIELDS:
        raise ValueError(f"{key}={value!r}: must be one of {', '.join(BOX_FIELDS)}")
    return box


def oracle_targets(frame, instances, box: str = DEFAULT_BOX_FIELD, image_size: tuple[int, int] | None = None) -> dict:
    """GT boxes of ``instances`` for the oracle detector: ``box="bbox_visib"`` the visible box (the object's box
    when no scene_gt_info), ``"bbox_obj"`` the whole object's box clipped to the ``image_size`` (width, height)
    image (what an amodal detector, ``detector_stage.box=bbox_obj``, gives). Instances with an empty visible box
    get none (fully occluded: not detected)."""
    check_oracle_box(box, "oracle box")
    if box == "bbox_obj" and image_size is None:
        raise ValueError("oracle_targets: box='bbox_obj' needs the image_size to clip the boxes to")
    boxes, ids = [], []
    for inst in instances:
        vis = inst.bbox_visib if inst.bbox_visib is not None else inst.bbox_obj
        if vis is None or np.asarray(vis)[2:].min() <= 0:
            continue  # not visible at all: the oracle has no box to give (counts as not detected)
        b = np.asarray(vis, dtype=np.float64)
        if box == "bbox_obj" and inst.bbox_obj is not None:
            clipped = clip_xywh_to_image(inst.bbox_obj, *image_size, min_size=0.0)
            b = clipped if clipped is not None and clipped[2:].min() > 0 else b
        boxes.append(b.astype(np.float32))
        ids.append(inst.obj_id)
    return {"boxes": np.asarray(boxes, np.float32).reshape(-1, 4), "obj_ids": np.asarray(ids, np.int64)}


def _eval_points(model) -> np.ndarray:
    v = model.vertices
    if len(v) > MAX_EVAL_POINTS:
        v = v[np.random.default_rng(0).choice(len(v), MAX_EVAL_POINTS, replace=False)]
    return v


def match_predictions(instances, preds: Sequence[dict], points: dict, symmetric: dict, K,
                      symmetries: dict | None = None) -> list[tuple[float, float]]:
    """(ADD(-S) mm, 2D projection px) for every instance; unmatched instances get (inf, inf).

    ``symmetries``: {obj_id: (S, 4, 4) transforms} (:func:`~kpd6d.evaluation.errors.symmetry_transforms`);
    an object listed there gets the symmetric 2D projection error (minimum over its symmetries)."""
    return [(add, proj) for _, add, proj in _assign(instances, preds, points, symmetric, K, symmetries)]


def _assign(instances, preds, points, symmetric, K, symmetries) -> list[tuple[int | None, float, float]]:
    """:func:`match_predictions` with the index into ``preds`` of each instance's match (None: unmatched):
    the ok predictions by falling score, each to the free instance of its object it is nearest (ADD(-S))."""
    symmetries = symmetries or {}
    out: list[tuple[int | None, float, float]] = [(None, np.inf, np.inf)] * len(instances)
    free = set(range(len(instances)))
    for i in sorted((i for i, p in enumerate(preds) if p.get("ok", True)), key=lambda i: -preds[i]["score"]):
        p = preds[i]
        cands = [j for j in free if instances[j].obj_id == p["obj_id"]]
        if not cands:
            continue
        f = adds_error if symmetric[p["obj_id"]] else add_error
        pts = points[p["obj_id"]]
        add = [f(p["R"], p["t"], instances[j].R, instances[j].t, pts) for j in cands]
        j = cands[int(np.argmin(add))]
        out[j] = (i, float(min(add)), proj2d_error(p["R"], p["t"], instances[j].R, instances[j].t, pts, K,
                                                   symmetries.get(p["obj_id"])))
        free.discard(j)
    return out


def compute_metrics(records: list[dict], diameters: dict[int, float], names: dict[int, str] | None = None,
                    symmetric: dict[int, bool] | None = None) -> dict:
    """Per-object and mean metrics from ``records`` = [{obj_id, add, proj}] (errors; inf = failure)."""
    names, symmetric = names or {}, symmetric or {}
    per_object = {}
    for oid in sorted({r["obj_id"] for r in records}):
        add = np.array([r["add"] for r in records if r["obj_id"] == oid], dtype=np.float64)
        proj = np.array([r["proj"] for r in records if r["obj_id"] == oid], dtype=np.float64)
        d = diameters[oid]
        per_object[str(oid)] = {
            "name": names.get(oid, ""), "symmetric": bool(symmetric.get(oid, False)), "n": len(add),
            "failures": int((~np.isfinite(add)).sum()),
            "add_s_01d": add_s_accuracy(add, d, 0.1), "proj2d_5px": proj2d_accuracy(proj, 5.0),
            "proj2d_10px": proj2d_accuracy(proj, 10.0), "proj2d_15px": proj2d_accuracy(proj, 15.0),
            "auc_add_s": auc(add / d, 0.5), "auc_proj2d": auc(proj, 50.0),
            "curves": {"proj2d": recall_at(proj, PX_THRESHOLDS).tolist(),
                       "add_s": recall_at(add / d, ADD_THRESHOLDS).tolist()},
        }
        kp = _keypoint_summary([r["kp"] for r in records if r["obj_id"] == oid and "kp" in r])
        if kp:
            per_object[str(oid)]["keypoints"] = kp
    objs = list(per_object.values())

    def mean(key):
        return float(np.mean([o[key] for o in objs])) if objs else 0.0

    out = {
        "per_object": per_object,
        "mean": {
            "n": int(sum(o["n"] for o in objs)),
            "add_s_01d": mean("add_s_01d"), "proj2d_5px": mean("proj2d_5px"),
            "proj2d_10px": mean("proj2d_10px"), "proj2d_15px": mean("proj2d_15px"),
            "auc_add_s": mean("auc_add_s"), "auc_proj2d": mean("auc_proj2d"),
            "curves": {k: np.mean([o["curves"][k] for o in objs], axis=0).tolist() if objs else []
                       for k in ("proj2d", "add_s")},
        },
        "curves": {"proj2d_thresholds": PX_THRESHOLDS.tolist(), "add_s_thresholds": ADD_THRESHOLDS.tolist()},
        "failures": int(sum(o["failures"] for o in objs)),
    }
    kp_objs = [o["keypoints"] for o in objs if "keypoints" in o]
    if kp_objs:  # means over the objects, as the other means
        out["mean"]["keypoints"] = {"n": int(sum(k["n"] for k in kp_objs)),
                                    **{key: float(np.mean([k[key] for k in kp_objs])) for key in ("err_px", "centroid_px", "scale")}}
    return out


#: Bands of the GT visible fraction for :func:`depth_by_visibility`: [lo, hi) each, the last one closed.
DEPTH_VISIBILITY_BANDS = ((0.0, 0.5), (0.5, 0.8), (0.8, 0.95), (0.95, 1.0))


def depth_by_visibility(records: list[dict], bands=DEPTH_VISIBILITY_BANDS, within: float = 0.02) -> list[dict]:
    """The matched estimates' depth ratio (:func:`~kpd6d.evaluation.errors.depth_ratio`, estimated / true depth of
    the object's centroid) by the GT instance's visible fraction: per band ``lo``, ``hi``, ``n``, ``median``,
    ``q25``, ``q75`` and ``within`` (the share within ``within`` of the true depth). Records without a visible
    fraction or a finite ratio are left out; a band without records has n 0 and NaN statistics."""
    rows = [(r["visib_fract"], r["depth_ratio"]) for r in records
            if r.get("visib_fract") is not None and np.isfinite(r.get("depth_ratio", np.nan))]
    vis = np.array([v for v, _ in rows], dtype=np.float64)
    ratio = np.array([d for _, d in rows], dtype=np.float64)
    out = []
    for k, (lo, hi) in enumerate(bands):
        sel = (vis >= lo) & ((vis <= hi) if k == len(bands) - 1 else (vis < hi))
        r = ratio[sel]
        stats = ({"median": float(np.median(r)), "q25": float(np.percentile(r, 25)), "q75": float(np.percentile(r, 75)),
                  "within": float(np.mean(np.abs(r - 1.0) <= within))} if len(r)
                 else dict.fromkeys(("median", "q25", "q75", "within"), float("nan")))
        out.append({"lo": float(lo), "hi": float(hi), "n": len(r), **stats})
    return out


def _keypoint_summary(errs: list[dict]) -> dict:
    """Medians over an object's matched instances of :func:`~kpd6d.evaluation.errors.keypoint_errors`
    (instances with NaN values left out); {} when there are none."""
    rows = np.array([[e["err_px"], e["centroid_px"], e["scale"]] for e in errs], dtype=np.float64).reshape(-1, 3)
    rows = rows[np.isfinite(rows).all(axis=1)]
    if not len(rows):
        return {}
    med = np.median(rows, axis=0)
    return {"n": len(rows), "err_px": float(med[0]), "centroid_px": float(med[1]), "scale": float(med[2])}


def _load_done(path: Path) -> dict[tuple[int, int], dict]:
    done = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut by an interruption: that frame is redone
            done[(rec["scene_id"], rec["im_id"])] = rec
    return done


def _batches(frames, batch_size):
    """Consecutive frames with one image size (read from the image when loaded)."""
    for i in range(0, len(frames), batch_size):
        yield frames[i:i + batch_size]


_SETTINGS_FILE = "settings.json"


def _settings(run_info: dict | None, oracle: bool) -> dict:
    """What made a set of predictions: ``run_info`` minus the device, plus ``oracle`` (as JSON reads it)."""
    return json.loads(json.dumps({k: v for k, v in (run_info or {}).items() if k != "device"} | {"oracle": oracle},
                                 default=str))


def _check_resumable(out_dir: Path, run_info: dict | None, oracle: bool) -> None:
    """Predictions in ``out_dir`` are reused only when they were made with the same settings
    (``run_info`` minus the device): rerunning with another solver, top-l, refinement or checkpoint
    into the same folder is an error that names the differences, never a silent mix."""
    settings = _settings(run_info, oracle)
    path = out_dir / _SETTINGS_FILE
    if path.is_file():
        old = json.loads(path.read_text())
        diff = sorted(k for k in set(old) | set(settings) if old.get(k) != settings.get(k))
        if diff:
            raise ValueError(f"{out_dir} holds predictions made with other settings ({', '.join(diff)}: "
                             + "; ".join(f"{k} was {old.get(k)!r}, now {settings.get(k)!r}" for k in diff)
                             + "); evaluate into a new folder")
    elif (out_dir / "predictions.jsonl").is_file():
        raise ValueError(f"{out_dir} holds predictions.jsonl without {_SETTINGS_FILE}: cannot tell which settings "
                         "made them; evaluate into a new folder")
    else:
        atomic_write_json(path, settings)


def evaluate(pipeline, dataset, out_dir: str | os.PathLike, *, oracle: bool = False, batch_size: int = 1,
             max_frames: int | None = None, n_overlays: int = 6, run_info: dict | None = None, progress: bool = True,
             extra_metrics: dict | None = None, shard: int = 0, num_shards: int = 1, merge: bool = False,
             oracle_box: str = DEFAULT_BOX_FIELD, refiner_ceiling: bool = False) -> dict:
    """Evaluate ``pipeline`` on ``dataset`` (a :class:`kpd6d.data.BopDataset`); writes everything to ``out_dir``.

    ``oracle``: give the detector the GT boxes (for the ``oracle`` detector), ``oracle_box`` which
    (:func:`oracle_targets`). BOP19 AR_MSSD / AR_MSPD
    are computed on the evaluated frames only (their targets are written to
    ``test_targets_bop19.json`` in ``out_dir``). ``extra_metrics`` (e.g. ``{"detector": {...}}``, the
    detector's own AP on the same frames) go into metrics.json and the report. Returns the metrics dict.

    ``shard`` / ``num_shards`` (> 1): predict only this shard's frames (:func:`frame_shards`) into
    ``<out_dir>/shards/shard-<shard>-of-<num_shards>/`` and return ``{"shard", "num_shards", "frames",
    "out_dir"}``; no metrics. ``merge=True`` (with ``num_shards``): gather the finished shards'
    predictions (a :class:`ShardMergeError` names an unfinished shard, other settings, a missing or
    duplicated frame) and write everything the single job writes.

    ``refiner_ceiling`` (with a pipeline that has a ``refiner``): the decomposition also scores the GT poses of
    the evaluated instances refined in their images (``gt_refined``, :func:`kpd6d.evaluation.decompose.refined_from_gt`).
    """
    from kpd6d.evaluation.bop19 import load_bop_gt, load_eval_models, score_bop19, score_bop19_file
    from kpd6d.evaluation.decompose import error_decomposition, refined_from_gt
    from kpd6d.evaluation.report import plot_curves, write_report_md
    from kpd6d.visualize import draw_overlay

    out_dir = Path(out_dir)
    data_root = Path(dataset.root).resolve()
    if out_dir.resolve() == data_root or data_root in out_dir.resolve().parents:
        raise ValueError(f"evaluate: the output folder {str(out_dir)!r} is inside the dataset {str(dataset.root)!r}; "
                         "outputs never go into an input dataset (they would overwrite its files, e.g. "
                         "test_targets_bop19.json): choose an out_dir outside it")
    shard, num_shards = _check_shard(shard, num_shards, merge)
    out_dir.mkdir(parents=True, exist_ok=True)
    frames = list(dataset)[: max_frames if max_frames else None]
    if not frames:
        raise ValueError(f"{dataset!r}: no frames to evaluate")
    if num_shards > 1 and not merge:
        return _evaluate_shard(pipeline, frames, out_dir, shard, num_shards, batch_size=batch_size, oracle=oracle,
                               run_info=run_info, progress=progress, oracle_box=oracle_box)
    obj_ids = sorted({i.obj_id for f in frames for i in eval_instances(f)})
    models = {m.obj_id: m for m in dataset.load_models(obj_ids)}
    points = {o: _eval_points(m) for o, m in models.items()}
    symmetric = {o: m.is_symmetric for o, m in models.items()}
    symmetries = {o: symmetry_transforms(m) for o, m in models.items() if m.is_symmetric}
    keypoints_3d = {int(o): np.asarray(v, np.float64) for o, v in (getattr(getattr(pipeline, "kpd", None),
                                                                           "keypoints_3d", None) or {}).items()}

    pred_path = out_dir / "predictions.jsonl"
    _check_resumable(out_dir, run_info, oracle)
    if merge:  # the shards' predictions, checked, become this folder's predictions.jsonl
        _merge_shard_predictions(out_dir, frames, num_shards, _settings(run_info, oracle), pred_path)
    _predict_frames(pipeline, frames, pred_path, batch_size=batch_size, oracle=oracle, progress=progress,
                    oracle_box=oracle_box)
    done = _load_done(pred_path)

    # errors and metrics
    records, results = [], []
    for f in frames:
        rec = done[(f.scene_id, f.im_id)]
        preds = [{**p, "R": np.asarray(p["R"], float), "t": np.asarray(p["t"], float)} for p in rec["preds"]]
        insts = eval_instances(f)
        for inst, (i, add, proj) in zip(insts, _assign(insts, preds, points, symmetric, f.K, symmetries)):
            rec_i = {"scene_id": f.scene_id, "im_id": f.im_id, "obj_id": inst.obj_id, "add": add, "proj": proj}
            if i is not None:  # the matched estimate's depth against the truth, by how much of the object is seen
                rec_i["depth_ratio"] = depth_ratio(preds[i]["R"], preds[i]["t"], inst.R, inst.t, points[inst.obj_id])
                rec_i["visib_fract"] = inst.visib_fract
            kp3d = keypoints_3d.get(inst.obj_id)
            if i is not None and "kp" in preds[i] and kp3d is not None:  # the keypoints that made the pose
                rec_i["kp"] = keypoint_errors(preds[i]["kp"], kp3d, inst.R, inst.t, f.K, symmetries.get(inst.obj_id))
            records.append(rec_i)
        for p in preds:
            if p["ok"]:
                results.append(PoseResult(f.scene_id, f.im_id, p["obj_id"], p["score"], p["R"], p["t"], rec["time"]))
    metrics = compute_metrics(records, {o: m.diameter for o, m in models.items()},
                              {o: m.name for o, m in models.items()}, symmetric)
    metrics["depth_by_visibility"] = depth_by_visibility(records)
    write_bop_results(out_dir / "results.csv", results)

    # BOP19 scores of the written results.csv, on the evaluated frames' targets (the dataset's targets
    # file when it was read with one, else derived from the GT: instances with visib_fract >= 0.1)
    tg: dict[tuple[int, int, int], int] = {}
    for f in frames:
        if f.targets:
            for oid, c in f.targets.items():
                tg[(f.scene_id, f.im_id, oid)] = c
        else:
            for inst in f.instances:
                if inst.visib_fract is None or inst.visib_fract >= 0.1:
                    tg[(f.scene_id, f.im_id, inst.obj_id)] = tg.get((f.scene_id, f.im_id, inst.obj_id), 0) + 1
    targets_file = out_dir / "test_targets_bop19.json"
    atomic_write_json(targets_file, [{"scene_id": s, "im_id": i, "obj_id": o, "inst_count": c}
                                for (s, i, o), c in sorted(tg.items())])
    try:
        where = dict(split=dataset.split, targets_filename=str(targets_file.resolve()))
        known = dict(gt=load_bop_gt(dataset.root, **where), models=load_eval_models(dataset.root))
        bop = score_bop19_file(out_dir / "results.csv", dataset.root, **where, **known)
        bop["decomposition"] = error_decomposition(read_bop_results(out_dir / "results.csv"), dataset.root,
                                                   **where, **known)
    except Exception as exc:  # scoring is a summary; never lose the metrics above over it
        bop = {"error": f"{type(exc).__name__}: {exc}"}
    if refiner_ceiling and getattr(pipeline, "refiner", None) is not None and "decomposition" in bop:
        try:  # its own failure loses only its row
            ceil = score_bop19(refined_from_gt(pipeline.refiner, frames, eval_instances), dataset.root, **where, **known)
            bop["decomposition"]["gt_refined"] = {"ar_mssd": ceil["ar_mssd"], "ar_mspd": ceil["ar_mspd"]}
        except Exception as exc:
            bop["decomposition_error"] = f"gt_refined: {type(exc).__name__}: {exc}"
    metrics["bop19"] = {k: bop[k] for k in ("ar_mssd", "ar_mspd", "vsd", "n_targets", "decomposition", "decomposition_error", "error")
                        if k in bop}
    for oid, o in (bop.get("per_object") or {}).items():
        if oid in metrics["per_object"]:
            metrics["per_object"][oid]["ar_mssd"] = o["ar_mssd"]
            metrics["per_object"][oid]["ar_mspd"] = o["ar_mspd"]
    if "ar_mssd" in bop:
        metrics["mean"]["ar_mssd"], metrics["mean"]["ar_mspd"] = bop["ar_mssd"], bop["ar_mspd"]

    # speed
    recs = [done[(f.scene_id, f.im_id)] for f in frames]
    total = sum(r["time"] for r in recs)
    metrics["fps"] = len(recs) / total if total > 0 else None
    stage_keys = sorted({k for r in recs for k in r.get("stages", {})})
    metrics["stage_seconds_per_frame"] = {k: float(np.mean([r["stages"].get(k, 0.0) for r in recs])) for k in stage_keys}
    metrics["run"] = {**(run_info or {}), "dataset": str(dataset.root), "split": dataset.split, "frames": len(frames),
                      "batch_size": batch_size, "oracle": oracle}
    metrics.update(extra_metrics or {})
    atomic_write_json(out_dir / "metrics.json", metrics)

    # plots, overlays, report
    plot_curves(metrics, out_dir)
    corners = {o: m.bbox_corners for o, m in models.items()}
    overlays = []
    for f in frames[: max(0, int(n_overlays))]:
        rec = done[(f.scene_id, f.im_id)]
        img = draw_overlay(f.load_rgb(), f.K, corners, [(i.obj_id, i.R, i.t) for i in eval_instances(f)],
                           [(p["obj_id"], np.asarray(p["R"]), np.asarray(p["t"])) for p in rec["preds"] if p["ok"]])
        name = f"overlays/{f.scene_id:06d}_{f.im_id:06d}.png"
        atomic_write_image(out_dir / name, img)
        overlays.append(name)
    write_report_md(metrics, out_dir / "report.md", overlays)
    return metrics


# ---------------------------------------------------------------------------------------------
# predicting, in one job or in shards
# ---------------------------------------------------------------------------------------------
class ShardMergeError(ValueError):
    """The shards of a sharded evaluation do not add up to the single job's frames; the message lists
    each problem with the frame and the shard."""


def frame_shards(n_frames: int, batch_size: int, num_shards: int) -> list[int]:
    """The shard of each of ``n_frames`` frames: the single job's batches (``batch_size`` consecutive
    frames) dealt round robin, batch ``b`` to shard ``b % num_shards``."""
    bs = max(1, int(batch_size))
    return [(p // bs) % int(num_shards) for p in range(int(n_frames))]


def _check_shard(shard, num_shards, merge) -> tuple[int, int]:
    from kpd6d.config import to_int

    shard, num_shards = to_int(shard, "shard"), to_int(num_shards, "num_shards")
    if num_shards < 1:
        raise ValueError(f"num_shards must be >= 1, got {num_shards}")
    if not 0 <= shard < num_shards:
        raise ValueError(f"shard must be in 0..num_shards-1 = 0..{num_shards - 1}, got {shard}")
    if merge and num_shards < 2:
        raise ValueError("merge=true needs num_shards=<n>, the number of shards the evaluation ran in")
    return shard, num_shards


def _shard_dir(out_dir: Path, shard: int, num_shards: int) -> Path:
    return out_dir / "shards" / f"shard-{shard}-of-{num_shards}"


def _predict_frames(pipeline, frames, pred_path: Path, *, batch_size: int, oracle: bool, progress: bool,
                    desc: str = "evaluate", oracle_box: str = DEFAULT_BOX_FIELD) -> None:
    """Append the predictions of every frame of ``frames`` not yet in ``pred_path`` to it, batch by batch."""
    from tqdm import tqdm

    done = _load_done(pred_path)
    todo = [f for f in frames if (f.scene_id, f.im_id) not in done]
    if pred_path.is_file() and pred_path.stat().st_size:
        with pred_path.open("rb") as f:
            f.seek(-1, os.SEEK_END)
            cut = f.read(1) != b"\n"
        if cut:  # a line cut by an interruption: end it, so the next record starts on its own line
            with pred_path.open("a") as f:
                f.write("\n")
    if not todo:
        return
    if done and progress:
        print(f"evaluate: resuming {pred_path.parent}: {len(frames) - len(todo)} of {len(frames)} frames already in "
              f"{pred_path.name}", flush=True)
    with pred_path.open("a") as fout, tqdm(total=len(frames), initial=len(frames) - len(todo), desc=desc,
                                           unit="frame", disable=not progress) as bar:
        for batch in _batches(todo, max(1, int(batch_size))):
            images = [f.load_rgb() for f in batch]
            sizes = {im.shape for im in images}
            groups = [list(range(len(batch)))] if len(sizes) == 1 else [[i] for i in range(len(batch))]
            for g in groups:
                targets = ([oracle_targets(batch[i], eval_instances(batch[i]), oracle_box,
                                           (images[i].shape[1], images[i].shape[0])) for i in g] if oracle else None)
                t0 = time.perf_counter()
                preds = pipeline.predict_batch([images[i] for i in g], np.stack([batch[i].K for i in g]), targets)
                dt = (time.perf_counter() - t0) / len(g)
                timings = {k: v / len(g) for k, v in getattr(pipeline, "last_timings", {}).items()}
                for i, ps in zip(g, preds):
                    rec = {"scene_id": batch[i].scene_id, "im_id": batch[i].im_id, "time": dt, "stages": timings,
                           "preds": [{"obj_id": int(p["obj_id"]), "score": float(p["score"]), "ok": bool(p["ok"]),
                                      "R": np.asarray(p["R"]).tolist(), "t": np.asarray(p["t"]).tolist(),
                                      **({"refined": bool(p["refined"])} if "refined" in p else {}),
                                      **({"kp": np.round(np.asarray(p["keypoints_2d"], float), 2).tolist()}
                                         if p.get("keypoints_2d") is not None else {})} for p in ps]}
                    fout.write(json.dumps(rec) + "\n")
                    fout.flush()
                bar.update(len(g))


def _evaluate_shard(pipeline, frames, out_dir: Path, shard: int, num_shards: int, *, batch_size: int, oracle: bool,
                    run_info: dict | None, progress: bool, oracle_box: str = DEFAULT_BOX_FIELD) -> dict:
    """Predict shard ``shard``'s frames into its folder; write its marker ``shard.json`` when done."""
    sdir = _shard_dir(out_dir, shard, num_shards)
    sdir.mkdir(parents=True, exist_ok=True)
    _check_resumable(sdir, run_info, oracle)
    marker = sdir / "shard.json"
    if marker.is_file():
        marker.unlink()  # not finished until written again
    owner = frame_shards(len(frames), batch_size, num_shards)
    mine = [f for f, o in zip(frames, owner) if o == shard]
    _predict_frames(pipeline, mine, sdir / "predictions.jsonl", batch_size=batch_size, oracle=oracle,
                    progress=progress, desc=f"evaluate shard {shard}/{num_shards}", oracle_box=oracle_box)
    atomic_write_json(marker, {"shard": shard, "num_shards": num_shards, "batch_size": max(1, int(batch_size)),
                               "frames_total": len(frames), "frames": [[f.scene_id, f.im_id] for f in mine],
                               "settings": _settings(run_info, oracle)})
    return {"shard": shard, "num_shards": num_shards, "frames": len(mine), "out_dir": str(sdir)}


def _merge_shard_predictions(out_dir: Path, frames, num_shards: int, settings: dict, pred_path: Path) -> None:
    """Check the shards' predictions against ``frames`` and write them, in frame order, to ``pred_path``."""
    problems: list[str] = []
    recs: dict[tuple[int, int], dict] = {}
    owners: dict[tuple[int, int], list[int]] = {}
    batch_sizes = set()
    for i in range(num_shards):
        sdir = _shard_dir(out_dir, i, num_shards)
        marker = sdir / "shard.json"
        if not marker.is_file():
            problems.append(f"shard {i} of {num_shards} has not finished: {marker} does not exist (rerun it with "
                            f"shard={i} num_shards={num_shards} and the same settings; it resumes)")
            continue
        m = read_json(marker, what="shard marker")
        batch_sizes.add(m.get("batch_size"))
        old = m.get("settings") or {}
        diff = sorted(k for k in set(old) | set(settings) if old.get(k) != settings.get(k))
        if diff:
            problems.append(f"shard {i} of {num_shards} predicted with other settings ("
                            + "; ".join(f"{k} was {old.get(k)!r}, now {settings.get(k)!r}" for k in diff) + ")")
        if m.get("frames_total") != len(frames):
            problems.append(f"shard {i} of {num_shards} was cut from {m.get('frames_total')} frames, the merge from "
                            f"{len(frames)} (other data.split / data.max_frames / data.obj_ids?)")
        for key, rec in _load_done(sdir / "predictions.jsonl").items():
            owners.setdefault(key, []).append(i)
            recs[key] = rec
    keys = [(f.scene_id, f.im_id) for f in frames]
    bs = next(iter(batch_sizes)) if len(batch_sizes) == 1 else 1
    if len(batch_sizes) > 1:
        problems.append(f"the shards ran with different batch_size values {sorted(batch_sizes, key=str)}")
    expected = frame_shards(len(keys), bs or 1, num_shards)
    for key, want in zip(keys, expected):
        got = owners.get(key, [])
        where = f"frame (scene {key[0]}, im_id {key[1]})"
        if not got:
            problems.append(f"{where} is missing: shard {want} of {num_shards} has no prediction for it (rerun "
                            f"shard {want}; it resumes)")
        elif len(got) > 1:
            problems.append(f"{where} is duplicated: predicted by shards {', '.join(map(str, got))} (it belongs to "
                            f"shard {want})")
    for key in sorted(set(owners) - set(keys)):
        problems.append(f"frame (scene {key[0]}, im_id {key[1]}) predicted by shard {owners[key][0]} is not among the "
                        f"{len(keys)} frames evaluated (other data.split / data.max_frames?)")
    if problems:
        lines = [f"  - {p}" for p in problems[:20]] + ([f"  ... and {len(problems) - 20} more"] if len(problems) > 20 else [])
        raise ShardMergeError("\n".join([f"evaluate: the {num_shards} shards in {out_dir / 'shards'} cannot be "
                                         f"merged ({len(problems)} problem{'s' * (len(problems) > 1)}):", *lines]))
    atomic_write_text(pred_path, "".join(json.dumps(recs[k]) + "\n" for k in keys))
