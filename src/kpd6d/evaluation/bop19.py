"""BOP19 scoring of pose estimates (6D localization): AR_MSSD and AR_MSPD, as the BOP toolkit does it.

The procedure follows bop_toolkit's ``eval_calc_errors.py`` / ``eval_calc_scores.py`` /
``pose_matching.py`` / ``score.py`` for the 6D localization task (our own, vectorised code):

1. Targets ``(scene_id, im_id, obj_id, inst_count)`` come from ``test_targets_bop19.json``. For each
   target the estimates of that object in that image are sorted by descending score (stable: ties
   keep file order) and the top ``inst_count`` are kept; estimates of anything else are ignored.
2. Errors of each kept estimate w.r.t. every GT instance of the same object in the image:
   MSSD (max symmetric surface distance, mm, infinite when the centres are a diameter or more
   apart) over the vertices of the evaluation models (``models_eval/`` when present), MSPD (max
   symmetric projection distance, px, with the image's own K). Symmetries come from
   models_info.json, continuous ones discretised as the toolkit does (``max_sym_disc_step`` 0.01:
   ``ceil(pi / 0.01)`` = 315 rotations).
3. Which GT instances count (are *valid*): by default (``visib_gt_min < 0``, the toolkit's
   current default) the ``inst_count`` most visible instances of each target object, i.e. the
   targets file decides (BOP built it from the instances with visib_fract >= 0.1). With
   ``visib_gt_min >= 0`` an instance counts when its object is a target of the image and its
   ``visib_fract`` is at least that value (0.1 = BOP19's visib_gt_min re-applied to the current
   scene_gt_info.json). The official LM-O reference numbers come from the default; on lmo_full
   13 target instances have visib_fract < 0.1 in the current scene_gt_info.json.
4. Per threshold, estimates are matched greedily in score order: each takes the still unmatched
   valid GT with the lowest error strictly below the threshold. MSSD errors are divided by the
   object diameter (thresholds 0.05..0.5), MSPD errors are multiplied by 640 / image width
   (thresholds 5..50 px). Recall = matched valid GTs / valid GTs (missing estimates count as
   failures); AR = mean recall over the 10 thresholds. Per-object values use that object's GTs.

VSD needs depth images and a depth renderer; it is not computed here and the output says so.
"""

from __future__ import annotations

import os
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kpd6d.evaluation.results_io import PoseResult, read_bop_results
from kpd6d.geometry import project_points, transform_points

__all__ = [
    "MSPD_THRESHOLDS",
    "MSSD_THRESHOLDS",
    "BopGt",
    "BopScoringError",
    "GtInstance",
    "bop_symmetry_transforms",
    "format_scores_summary",
    "format_scores_table",
    "greedy_match",
    "load_bop_gt",
    "load_eval_models",
    "mspd_batch",
    "mssd_batch",
    "score_bop19",
    "score_bop19_file",
]

#: Correctness thresholds of BOP19, exactly as the toolkit builds them.
MSSD_THRESHOLDS = np.arange(0.05, 0.51, 0.05)  # fraction of the object diameter
MSPD_THRESHOLDS = np.arange(5, 51, 5).astype(np.float64)  # px at image width 640
MAX_SYM_DISC_STEP = 0.01


class BopScoringError(ValueError):
    """A dataset or results file that cannot be scored; the message names the file and field."""


@dataclass
class GtInstance:
    gt_id: int
    obj_id: int
    R: np.ndarray
    t: np.ndarray
    visib_fract: float


@dataclass
class BopGt:
    """Ground truth of one split restricted to the target images."""

    targets: dict[tuple[int, int], dict[int, int]]  # (scene, im) -> {obj_id: inst_count}
    instances: dict[tuple[int, int], list[GtInstance]]  # (scene, im) -> all GT instances
    K: dict[tuple[int, int], np.ndarray]
    im_width: dict[int, int] = field(default_factory=dict)  # scene -> image width


