"""Where a set of pose estimates loses its BOP19 score: the same estimates scored again with one part of
each pose taken from the ground truth (oracle substitution, a diagnosis, not a result).

For every estimate the GT instance of its object in its image nearest to it (in translation) supplies

- ``depth``: the GT depth, the estimate's translation scaled along its own viewing ray (its projected
  centre stays where it was; only the distance to the camera changes);
- ``translation``: the GT translation;
- ``rotation``: the GT rotation.

The gain of each substitution over the estimates as they are bounds what a perfect estimate of that part
would add. A monocular keypoint method typically loses most of its AR_MSSD in depth (the pattern's scale
fixes it; a 1 % scale error is 10 mm at 1 m) and most of its AR_MSPD in rotation.

:func:`refined_from_gt` asks the opposite question of a pose refiner: each GT pose refined in its own image
(``gt_refined``), scored as the estimates are. A refiner whose optimum is the truth leaves those poses near
1.0; what they lose is what the refiner takes from a perfect start (its ceiling on these images: the image
and the mesh, or the GT itself, disagree where it settles).
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from kpd6d.evaluation.bop19 import BopGt, load_bop_gt, load_eval_models, score_bop19
from kpd6d.evaluation.results_io import PoseResult

__all__ = ["LABELS", "SUBSTITUTIONS", "error_decomposition", "format_decomposition", "refined_from_gt", "substitute"]

#: the parts of a pose :func:`substitute` can take from the ground truth
SUBSTITUTIONS = ("depth", "translation", "rotation")
#: how reports name the rows of :func:`error_decomposition`
LABELS = {"estimated": "as estimated", "depth": "depth from the GT (along each estimate's ray)",
          "translation": "translation from the GT", "rotation": "rotation from the GT",
          "gt_refined": "the GT pose, refined (the refiner's ceiling)"}


def substitute(results: Sequence[PoseResult], gt: BopGt, part: str) -> list[PoseResult]:
    """Copies of ``results`` with ``part`` (one of :data:`SUBSTITUTIONS`) of each pose taken from the nearest
    GT instance of its object in its image; estimates with no such instance (or, for ``depth``, not in front of
    the camera) are copied unchanged."""
    if part not in SUBSTITUTIONS:
        raise ValueError(f"substitute: part={part!r} unknown; known: {', '.join(SUBSTITUTIONS)}")
    out = []
    for r in results:
        R, t = np.array(r.R, float), np.array(r.t, float)
        cands = [g for g in gt.instances.get((r.scene_id, r.im_id), []) if g.obj_id == r.obj_id]
        if cands:
            g = min(cands, key=lambda g: float(np.linalg.norm(g.t - t)))
            if part == "rotation":
                R = g.R.copy()
            elif part == "translation":
                t = g.t.copy()
            elif t[2] > 0:
                t = t * (g.t[2] / t[2])
        out.append(PoseResult(r.scene_id, r.im_id, r.obj_id, r.score, R, t, r.time))
    return out


def error_decomposition(results: Sequence[PoseResult], root: str | os.PathLike, split: str = "test",
                        targets_filename: str = "test_targets_bop19.json", visib_gt_min: float = -1.0,
                        models: dict[int, dict] | None = None, gt: BopGt | None = None) -> dict:
    """BOP19 AR_MSSD / AR_MSPD of ``results`` as they are (``estimated``) and with each part of
    :data:`SUBSTITUTIONS` taken from the ground truth: ``{name: {"ar_mssd": .., "ar_mspd": ..}}``. Arguments
    as :func:`kpd6d.evaluation.bop19.score_bop19`."""
    gt = gt if gt is not None else load_bop_gt(root, split, targets_filename)
    models = models if models is not None else load_eval_models(root)
    kw = dict(split=split, targets_filename=targets_filename, visib_gt_min=visib_gt_min, models=models, gt=gt)
    out = {}
    for name in ("estimated", *SUBSTITUTIONS):
        s = score_bop19(results if name == "estimated" else substitute(results, gt, name), root, **kw)
        out[name] = {"ar_mssd": s["ar_mssd"], "ar_mspd": s["ar_mspd"]}
    return out


def refined_from_gt(refiner, frames: Iterable, instances: Callable | None = None) -> list[PoseResult]:
    """Each GT instance's pose refined by ``refiner`` (anything with ``refine_poses(images, Ks, poses)``, e.g.
    :class:`kpd6d.refinement.RegionRefiner`) in its own image, as BOP results (score 1, the frame's refine time):
    ``frames`` are :class:`kpd6d.data.BopFrame` s, ``instances(frame)`` the GT instances to refine (default all).
    Poses the refiner finds too little evidence for stay at the truth, as in a pipeline."""
    out = []
    for f in frames:
        insts = list(instances(f) if instances is not None else f.instances)
        if not insts:
            continue
        poses = [{"obj_id": int(i.obj_id), "R": np.array(i.R, np.float64).reshape(3, 3),
                  "t": np.array(i.t, np.float64).reshape(3), "ok": True} for i in insts]
        t0 = time.perf_counter()
        refiner.refine_poses([f.load_rgb()], np.asarray(f.K, np.float64)[None], [poses])
        dt = time.perf_counter() - t0
        out += [PoseResult(f.scene_id, f.im_id, p["obj_id"], 1.0, np.asarray(p["R"], np.float64),
                           np.asarray(p["t"], np.float64), dt) for p in poses]
    return out


def format_decomposition(dec: dict) -> str:
    """:func:`error_decomposition`'s result as a plain-text table (AR in %)."""
    w = max(len(LABELS.get(k, k)) for k in dec)
    rows = [f"{'poses':<{w}}  AR_MSSD  AR_MSPD"]
    rows += [f"{LABELS.get(k, k):<{w}}  {100 * v['ar_mssd']:7.1f}  {100 * v['ar_mspd']:7.1f}" for k, v in dec.items()]
    return "\n".join(rows)
