"""Depth calibration: the factor by which a pose estimator's translations are too long, fitted on
labelled (synthetic) data.

A heatmap KPD trained for minutes pulls its keypoints toward where keypoints usually lie in the
crop: the predicted keypoints of an object spread less than the true ones, and PnP then puts the
object too far from the camera (docs/benchmarks.md, session 9: spread 0.93, depth +8-11 % on
synthetic validation). The bias is systematic, so it can be measured where the ground truth is
known — the synthetic validation split, never the real test frames — and removed from the
estimates: ``t <- s * t`` with ``s`` per object (``depth_calibration`` of the pose pipelines,
:func:`kpd6d.pnp.estimator.parse_depth_calibration`). Scaling ``t`` moves the object along its viewing
ray: its projected centre stays where it is, its projected size changes by ``1 / s``.

:func:`fit_depth_calibration` pairs each estimate of a BOP results file with the ground-truth instance of
the same object in the same image whose projected centre is nearest (and near enough: within
``max_centre_error`` object diameters at the instance's depth, so a pose of the wrong instance or a
wild one does not enter), and takes the median of ``(t_gt . t_est) / |t_est|^2`` (the least-squares
scale along the estimated ray) over all objects, or per object.
"""

from __future__ import annotations

import json
import os
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["fit_depth_calibration", "write_depth_calibration"]


def _load_results(results) -> list:
    from kpd6d.evaluation.results_io import read_bop_results

    if isinstance(results, (str, os.PathLike)):
        return read_bop_results(results)
    return list(results)


def _diameters(root: Path) -> dict[int, float]:
    path = root / "models" / "models_info.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file does not exist (the depth calibration needs the object diameters)")
    info = json.loads(path.read_text())
    try:
        return {int(k): float(v["diameter"]) for k, v in info.items()}
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: every entry needs a numeric 'diameter' ({exc})") from None


def fit_depth_calibration(results, root: str | os.PathLike, split: str = "val", *, per_object: bool = False,
                          min_instances: int = 10, max_centre_error: float = 0.25, min_visib_fract: float = 0.1,
                          applied: Any = 1.0) -> dict:
    """Depth factors from the estimates in ``results`` (a BOP results CSV or
    :class:`~kpd6d.evaluation.results_io.PoseResult` list) against the ground truth of the BOP
    dataset ``root`` / ``split``.

    Returns ``{"fitted": True, "global": s, "per_object": {obj_id: s}, "median_per_object": {obj_id: s},
    "instances": {obj_id: n}, "iqr": {obj_id: [q25, q75]}, "settings": {...}}``: ``global`` is the
    median over every paired instance. ``per_object=True`` gives each object with at least
    ``min_instances`` pairs its own factor (``per_object``); by default every object takes the global
    one, which did better on held-out synthetic frames at ~50 pairs per object (docs/benchmarks.md,
    session 10); ``median_per_object`` always reports the per-object medians. ``applied``: the
    ``depth_calibration`` the estimates were made with (the fitted factors are absolute: applied x
    measured). The record is what ``depth_calibration=<file>`` of kpd6d-evaluate / kpd6d-predict reads.
    """
    from kpd6d.data import BopDataset
    from kpd6d.pnp.estimator import parse_depth_calibration

    root = Path(root)
    default, per_applied = parse_depth_calibration(applied)
    diameters = _diameters(root)
    est_by_frame: dict[tuple[int, int], list] = defaultdict(list)
    for r in _load_results(results):
        if np.isfinite(r.t).all() and r.t[2] > 0:
            est_by_frame[(int(r.scene_id), int(r.im_id))].append(r)
    ratios: dict[int, list[float]] = defaultdict(list)
    for frame in BopDataset(root, split, targets=None):
        ests = est_by_frame.get((frame.scene_id, frame.im_id))
        if not ests:
            continue
        K = np.asarray(frame.K, dtype=np.float64).reshape(3, 3)
        for e in ests:
            oid = int(e.obj_id)
            if oid not in diameters:
                raise ValueError(f"{root / 'models' / 'models_info.json'}: no diameter for object {oid}")
            uv_e = (K @ e.t)[:2] / e.t[2]
            best, best_d = None, np.inf
            for inst in frame.instances:
                if int(inst.obj_id) != oid or (inst.visib_fract is not None and inst.visib_fract < min_visib_fract):
                    continue
                t_g = np.asarray(inst.t, dtype=np.float64).reshape(3)
                if t_g[2] <= 0:
                    continue
                d = float(np.linalg.norm((K @ t_g)[:2] / t_g[2] - uv_e))
                if d < best_d:
                    best, best_d = t_g, d
            if best is None or best_d > max_centre_error * K[0, 0] * diameters[oid] / best[2]:
                continue
            s_applied = per_applied.get(oid, default)
            ratios[oid].append(s_applied * float(best @ e.t) / float(e.t @ e.t))
    every = [r for rs in ratios.values() for r in rs]
    if not every:
        raise ValueError(f"no estimate in the results could be paired with a ground-truth instance of {root} / "
                         f"{split} (are they of this dataset and split?)")
    return {
        "fitted": True,
        "global": float(np.median(every)),
        "per_object": {int(o): float(np.median(rs)) for o, rs in sorted(ratios.items())
                       if per_object and len(rs) >= min_instances},
        "median_per_object": {int(o): float(np.median(rs)) for o, rs in sorted(ratios.items())},
        "instances": {int(o): len(rs) for o, rs in sorted(ratios.items())},
        "iqr": {int(o): [float(np.percentile(rs, 25)), float(np.percentile(rs, 75))] for o, rs in sorted(ratios.items())},
        "settings": {"root": str(root), "split": split, "per_object": bool(per_object),
                     "min_instances": int(min_instances),
                     "max_centre_error": float(max_centre_error), "min_visib_fract": float(min_visib_fract)},
    }


def write_depth_calibration(fit: dict, path: str | os.PathLike) -> Path:
    """Write a :func:`fit_depth_calibration` record as JSON (atomically)."""
    from kpd6d.io import atomic_write_text

    return atomic_write_text(path, json.dumps(fit, indent=2) + "\n")