# ---------------------------------------------------------------------------------------------
# dataset
# ---------------------------------------------------------------------------------------------
def load_bop_gt(root: str | os.PathLike, split: str = "test",
                targets_filename: str = "test_targets_bop19.json") -> BopGt:
    """GT instances (of the target objects), K and image width of the target images (via :class:`kpd6d.data.BopDataset`)."""
    from kpd6d.data import BopDataset
    from kpd6d.data.bop_io import BopFormatError

    root = Path(root)
    if not (root / targets_filename).is_file():
        raise BopScoringError(f"{root / targets_filename}: file does not exist (BOP19 scoring needs the targets)")
    try:
        ds = BopDataset(root, split, targets=targets_filename)
    except (FileNotFoundError, BopFormatError) as exc:
        raise BopScoringError(str(exc)) from exc
    width = int(ds.camera["width"]) if ds.camera is not None else 640
    targets, instances, Ks, widths = {}, {}, {}, {}
    for f in ds:
        key = (f.scene_id, f.im_id)
        targets[key] = dict(f.targets or {})
        insts = []
        for inst in f.instances:
            if inst.visib_fract is None:
                raise BopScoringError(f"{f.scene_dir}: scene_gt_info.json is missing (needed for visib_fract)")
            insts.append(GtInstance(inst.gt_index, int(inst.obj_id), np.asarray(inst.R, float).reshape(3, 3),
                                    np.asarray(inst.t, float).reshape(3), float(inst.visib_fract)))
        instances[key] = insts
        Ks[key] = np.asarray(f.K, float).reshape(3, 3)
        widths[f.scene_id] = width
    for key in ds.targets or {}:  # targets without an annotated frame entry (all instances filtered)
        targets.setdefault(key, dict(ds.targets[key]))
        instances.setdefault(key, [])
    if not ds.targets:
        raise BopScoringError(f"{root / targets_filename}: the targets file lists no targets; nothing to score "
                              f"(a BOP19 targets file lists scene_id, im_id, obj_id, inst_count entries)")
    return BopGt(targets, instances, Ks, widths)


def bop_symmetry_transforms(info: dict, max_sym_disc_step: float = MAX_SYM_DISC_STEP) -> np.ndarray:
    """(S, 4, 4) symmetry transforms of a models_info entry, discretised as bop_toolkit does
    (:func:`kpd6d.evaluation.errors.symmetry_transforms`)."""
    from kpd6d.evaluation.errors import symmetry_transforms

    return np.asarray(symmetry_transforms(info, max_sym_disc_step=max_sym_disc_step), dtype=np.float64)


def load_eval_models(root: str | os.PathLike) -> dict[int, dict]:
    """``{obj_id: {"pts": (N, 3), "diameter": d, "syms": (S, 4, 4)}}`` from models_eval/ (else models/)."""
    from kpd6d.objects import ModelError, ObjectModel, load_models_info

    root = Path(root)
    mdir = root / "models_eval" if (root / "models_eval" / "models_info.json").is_file() else root / "models"
    try:
        info = load_models_info(mdir / "models_info.json")
    except ModelError as exc:
        raise BopScoringError(str(exc)) from exc
    out = {}
    for oid, entry in info.items():
        ply = mdir / f"obj_{oid:06d}.ply"
        if not ply.is_file():
            continue  # objects without a mesh cannot be targets; checked when they are
        try:
            pts = ObjectModel.load(ply, obj_id=oid, info=entry).vertices
        except ModelError as exc:
            raise BopScoringError(str(exc)) from exc
        out[oid] = {"pts": pts, "diameter": float(entry["diameter"]), "syms": bop_symmetry_transforms(entry),
                    "path": ply}
    if not out:
        raise BopScoringError(f"{mdir}: no obj_XXXXXX.ply meshes for the objects of models_info.json")
    return out


# ---------------------------------------------------------------------------------------------
# errors (batched over (estimate, GT) pairs)
# ---------------------------------------------------------------------------------------------
def _sym_gt_poses(R_g, t_g, syms):
    """GT poses composed with every symmetry: (P, S, 3, 3), (P, S, 3)."""
    Rs, ts = syms[:, :3, :3], syms[:, :3, 3]
    R = R_g[:, None] @ Rs[None]
    t = (R_g[:, None] @ ts[None, :, :, None])[..., 0] + t_g[:, None]
    return R, t


