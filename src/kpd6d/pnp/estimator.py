"""The pose pipelines' shared, torch-free core: detections → crops → keypoints → top-l → PnP → pose dicts.

:class:`PoseEstimatorBase` holds what :class:`kpd6d.pipeline.PosePipeline` (torch) and
:class:`kpd6d.deploy.runtime.RuntimePipeline` (ONNX Runtime / OpenVINO, no torch) do alike: the
settings and their checks, ``predict_batch`` / ``detect`` / ``predict_boxes``, the flattening of the
detector's output, the estimation loop with box refinement (``refine_boxes``: re-crop on the box of
the object's surface points projected with the estimated pose), ``box_scale`` (the KPD crops on each
box grown by this factor about its centre; the boxes reported and refined stay as they are),
``crop_tta`` (test-time crops: the KPD sees n jittered crops of each box, :data:`CROP_TTA_JITTER`, and each
keypoint is the median of its n locations, its confidence the mean; ``{crops: n, stability: τ}`` also weighs
each confidence by how little the keypoint moves from crop to crop, :func:`combine_tta`),
``depth_calibration`` (each estimated translation multiplied by a factor, one for all objects or one per
object: a depth calibration fitted on synthetic validation, :mod:`kpd6d.evaluation.calibration`),
``candidates`` (the ``n`` highest-scoring detections of each object in an image all go through KPD + PnP
and the pose with the highest pose confidence times detection score is kept (``detector_weight``: the
score's exponent): the keypoints verify the detector's hypotheses; one pose per object, as in BOP's LM-O,
unless ``max_instances`` > 1 (then the next ones whose boxes do not overlap a kept one's); give the detector
``one_per_object=False`` so that it offers more than one; ``{per_object: n, any_class: m}`` also tries
the m best boxes of each image, whatever their class, as every object) and ``last_timings``. A subclass says
how its images become a batch and how its networks run:

* ``_batch(images)`` → the batch its networks take; ``_num_images(x)``, ``_image_hw(x)`` → (H, W);
* ``_run_detector(x, targets)`` → one detections object per image (``.boxes`` (n, 4) xywh,
  ``.obj_ids``, ``.scores``, each with ``.tolist()``);
* ``_keypoints(x, boxes, image_index, obj_ids)`` → ``keypoints_2d`` (N, k, 2) image px and
  ``confidences`` (N, k), float64 numpy, for ``boxes`` (N, 4) float64 numpy;
* ``object_points(obj_id)`` → (P, 3) mm points whose projection bounds the object;
* attributes ``kpd`` (with ``keypoints_3d``: obj_id → (k, 3)) and ``pnp`` (a ``PNP_SOLVERS`` solver).

Imports numpy and kpd6d's geometry / PnP modules only.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from kpd6d.geometry import (
    box_iou_xywh,
    check_box_inputs,
    check_intrinsics,
    clip_box_to_image,
    project_points,
)
from kpd6d.pnp.confidence import RESIDUAL_SCALE_PX
from kpd6d.pnp.top_l import pose_records, solve_top_l, top_l_mask

__all__ = ["CROP_TTA_JITTER", "DETECTOR_WEIGHT", "SAME_INSTANCE_IOU", "CandidateSpec", "PoseEstimatorBase",
           "best_candidates", "build_pnp", "candidate_options", "candidates_record", "check_candidates",
           "check_crop_tta", "combine_tta", "crop_tta_record", "parse_depth_calibration", "scale_boxes",
           "top_candidates", "tta_boxes"]


#: ``candidates``: a candidate pose's rank is its pose confidence x its detection score ** DETECTOR_WEIGHT
#: (chosen on synthetic LM-O validation, session 18: AR_MSPD +0.012 / +0.021 over the pose confidence
#: alone with full- / half-budget networks; docs/benchmarks.md)
DETECTOR_WEIGHT = 1.0

#: ``candidates.max_instances`` > 1: a candidate whose box overlaps a kept pose's box of the same object by
#: this IoU or more is another hypothesis of the same instance (BOP's and COCO's match threshold)
SAME_INSTANCE_IOU = 0.5

#: ``crop_tta=n`` uses the first n of these crops of each box: (side factor, x shift, y shift as
#: fractions of the box side) about the box centre — the box itself, then 0.9x / 1.1x, then shifted.
CROP_TTA_JITTER = ((1.0, 0.0, 0.0), (0.9, 0.0, 0.0), (1.1, 0.0, 0.0), (1.0, 0.06, 0.06), (1.0, -0.06, -0.06),
                   (0.9, 0.06, 0.06), (1.1, 0.06, 0.06), (0.9, -0.06, -0.06), (1.1, -0.06, -0.06))


def tta_boxes(boxes: np.ndarray, n: int) -> np.ndarray:
    """(n * N, 4) xywh: the first ``n`` crops of :data:`CROP_TTA_JITTER` of each of ``boxes`` (N, 4),
    crop-major (rows ``j * N + i`` are crop j of box i)."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    side = b[:, 2:]
    return np.concatenate([scale_boxes(b + np.hstack([side * [dx, dy], 0 * side]), f) for f, dx, dy in CROP_TTA_JITTER[:n]])