def _chunks(n_pairs: int, n_syms: int, n_pts: int, budget: int = 3_000_000):
    step = max(1, budget // max(1, n_syms * n_pts))
    for i in range(0, n_pairs, step):
        yield slice(i, min(n_pairs, i + step))


def mssd_batch(R_e, t_e, R_g, t_g, pts, syms) -> np.ndarray:
    """MSSD (mm) of P pose pairs: ``min_S max_x ||(R_e x + t_e) - (R_g S x + t_g)||``. Shapes (P,3,3), (P,3)."""
    R_e, t_e, R_g, t_g = (np.asarray(a, dtype=np.float64) for a in (R_e, t_e, R_g, t_g))
    out = np.empty(len(R_e))
    for sl in _chunks(len(R_e), len(syms), len(pts)):
        pe = transform_points(pts, R_e[sl], t_e[sl])  # (p, N, 3)
        Rs, ts = _sym_gt_poses(R_g[sl], t_g[sl], syms)
        pg = transform_points(pts, Rs, ts)  # (p, S, N, 3)
        d = np.linalg.norm(pe[:, None] - pg, axis=-1).max(axis=-1)  # (p, S)
        out[sl] = d.min(axis=-1)
    return out


def mspd_batch(R_e, t_e, R_g, t_g, K, pts, syms) -> np.ndarray:
    """MSPD (px) of P pose pairs with intrinsics K (3, 3) or (P, 3, 3)."""
    R_e, t_e, R_g, t_g = (np.asarray(a, dtype=np.float64) for a in (R_e, t_e, R_g, t_g))
    K = np.broadcast_to(np.asarray(K, dtype=np.float64), (len(R_e), 3, 3))
    out = np.empty(len(R_e))
    for sl in _chunks(len(R_e), len(syms), len(pts)):
        ue = project_points(pts, K[sl], R_e[sl], t_e[sl])  # (p, N, 2)
        Rs, ts = _sym_gt_poses(R_g[sl], t_g[sl], syms)
        ug = project_points(pts, K[sl][:, None], Rs, ts)  # (p, S, N, 2)
        d = np.linalg.norm(ue[:, None] - ug, axis=-1).max(axis=-1)
        out[sl] = d.min(axis=-1)
    return out


# ---------------------------------------------------------------------------------------------
# matching
# ---------------------------------------------------------------------------------------------
def greedy_match(errors: np.ndarray, valid: Sequence[bool], threshold: float) -> np.ndarray:
    """bop_toolkit's match_poses for one (image, object) and one threshold.

    ``errors`` (n_est, n_gt) with the estimates already in descending score order; each estimate
    in turn takes the unmatched valid GT with the lowest error strictly below ``threshold`` (ties:
    the lower GT index). Returns the matched GT index per estimate (-1: none).
    """
    errors = np.asarray(errors, dtype=np.float64)
    free = np.asarray(valid, dtype=bool).copy()
    out = np.full(errors.shape[0], -1, dtype=np.int64)
    for i, row in enumerate(errors):
        cand = np.where(free & (row < threshold), row, np.inf)
        if cand.size and np.isfinite(cand).any():
            j = int(np.argmin(cand))
            out[i] = j
            free[j] = False
    return out


def _valid_mask(insts: list[GtInstance], im_targets: dict[int, int], visib_gt_min: float) -> np.ndarray:
    if visib_gt_min >= 0:
        return np.array([g.obj_id in im_targets and g.visib_fract >= visib_gt_min for g in insts], dtype=bool)
    valid = np.zeros(len(insts), dtype=bool)
    left = dict(im_targets)
    for gid in sorted(range(len(insts)), key=lambda i: insts[i].visib_fract, reverse=True):
        oid = insts[gid].obj_id
        if left.get(oid, 0) > 0:
            valid[gid] = True
            left[oid] -= 1
    return valid


# ---------------------------------------------------------------------------------------------
# scoring
# ---------------------------------------------------------------------------------------------
def score_bop19(results: Sequence[PoseResult], root: str | os.PathLike, split: str = "test",
                targets_filename: str = "test_targets_bop19.json", visib_gt_min: float = -1.0,
                models: dict[int, dict] | None = None, gt: BopGt | None = None) -> dict:
    """Score ``results`` against the BOP dataset at ``root``; returns a JSON-ready dict.

    Keys: ``ar_mssd``, ``ar_mspd`` (0-1), ``recalls_mssd`` / ``recalls_mspd`` (one per threshold),
    ``per_object`` ({obj_id: {ar_mssd, ar_mspd, n_gt}}), ``vsd`` (why it was skipped), counts and
    ``average_time_per_image`` (-1 when the results hold no times).
    """
    root = Path(root)
    gt = gt if gt is not None else load_bop_gt(root, split, targets_filename)
    models = models if models is not None else load_eval_models(root)
    check_targets_and_results(results, gt, models, root / targets_filename)

    # organise estimates by (scene, im, obj) in file order
    ests: dict[tuple[int, int, int], list[int]] = defaultdict(list)
    for i, r in enumerate(results):
        ests[(r.scene_id, r.im_id, r.obj_id)].append(i)

    # build the (estimate, GT) pairs of every target
    blocks = []  # (scene, im, obj, est indices (sorted, top-k), gt indices, valid mask)
    pair_e, pair_g, pair_key = [], [], []
    for (scene, im), im_targets in sorted(gt.targets.items()):
        insts = gt.instances[(scene, im)]
        valid = _valid_mask(insts, im_targets, visib_gt_min)
        for oid, inst_count in sorted(im_targets.items()):
            gids = [j for j, g in enumerate(insts) if g.obj_id == oid]  # positions in insts
            if not gids:
                continue
            if oid not in models:
                raise BopScoringError(f"{root}: target object {oid} (scene {scene}, image {im}) has no evaluation mesh; "
                                      f"known objects: {sorted(models)}")
            idx = ests.get((scene, im, oid), [])
            order = sorted(idx, key=lambda i: results[i].score, reverse=True)[:inst_count]  # stable, as the toolkit
            blocks.append((scene, im, oid, order, gids, valid[gids]))
            for e in order:
                for g in gids:
                    pair_e.append(e)
                    pair_g.append((scene, im, g))
                    pair_key.append(oid)

    # errors, vectorised per object
    n_pairs = len(pair_e)
    mssd = np.empty(n_pairs)
    mspd = np.empty(n_pairs)
    pair_key_arr = np.asarray(pair_key, dtype=np.int64)
    for oid in np.unique(pair_key_arr):
        sel = np.nonzero(pair_key_arr == oid)[0]
        m = models[int(oid)]
        R_e = np.stack([results[pair_e[k]].R for k in sel])
        t_e = np.stack([results[pair_e[k]].t for k in sel])
        gts = [gt.instances[pair_g[k][:2]][pair_g[k][2]] for k in sel]
        R_g = np.stack([g.R for g in gts])
        t_g = np.stack([g.t for g in gts])
        K = np.stack([gt.K[pair_g[k][:2]] for k in sel])
        d = mssd_batch(R_e, t_e, R_g, t_g, m["pts"], m["syms"])
        far = np.linalg.norm(t_e - t_g, axis=-1) >= m["diameter"]  # toolkit: non-overlapping spheres -> inf
        d[far] = np.inf
        mssd[sel] = d / m["diameter"]
        width = np.array([gt.im_width.get(pair_g[k][0], 640) for k in sel], dtype=np.float64)
        mspd[sel] = mspd_batch(R_e, t_e, R_g, t_g, K, m["pts"], m["syms"]) * (640.0 / width)

    # matching and recall per threshold
    obj_ids = sorted({b[2] for b in blocks})
    n_valid = {o: 0 for o in obj_ids}
    for b in blocks:
        n_valid[b[2]] += int(np.sum(b[5]))
    total_valid = sum(n_valid.values())
    per_err = {}
    pos = 0
    block_errs = []
    for b in blocks:
        n = len(b[3]) * len(b[4])
        block_errs.append((mssd[pos:pos + n].reshape(len(b[3]), len(b[4])), mspd[pos:pos + n].reshape(len(b[3]), len(b[4]))))
        pos += n
    for name, ths, which in (("mssd", MSSD_THRESHOLDS, 0), ("mspd", MSPD_THRESHOLDS, 1)):
        recalls, obj_recalls = [], {o: [] for o in obj_ids}
        for th in ths:
            tps = {o: 0 for o in obj_ids}
            for b, errs in zip(blocks, block_errs):
                matched = greedy_match(errs[which], b[5], float(th))
                tps[b[2]] += int(np.sum(matched >= 0))  # only valid GTs can be matched
            recalls.append(sum(tps.values()) / total_valid if total_valid else 0.0)
            for o in obj_ids:
                obj_recalls[o].append(tps[o] / n_valid[o] if n_valid[o] else 0.0)
        per_err[name] = (recalls, obj_recalls)

    times: dict[tuple[int, int], float] = {}
    for r in results:
        if r.time >= 0:
            times[(r.scene_id, r.im_id)] = r.time
    n_considered = sum(len(b[3]) for b in blocks)
    return {
        "ar_mssd": float(np.mean(per_err["mssd"][0])),
        "ar_mspd": float(np.mean(per_err["mspd"][0])),
        "ar_vsd": None,
        "vsd": "skipped: VSD needs depth images and a depth renderer; not computed by kpd6d-score",
        "recalls_mssd": [float(v) for v in per_err["mssd"][0]],
        "recalls_mspd": [float(v) for v in per_err["mspd"][0]],
        "thresholds_mssd": [float(v) for v in MSSD_THRESHOLDS],
        "thresholds_mspd_px_at_640": [float(v) for v in MSPD_THRESHOLDS],
        "per_object": {
            str(o): {"ar_mssd": float(np.mean(per_err["mssd"][1][o])), "ar_mspd": float(np.mean(per_err["mspd"][1][o])),
                     "n_gt": n_valid[o]}
            for o in obj_ids
        },
        "n_targets": int(total_valid),
        "n_estimates": len(results),
        "n_estimates_considered": int(n_considered),
        "visib_gt_min": float(visib_gt_min),
        "average_time_per_image": float(np.mean(list(times.values()))) if times else -1.0,
    }


def check_targets_and_results(results: Sequence[PoseResult], gt: BopGt, models: dict[int, dict],
                              targets_path: str | os.PathLike, results_source: str = "the estimates") -> None:
    """Scoring input that would give a meaningless score raises :class:`BopScoringError`: a target
    object without an evaluation model, or estimates none of which is in a target image."""
    for (scene, im), objs in sorted(gt.targets.items()):
        for oid in sorted(objs):
            if oid not in models:
                raise BopScoringError(f"{targets_path}: target scene_id {scene} im_id {im} obj_id {oid}: no model for "
                                      f"object {oid} (objects with models: {sorted(models)})")
    if results and not any((r.scene_id, r.im_id) in gt.targets for r in results):
        seen = sorted({(r.scene_id, r.im_id) for r in results})
        raise BopScoringError(f"{results_source}: none of the {len(results)} estimates is in a target image of "
                              f"{targets_path} (estimates' (scene_id, im_id): {seen[:5]}{' ...' if len(seen) > 5 else ''}; "
                              f"targets: {sorted(gt.targets)[:5]}{' ...' if len(gt.targets) > 5 else ''}); wrong dataset or split?")


def score_bop19_file(results_csv: str | os.PathLike, root: str | os.PathLike, **kwargs) -> dict:
    """:func:`score_bop19` on a BOP results CSV."""
    results = read_bop_results(results_csv)
    root = Path(root)
    split = kwargs.get("split", "test")
    targets_filename = kwargs.get("targets_filename", "test_targets_bop19.json")
    if kwargs.get("gt") is None:
        kwargs["gt"] = load_bop_gt(root, split, targets_filename)
    if kwargs.get("models") is None:
        kwargs["models"] = load_eval_models(root)
    check_targets_and_results(results, kwargs["gt"], kwargs["models"], root / targets_filename, str(results_csv))
    return score_bop19(results, root, **kwargs)


def format_scores_table(scores: dict) -> str:
    """Per-object table (markdown) of a :func:`score_bop19` result."""
    lines = ["| obj_id | n_gt | AR_MSSD | AR_MSPD |", "|---:|---:|---:|---:|"]
    for oid, s in sorted(scores["per_object"].items(), key=lambda kv: int(kv[0])):
        lines.append(f"| {oid} | {s['n_gt']} | {s['ar_mssd']:.4f} | {s['ar_mspd']:.4f} |")
    lines.append(f"| **all** | {scores['n_targets']} | {scores['ar_mssd']:.4f} | {scores['ar_mspd']:.4f} |")
    return "\n".join(lines)


def format_scores_summary(scores: dict) -> str:
    """The closing lines of ``kpd6d-score``: both ARs, what was counted, and why VSD is not computed."""
    return (f"AR_MSSD {scores['ar_mssd']:.4f}  AR_MSPD {scores['ar_mspd']:.4f}  "
            f"({scores['n_estimates_considered']} of {scores['n_estimates']} estimates considered, "
            f"{scores['n_targets']} GT instances)\nVSD: {scores['vsd']}")