def combine_tta(kp2d: np.ndarray, conf: np.ndarray, n: int,
                stability: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (n * N, k, 2) and confidences (n * N, k) of :func:`tta_boxes`' crops → each keypoint's
    coordinate-wise median over the n crops (robust to one crop's outlier) and its mean confidence.

    ``stability`` = τ > 0: each confidence is also multiplied by ``exp(-(mad / (τ r))²)``, where ``mad`` is
    the median distance of the keypoint's n locations from their median and ``r`` the RMS distance of the
    instance's median keypoints from their centroid. A keypoint the image pins down stays where it is
    whichever crop the KPD sees; one the network places from where keypoints usually lie in a crop moves
    with the crop, and loses weight (floor 1e-6, so it stays usable)."""
    kp = np.asarray(kp2d, dtype=np.float64)
    kp = kp.reshape(n, -1, *kp.shape[1:])
    c = np.asarray(conf, dtype=np.float64).reshape(n, kp.shape[1], -1)
    med, mean = np.median(kp, axis=0), c.mean(axis=0)
    if stability is not None:
        mad = np.median(np.linalg.norm(kp - med[None], axis=-1), axis=0)  # (N, k)
        r = np.sqrt(((med - med.mean(axis=1, keepdims=True)) ** 2).sum(-1).mean(-1))  # (N,)
        rel = mad / (float(stability) * np.maximum(r, 1e-9))[:, None]
        mean = np.maximum(mean * np.exp(-rel * rel), 1e-6)
    return med, mean


def scale_boxes(boxes: np.ndarray, factor: float) -> np.ndarray:
    """Boxes (N, 4) xywh grown (or shrunk) by ``factor`` about their centres."""
    if factor == 1.0:
        return boxes
    b = np.array(boxes, dtype=np.float64)
    centre = b[:, :2] + b[:, 2:] / 2
    b[:, 2:] *= factor
    b[:, :2] = centre - b[:, 2:] / 2
    return b


def parse_depth_calibration(value: Any, error: type[Exception] = ValueError) -> tuple[float, dict[int, float]]:
    """``depth_calibration`` → (factor for every object, {obj_id: factor}).

    ``value``: a number (every object; None: 1); a mapping ``{obj_id: factor}`` with an optional
    ``"default"``; the output of :func:`kpd6d.evaluation.calibration.fit_depth_calibration`
    (``{"global": g, "per_object": {...}}``); or the path of a JSON file holding either mapping.
    Every factor must be a finite number > 0; ``error`` names the bad one."""
    source = ""
    if isinstance(value, (str, os.PathLike)) and not _is_number(value):
        source = f"{os.fspath(value)}: "
        try:
            with open(value, encoding="utf-8") as fh:
                value = json.load(fh)
        except FileNotFoundError:
            raise error(f"depth_calibration file {os.fspath(value)} does not exist") from None
        except (OSError, json.JSONDecodeError) as exc:
            raise error(f"depth_calibration file {os.fspath(value)} cannot be read as JSON: {exc}") from None

    def factor(v, what):
        return _positive_number(v, f"{source}depth_calibration{what}", error)

    if value is None:
        return 1.0, {}
    if not isinstance(value, Mapping) and not hasattr(value, "keys"):
        return factor(value, ""), {}
    value = dict(value)
    if "per_object" in value or "global" in value:  # fit_depth_calibration's record
        default, per = value.get("global", 1.0), value.get("per_object") or {}
    else:
        default, per = value.pop("default", 1.0), value
    out = {}
    for k, v in dict(per).items():
        try:
            oid = int(k)
        except (TypeError, ValueError):
            raise error(f"{source}depth_calibration keys must be object ids (or 'default'), got {k!r}") from None
        out[oid] = factor(v, f"[{k}]")
    return factor(default, " (default)"), out


class CandidateSpec(NamedTuple):
    """A checked ``candidates`` setting (:func:`check_candidates`)."""

    per_object: int = 1  # the n highest-scoring boxes of each object go through KPD + PnP
    any_class: int = 0  # and the image's m best boxes of any class, as every object
    detector_weight: float = DETECTOR_WEIGHT  # a candidate's rank: pose confidence x detection score ** this
    verify_crops: int | None = None  # KPD crops per candidate while verifying (None: crop_tta's); the kept
    #                                  pose is then estimated again with crop_tta crops
    refine_weight: float = 0.0  # > 0: every candidate's pose goes through the refiner first, and its rank is
    #                             also multiplied by its refinement evidence ** this
    max_instances: int = 1  # poses kept per object and image: the best-ranked candidate, then (m > 1) the next
    #                         ones whose boxes overlap no kept one's by SAME_INSTANCE_IOU or more

    @property
    def verifies(self) -> bool:
        """Whether more than one box per object goes through KPD + PnP (and the best pose is picked)."""
        return self.per_object > 1 or self.any_class > 0


def check_candidates(candidates: Any, error: type[Exception] = ValueError,
                     key: str = "candidates") -> CandidateSpec:
    """``candidates`` as a :class:`CandidateSpec`: an int n >= 1 is ``(n, 0, DETECTOR_WEIGHT, None, 0, 1)``
    (None: n = 1); a mapping ``{per_object: n, any_class: m, detector_weight: w, verify_crops: c,
    refine_weight: r, max_instances: i}`` (n >= 1, m >= 0, w and r >= 0 finite, c from 1 to
    len(CROP_TTA_JITTER) or None, i >= 1; any may be left out) gives all six. Anything else raises
    ``error`` naming ``key`` and the value."""
    def count(v, low: int, name: str) -> int:
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < low:
            raise error(f"{name} must be an integer >= {low}, got {v!r}")
        return int(v)

    if candidates is None:
        return CandidateSpec()
    if isinstance(candidates, Mapping) or hasattr(candidates, "keys"):
        spec = dict(candidates)
        unknown = sorted(set(map(str, spec)) - set(CandidateSpec._fields))
        if unknown:
            raise error(f"{key}: unknown key(s) {unknown}; known: {sorted(CandidateSpec._fields)}")
        w, r = (spec.get(name, default) for name, default in (("detector_weight", DETECTOR_WEIGHT), ("refine_weight", 0.0)))
        for name, v in (("detector_weight", w), ("refine_weight", r)):
            if isinstance(v, bool) or not _is_number(v) or not (math.isfinite(float(v)) and float(v) >= 0):
                raise error(f"{key}.{name} must be a finite number >= 0, got {v!r}")
        c = spec.get("verify_crops")
        n = count(spec.get("per_object", 1), 1, f"{key}.per_object")
        i = count(spec.get("max_instances", 1), 1, f"{key}.max_instances")
        if i > n:
            raise error(f"{key}.max_instances={i} exceeds per_object={n}: at most per_object boxes of an object are "
                        "tried, and each gives at most one pose")
        return CandidateSpec(n, count(spec.get("any_class", 0), 0, f"{key}.any_class"), float(w),
                             None if c is None else _crop_count(c, f"{key}.verify_crops", error), float(r), i)
    return CandidateSpec(count(candidates, 1, key))


def candidates_record(per_object: int, any_class: int = 0, detector_weight: float = DETECTOR_WEIGHT,
                      verify_crops: int | None = None, refine_weight: float = 0.0, max_instances: int = 1) -> Any:
    """The plain value of a candidates setting: n, or the mapping of the keys that differ from n's
    defaults (``{per_object: n, any_class: m, detector_weight: w, verify_crops: c, refine_weight: r,
    max_instances: i}``)."""
    if (any_class == 0 and detector_weight == DETECTOR_WEIGHT and verify_crops is None and not refine_weight
            and max_instances == 1):
        return int(per_object)
    out: dict[str, Any] = {"per_object": int(per_object)}
    if any_class:
        out["any_class"] = int(any_class)
    if detector_weight != DETECTOR_WEIGHT:
        out["detector_weight"] = float(detector_weight)
    if verify_crops is not None:
        out["verify_crops"] = int(verify_crops)
    if refine_weight:
        out["refine_weight"] = float(refine_weight)
    if max_instances != 1:
        out["max_instances"] = int(max_instances)
    return out


def candidate_options(candidates: Any, detector_ckpt: Any, error: type[Exception] = ValueError,
                      overrides: Mapping[str, Any] | None = None) -> dict:
    """The pipeline keywords of a config's ``candidates`` and its checked ``detector_overrides``
    (``overrides``: the trained detector's inference settings, e.g. ``score_threshold``): with more than
    one candidate per object the detector must offer several boxes per object (``one_per_object=False``;
    an override asking for ``one_per_object=True`` then is an error); with the oracle (ground-truth
    boxes) nothing."""
    spec = check_candidates(candidates, error)
    if str(detector_ckpt) == "oracle":
        return {}
    over = dict(overrides or {})
    if not spec.verifies:
        return over
    if over.get("one_per_object") is True:
        raise error(f"detector_overrides.one_per_object=true contradicts candidates={candidates_record(*spec)!r}: "
                    "several candidates per object need several boxes per object")
    return {**over, "candidates": candidates_record(*spec), "one_per_object": False}


def top_candidates(dets: list[dict], n: int, any_class: int = 0, obj_ids: Any = ()) -> list[dict]:
    """The ``n`` highest-scoring of ``dets`` (flat detections: image_index, obj_id, score, box) of each
    object in each image, in their order; with ``any_class`` = m > 0, after them the m highest-scoring
    boxes of each image, whatever their class, once more as a candidate of each of ``obj_ids`` (the
    objects the KPD knows) that does not already have that box: a detector that mistakes one object
    for another still found it, and the keypoints can tell."""
    keep, count = set(), {}
    order = sorted(range(len(dets)), key=lambda i: -dets[i]["score"])
    for i in order:
        key = (dets[i]["image_index"], dets[i]["obj_id"])
        count[key] = count.get(key, 0) + 1
        if count[key] <= n:
            keep.add(i)
    out = [d for i, d in enumerate(dets) if i in keep]
    if any_class <= 0:
        return out
    have = {(d["image_index"], d["obj_id"], tuple(d["box"])) for d in out}
    per_image: dict[int, int] = {}
    for i in order:
        d = dets[i]
        b = d["image_index"]
        per_image[b] = per_image.get(b, 0) + 1
        if per_image[b] > any_class:
            continue
        for o in obj_ids:
            key = (b, int(o), tuple(d["box"]))
            if key not in have:
                have.add(key)
                out.append({**d, "obj_id": int(o)})
    return out


def best_candidates(poses: list[dict], detector_weight: float = DETECTOR_WEIGHT, refine_weight: float = 0.0,
                    max_instances: int = 1) -> list[dict]:
    """The poses kept of one image's candidates: per object, the one with the highest pose ``confidence``
    times its detection ``score`` to the power ``detector_weight`` (0: the pose confidence alone; a failed
    pose has confidence 0) times its refinement ``evidence`` (0 when absent) to the power ``refine_weight``
    (0: not used), ties to the higher detection score. With ``max_instances`` = m > 1, up to m - 1 more
    per object, next in that rank, each with a rank above 0 and a ``box`` whose IoU with every kept box of
    its object is below :data:`SAME_INSTANCE_IOU` (a box that overlaps a kept one is another hypothesis of
    the same instance). In score order; each kept pose records how many candidates its object had
    (``candidates``)."""
    ranked: dict[int, list[tuple]] = {}
    for p in poses:
        rank = p["confidence"] * max(p["score"], 0.0) ** detector_weight  # 0 ** 0 = 1
        if refine_weight:
            rank *= max(p.get("evidence", 0.0), 0.0) ** refine_weight
        ranked.setdefault(p["obj_id"], []).append(((rank, p["score"]), p))
    kept = []
    for cands in ranked.values():
        cands.sort(key=lambda kp: kp[0], reverse=True)  # stable: equal keys keep their order
        mine = [cands[0][1]]
        for (rank, _), p in cands[1:]:
            if len(mine) >= max_instances:
                break
            if rank > 0 and (box_iou_xywh(p["box"], [q["box"] for q in mine]) < SAME_INSTANCE_IOU).all():
                mine.append(p)
        kept += [{**p, "candidates": len(cands)} for p in mine]
    return sorted(kept, key=lambda p: -p["score"])


def _crop_count(v, name: str, error: type[Exception]) -> int:
    """A number of test-time crops: an integer from 1 to len(CROP_TTA_JITTER), else ``error`` naming ``name``."""
    if isinstance(v, bool) or not isinstance(v, int | np.integer) or not 1 <= int(v) <= len(CROP_TTA_JITTER):
        raise error(f"{name} must be an integer from 1 to {len(CROP_TTA_JITTER)}, got {v!r}")
    return int(v)


def check_crop_tta(v: Any, error: type[Exception] = ValueError, key: str = "crop_tta") -> tuple[int, float | None]:
    """``crop_tta``: n (an integer from 1 to len(CROP_TTA_JITTER)) or ``{crops: n, stability: τ}`` (τ > 0 or
    None; :func:`combine_tta`) → (n, τ); anything else raises ``error`` naming ``key``."""
    if not isinstance(v, Mapping):
        return _crop_count(v, key, error), None
    unknown = sorted(set(v) - {"crops", "stability"})
    if unknown:
        raise error(f"{key}: unknown key(s) {unknown}; known: crops, stability")
    n = _crop_count(v.get("crops", 1), f"{key}.crops", error)
    tau = v.get("stability")
    if tau is None:
        return n, None
    tau = _positive_number(tau, f"{key}.stability", error)
    if n < 2:
        raise error(f"{key}.stability needs crops >= 2 (the keypoints' spread over the crops), got crops {n}")
    return n, tau


def crop_tta_record(n: int, stability: float | None = None) -> int | dict:
    """The setting as written to run records: n, or ``{crops: n, stability: τ}``."""
    return int(n) if stability is None else {"crops": int(n), "stability": float(stability)}


def _positive_number(v, name: str, error: type[Exception]) -> float:
    """``float(v)`` when it is finite and > 0; else ``error`` naming ``name`` and the value."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise error(f"{name} must be a number > 0, got {v!r}") from None
    if not (math.isfinite(f) and f > 0):
        raise error(f"{name} must be a number > 0, got {v!r}")
    return f


def _is_number(v) -> bool:
    try:
        float(v)
    except (TypeError, ValueError):
        return False
    return True


def build_pnp(pnp: Any):
    """A ``PNP_SOLVERS`` solver from a name or a config mapping; a solver object as it is."""
    from kpd6d.registry import PNP_SOLVERS, build_from_cfg

    if isinstance(pnp, str):
        return PNP_SOLVERS.build(pnp)
    if isinstance(pnp, dict) or hasattr(pnp, "keys"):
        return build_from_cfg(PNP_SOLVERS, dict(pnp))
    return pnp


class PoseEstimatorBase:
    """Shared core of the pose pipelines (module docstring). ``input_error``: the exception class for
    bad input (``PosePipeline`` raises its ``PipelineInputError``)."""

    input_error: type[Exception] = ValueError
    kpd: Any
    pnp: Any
    #: a pose refiner (``refine_poses(images, Ks, poses)``, e.g. :class:`kpd6d.refinement.RegionRefiner`)
    #: run on the final poses of ``predict_batch`` / ``predict_boxes``; None: the PnP poses as they are
    refiner: Any = None

    def set_refiner(self, refiner: Any) -> None:
        """Use ``refiner`` (None: none) on the poses this pipeline returns (:attr:`refiner`)."""
        if refiner is not None and not callable(getattr(refiner, "refine_poses", None)):
            raise self.input_error(f"refiner must have .refine_poses(images, Ks, poses) (or be None), "
                                   f"got {type(refiner).__name__}")
        self.refiner = refiner

    def _set_options(self, pnp: Any, top_l: int | None, refine_boxes: int, min_confidence: float,
                     residual_scale_px: float = RESIDUAL_SCALE_PX, box_scale: float = 1.0,
                     depth_calibration: Any = 1.0, candidates: Any = 1, crop_tta: Any = 1) -> None:
        """Check and keep the settings both pipelines take."""
        err = self.input_error
        self.crop_tta, self.crop_tta_stability = check_crop_tta(crop_tta, err)
        self.candidate_spec = check_candidates(candidates, err)
        self.depth_calibration_default, self.depth_calibration_per_object = parse_depth_calibration(depth_calibration, err)
        self.box_scale = _positive_number(box_scale, "box_scale", err)
        if top_l is not None and int(top_l) < 4:
            raise err(f"top_l must be >= 4 (PnP needs at least 4 points) or None, got {top_l}")
        if int(refine_boxes) < 0:
            raise err(f"refine_boxes must be >= 0, got {refine_boxes}")
        if not 0.0 <= float(min_confidence) <= 1.0:
            raise err(f"min_confidence must be in [0, 1], got {min_confidence}")
        if not float(residual_scale_px) > 0:
            raise err(f"residual_scale_px must be > 0, got {residual_scale_px}")
        self.pnp = build_pnp(pnp)
        self.top_l = None if top_l is None else int(top_l)
        self.refine_boxes = int(refine_boxes)
        self.min_confidence, self.residual_scale_px = float(min_confidence), float(residual_scale_px)
        self.last_timings: dict[str, float] = {}

    # -- what a subclass provides ----------------------------------------------------------------
    def _batch(self, images):  # pragma: no cover - abstract
        raise NotImplementedError

    def _num_images(self, x) -> int:  # pragma: no cover - abstract
        raise NotImplementedError

    def _image_hw(self, x) -> tuple[int, int]:  # pragma: no cover - abstract
        raise NotImplementedError

    def _run_detector(self, x, targets):  # pragma: no cover - abstract
        raise NotImplementedError

    def _keypoints(self, x, boxes: np.ndarray, image_index: np.ndarray, obj_ids: list[int]):  # pragma: no cover
        raise NotImplementedError

    def object_points(self, obj_id: int) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    # -- the interface ----------------------------------------------------------------------------
    def __call__(self, image: np.ndarray, K, targets: dict | None = None) -> list[dict]:
        """Poses of the objects in one uint8 RGB image with intrinsics ``K`` (3, 3)."""
        return self.predict_batch([image], K, None if targets is None else [targets])[0]

    def predict_batch(self, images, K, targets: list[dict] | None = None) -> list[list[dict]]:
        """Poses for a batch of images. ``K`` is (3, 3) for all images or (B, 3, 3); ``targets`` goes to
        the detector (the oracle's GT boxes). One list of pose dicts per image: the same as
        :meth:`detect` followed by :meth:`predict_boxes` on its boxes."""
        t0 = time.perf_counter()
        x = self._batch(images)
        Ks = check_intrinsics(K, self._num_images(x), self.input_error)
        dets = self._detect(x, targets)
        spec = self.candidate_spec
        refined_all = spec.verifies and spec.refine_weight > 0
        if refined_all and self.refiner is None:
            raise self.input_error(f"candidates.refine_weight={spec.refine_weight:g} ranks the candidates by their "
                                   "refinement: it needs a refiner (refiner=region)")
        if spec.verifies:
            dets = top_candidates(dets, spec.per_object, spec.any_class, sorted(self.kpd.keypoints_3d))
        t1 = time.perf_counter()
        crops = spec.verify_crops if spec.verifies and spec.verify_crops is not None else self.crop_tta
        out = self._estimate(x, Ks, [d["box"] for d in dets], [d["image_index"] for d in dets],
                             [d["obj_id"] for d in dets], [d["score"] for d in dets], crops)
        refine_s = 0.0
        if spec.verifies:
            if refined_all:  # every candidate refined, its evidence part of its rank
                out, refine_s = self._refine(images, Ks, out)
            out = [best_candidates(poses, spec.detector_weight, spec.refine_weight, spec.max_instances) for poses in out]
            if crops != self.crop_tta:  # the kept candidates again, with crop_tta crops
                out = self._reestimate(x, Ks, out)
        if not refined_all or crops != self.crop_tta:  # (else the kept poses are refined already)
            out, dt = self._refine(images, Ks, out)
            refine_s += dt
        if self.refiner is not None:
            self.last_timings["refine"] = refine_s
        self.last_timings["detect"] = t1 - t0
        self.last_timings["total"] = time.perf_counter() - t0
        return out

    def detect(self, images, targets: list[dict] | None = None) -> list[list[dict]]:
        """The detector alone: per image a list of ``{"box": (4,) xywh px, "obj_id", "score"}`` (highest
        score first, only objects the KPD has keypoints for): the boxes :meth:`predict_batch` estimates."""
        t0 = time.perf_counter()
        x = self._batch(images)
        out: list[list[dict]] = [[] for _ in range(self._num_images(x))]
        for d in self._detect(x, targets):
            out[d["image_index"]].append({"box": d["box"], "obj_id": d["obj_id"], "score": d["score"]})
        dt = time.perf_counter() - t0
        self.last_timings = {"detect": dt, "kpd": 0.0, "pnp": 0.0, "total": dt}
        return out

    def predict_boxes(self, images, K, boxes, obj_ids, image_index=None, scores=None) -> list[list[dict]]:
        """KPD + PnP (and ``refine_boxes``) on given boxes, no detector: what tracking runs on the boxes of
        the objects projected with their previous poses.

        ``boxes`` (N, 4) xywh px, ``obj_ids`` (N,), ``image_index`` (N,) which image each box is in
        (None: all in image 0), ``scores`` (N,) copied to the pose dicts' ``score`` (None: 1). Returns
        one list of pose dicts per image, in the order of the boxes. Objects the KPD has no keypoints
        for raise ``input_error``.
        """
        t0 = time.perf_counter()
        x = self._batch(images)
        n = self._num_images(x)
        Ks = check_intrinsics(K, n, self.input_error)
        boxes, obj_ids, img_idx, scores = check_box_inputs(boxes, obj_ids, image_index, scores, n,
                                                           self.kpd.keypoints_3d, error=self.input_error)
        out, refine_s = self._refine(images, Ks, self._estimate(x, Ks, boxes.tolist(), img_idx, obj_ids, scores))
        if self.refiner is not None:
            self.last_timings["refine"] = refine_s
        self.last_timings["detect"] = 0.0
        self.last_timings["total"] = time.perf_counter() - t0
        return out

    # -- the shared steps -------------------------------------------------------------------------
    def _refine(self, images, Ks: np.ndarray, poses: list[list[dict]]) -> tuple[list[list[dict]], float]:
        """:attr:`refiner` on the poses; (poses, seconds it took)."""
        if self.refiner is None:
            return poses, 0.0
        t0 = time.perf_counter()
        return self.refiner.refine_poses(images, Ks, poses), time.perf_counter() - t0

    def _detect(self, x, targets) -> list[dict]:
        """The detections of the batch ``x`` the KPD can localise, flat: box, image_index, obj_id, score."""
        B = self._num_images(x)
        dets = self._run_detector(x, targets)
        if len(dets) != B:
            raise self.input_error(f"detector returned {len(dets)} results for {B} images")
        known = {int(o) for o in self.kpd.keypoints_3d}
        flat = []
        for b, d in enumerate(dets):
            for box, oid, s in zip(d.boxes.tolist(), d.obj_ids.tolist(), d.scores.tolist()):
                if int(oid) in known:  # the KPD cannot localise objects it has no keypoints for
                    flat.append({"box": box, "image_index": b, "obj_id": int(oid), "score": float(s)})
        return flat

    def _reestimate(self, x, Ks: np.ndarray, poses: list[list[dict]]) -> list[list[dict]]:
        """``poses`` (per image) estimated again from their boxes with ``crop_tta`` crops, in the same
        order, each keeping its candidate count; ``last_timings`` adds up both estimates."""
        before = dict(self.last_timings)
        flat = [(b, p) for b, ps in enumerate(poses) for p in ps]
        out = self._estimate(x, Ks, [p["box"] for _, p in flat], [b for b, _ in flat], [p["obj_id"] for _, p in flat],
                             [p["score"] for _, p in flat])
        for k in ("kpd", "pnp", "total"):
            self.last_timings[k] += before.get(k, 0.0)
        return [[{**q, "candidates": p["candidates"]} for q, p in zip(new, old)] for new, old in zip(out, poses)]

    def _estimate(self, x, Ks: np.ndarray, boxes: list, img_idx: list[int], obj_ids: list[int],
                  scores: list[float], crop_tta: int | None = None) -> list[list[dict]]:
        """keypoints -> top-l -> PnP (``refine_boxes`` more times) on ``boxes`` (``crop_tta`` crops each;
        None: the pipeline's); sets ``last_timings``."""
        out: list[list[dict]] = [[] for _ in range(self._num_images(x))]
        if not boxes:
            self.last_timings = {"detect": 0.0, "kpd": 0.0, "pnp": 0.0, "total": 0.0}
            return out
        hw = self._image_hw(x)
        cur = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        idx = np.asarray(img_idx, dtype=np.int64)
        pts3d = np.stack([np.asarray(self.kpd.keypoints_3d[o], dtype=np.float64).reshape(-1, 3) for o in obj_ids])
        Kn = np.ascontiguousarray(Ks[idx])
        dscale = self.depth_factors(obj_ids)
        t_kpd = t_pnp = 0.0
        for it in range(self.refine_boxes + 1):
            ta = time.perf_counter()
            kp2d, conf = self._crop_keypoints(x, scale_boxes(cur, self.box_scale), idx, obj_ids, crop_tta)
            tb = time.perf_counter()
            if pts3d.shape[1] != kp2d.shape[1]:
                raise self.input_error(f"KPD returned {kp2d.shape[1]} keypoints but keypoints_3d has "
                                       f"{pts3d.shape[1]}")
            est = solve_top_l(self.pnp, pts3d, kp2d, Kn, conf, self.top_l)
            t_kpd += tb - ta
            t_pnp += time.perf_counter() - tb
            if it < self.refine_boxes:
                cur = self._boxes_from_poses(est, obj_ids, img_idx, Ks, cur, hw, dscale)
        used = top_l_mask(conf, self.top_l)
        pose_records(est, boxes, hw, img_idx, obj_ids, scores, kp2d, conf, used, out,
                     points_3d=pts3d, K=Kn, min_confidence=self.min_confidence,
                     residual_scale_px=self.residual_scale_px, depth_calibration=dscale)
        self.last_timings = {"detect": 0.0, "kpd": t_kpd, "pnp": t_pnp, "total": t_kpd + t_pnp}
        return out

    def _crop_keypoints(self, x, boxes: np.ndarray, idx: np.ndarray, obj_ids: list[int], n: int | None = None):
        """``_keypoints`` on ``boxes``; with n (None: ``crop_tta``) > 1 one KPD call on n crops of each box
        (:func:`tta_boxes`), combined by :func:`combine_tta`."""
        n = self.crop_tta if n is None else int(n)
        if n == 1:
            return self._keypoints(x, boxes, idx, obj_ids)
        kp2d, conf = self._keypoints(x, tta_boxes(boxes, n), np.tile(idx, n), list(obj_ids) * n)
        return combine_tta(kp2d, conf, n, self.crop_tta_stability)

    def depth_factors(self, obj_ids) -> np.ndarray | None:
        """The ``depth_calibration`` factor of each of ``obj_ids`` (None when every factor is 1)."""
        f = np.array([self.depth_calibration_per_object.get(int(o), self.depth_calibration_default) for o in obj_ids],
                     dtype=np.float64)
        return None if (f == 1.0).all() else f

    def _boxes_from_poses(self, est, obj_ids, img_idx, Ks, boxes: np.ndarray, hw,
                          depth_calibration: np.ndarray | None = None) -> np.ndarray:
        """Box refinement: each solved instance's box becomes the box of its object's surface points
        projected with the estimated pose (its translation times ``depth_calibration``), clipped to the image;
        failed or degenerate ones keep theirs."""
        H, W = int(hw[0]), int(hw[1])
        new = np.array(boxes, dtype=np.float64)
        for n, (oid, b) in enumerate(zip(obj_ids, img_idx)):
            if not bool(est.ok[n]):
                continue
            t = np.asarray(est.t[n], dtype=np.float64) * (1.0 if depth_calibration is None else depth_calibration[n])
            uv, z = project_points(self.object_points(oid), Ks[b], np.asarray(est.R[n]), t, return_depth=True)
            if not (z > 0).all() or not np.isfinite(uv).all():
                continue
            box = clip_box_to_image(uv.min(0), uv.max(0), W, H)
            if box is not None:
                new[n] = box
        return new
