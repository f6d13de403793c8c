"""Pose prediction on an image, a folder of images or a video (what ``kpd6d-predict`` runs).

:func:`predict_inputs` runs a :class:`kpd6d.pipeline.PosePipeline` over the frames and writes
``poses.json`` (one entry per image / video frame), ``poses.csv`` (BOP results format, scene_id 0,
im_id = image index / frame number) and overlays (3D boxes in blue, used keypoints as dots, drawn by
:func:`kpd6d.visualize.draw_predictions`): one PNG per image, or ``overlay.mp4`` for a video.
:func:`load_intrinsics` reads the camera: a BOP ``camera.json`` (fx, fy, cx, cy), or a JSON / text
file holding a 3x3 matrix; None -> the LineMod camera. :func:`predict_from_config` does all of it
for a composed ``conf/predict.yaml``.

Every pose in ``poses.json`` holds ``confidence`` (in [0, 1], :mod:`kpd6d.pnp.confidence`) and ``ok``.
``track`` (a dict of :class:`kpd6d.tracking.PoseTracker` options: ``detect_every``, ``lost_threshold``,
``smoothing``, ``margin``, ``min_in_view``, ``obj_ids``) tracks the objects over the frames in order
(a video, a camera, a folder as an image sequence): each pose then also holds ``source``
(``detector`` / ``track``) and ``reason``, each frame ``detected`` (whether the detector ran), and the
summary ``detector_calls``. ``input`` may be a camera index (``0``: ``cv2.VideoCapture(0)``), read until
it stops or ``max_frames``.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from kpd6d.config import cfg_float, cfg_int, to_int
from kpd6d.geometry import LINEMOD_K
from kpd6d.io import atomic_write_image, atomic_write_text, to_plain
from kpd6d.visualize import draw_predictions

__all__ = ["IMAGE_EXTS", "TRACK_OPTIONS", "VIDEO_EXTS", "corners_from_kpd", "expand_track_override", "is_camera",
           "load_intrinsics", "predict_from_config", "predict_inputs", "track_options"]

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_EXTS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v")
TRACK_OPTIONS = ("detect_every", "search_every", "lost_threshold", "smoothing", "margin", "min_in_view", "obj_ids")
_BOOLS = {"true": "true", "false": "false", "1": "true", "0": "false", "yes": "true", "no": "false", "on": "true",
          "off": "false"}


def is_camera(source) -> bool:
    """Whether ``input`` names a camera: a non-negative integer (``0``, or ``"1"`` when no such file exists),
    read with cv2.VideoCapture(int)."""
    if isinstance(source, bool):
        return False
    if isinstance(source, int):
        return source >= 0
    return isinstance(source, str) and source.isdigit() and not os.path.exists(source)


def expand_track_override(args: list[str]) -> list[str]:
    """Command-line overrides with ``track=true|false`` spelled ``track.enabled=...``: ``track`` is a
    settings node (``track.detect_every=5`` ...), which Hydra would replace by the bare boolean."""
    out = []
    for a in args:
        key, eq, val = str(a).partition("=")
        if eq and key == "track" and val.strip().lower() in _BOOLS:
            a = f"track.enabled={_BOOLS[val.strip().lower()]}"
        out.append(a)
    return out


def track_options(node) -> dict | None:
    """The :class:`kpd6d.tracking.PoseTracker` options of a config's ``track`` node (None: no tracking).
    ``track`` may be a bool or a dict with ``enabled`` and the options; unknown keys raise ``ValueError``."""
    if node is None or node is False:
        return None
    if node is True:
        return {}
    if hasattr(node, "items"):
        d = {str(k): v for k, v in node.items()}
        if not bool(d.pop("enabled", True)):
            return None
        unknown = sorted(set(d) - set(TRACK_OPTIONS))
        if unknown:
            raise ValueError(f"track.{unknown[0]}: unknown tracking setting; known: enabled, {', '.join(TRACK_OPTIONS)}")
        out = {k: v for k, v in d.items() if v is not None}
        if "obj_ids" in out:
            out["obj_ids"] = [int(o) for o in out["obj_ids"]]
        for k in ("detect_every", "search_every"):
            if k in out:
                out[k] = to_int(out[k], f"track.{k}")
        for k in ("lost_threshold", "smoothing", "margin", "min_in_view"):
            if k in out:
                try:
                    out[k] = float(out[k])
                except (TypeError, ValueError):
                    raise ValueError(f"track.{k} must be a number, got {out[k]!r}") from None
        return out
    raise ValueError(f"track must be true/false or a dict of tracking settings, got {node!r}")


def load_intrinsics(path: str | os.PathLike | None) -> np.ndarray:
    """K (3, 3) from a BOP camera.json, a JSON 3x3 / 9-list (or ``{"K"|"cam_K": ...}``) or a text file; None -> LineMod."""
    if path is None:
        return LINEMOD_K.copy()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"camera={str(path)!r}: intrinsics file does not exist")
    text = path.read_text()
    try:
        data = json.loads(text)
    except json.JSONDecodeError:
        data = None
    if data is None:
        try:
            vals = np.array(text.replace(",", " ").split(), dtype=np.float64)
        except ValueError:
            raise ValueError(f"{path}: expected 9 numbers (a 3x3 K) or JSON") from None
    elif isinstance(data, dict) and all(k in data for k in ("fx", "fy", "cx", "cy")):
        vals = np.array([data["fx"], 0, data["cx"], 0, data["fy"], data["cy"], 0, 0, 1], dtype=np.float64)
    elif isinstance(data, dict) and ("K" in data or "cam_K" in data):
        vals = np.asarray(data.get("K", data.get("cam_K")), dtype=np.float64).reshape(-1)
    elif isinstance(data, list):
        vals = np.asarray(data, dtype=np.float64).reshape(-1)
    else:
        raise ValueError(f"{path}: JSON must be a BOP camera.json (fx, fy, cx, cy), a 3x3 list or hold 'K'/'cam_K'")
    if vals.size != 9 or not np.isfinite(vals).all():
        raise ValueError(f"{path}: expected 9 finite numbers for K, got {vals.size}")
    K = vals.reshape(3, 3)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"{path}: focal lengths must be > 0, got fx={K[0, 0]}, fy={K[1, 1]}")
    return K


def _read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"{path}: cannot be read as an image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _try_read(path: Path):
    """(rgb, None) or (None, why) for an image of a folder: one bad file must not stop the others."""
    try:
        return _read_rgb(path), None
    except (ValueError, OSError, cv2.error) as exc:
        return None, str(exc)


def _frames(source, batch_size: int, max_frames: int | None = None):
    """Yield (kind, [(index, name, rgb)], fps, [(index, name, error)]) batches from an image, a folder of
    images, a video or a camera index; unreadable images of a folder come in the error list."""
    if is_camera(source):
        yield from _video_frames(cv2.VideoCapture(int(source)), f"camera {int(source)}", batch_size, max_frames)
        return
    source = Path(source)
    if source.is_dir():
        files = sorted(p for p in source.iterdir() if p.suffix.lower() in IMAGE_EXTS)
        if not files:
            raise FileNotFoundError(f"input={str(source)!r}: folder holds no images ({', '.join(IMAGE_EXTS)})")
        for i in range(0, len(files), batch_size):
            read = [(i + j, f.name, *_try_read(f)) for j, f in enumerate(files[i:i + batch_size])]
            yield ("images", [(k, n, im) for k, n, im, err in read if err is None], None,
                   [(k, n, err) for k, n, im, err in read if err is not None])
    elif source.suffix.lower() in VIDEO_EXTS:
        yield from _video_frames(cv2.VideoCapture(str(source)), f"input={str(source)!r}", batch_size, max_frames)
    elif source.is_file():
        yield "images", [(0, source.name, _read_rgb(source))], None, []
    else:
        raise FileNotFoundError(f"input={str(source)!r} does not exist")


def _video_frames(cap, what: str, batch_size: int, max_frames: int | None):
    if not cap.isOpened():
        raise ValueError(f"{what}: cannot open the video")
    fps = cap.get(cv2.CAP_PROP_FPS) or 25.0
    idx, batch = 0, []
    try:
        while max_frames is None or idx < max_frames:
            ok, frame = cap.read()
            if not ok:
                break
            batch.append((idx, f"frame_{idx:06d}", cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)))
            idx += 1
            if len(batch) == batch_size:
                yield "video", batch, fps, []
                batch = []
    finally:
        cap.release()
    if batch:
        yield "video", batch, fps, []
    if idx == 0:
        raise ValueError(f"{what}: the video has no readable frames")


def _count(source, max_frames: int | None = None) -> int | None:
    if is_camera(source):
        return max_frames
    source = Path(source)
    if source.is_dir():
        return sum(1 for p in source.iterdir() if p.suffix.lower() in IMAGE_EXTS)
    if source.suffix.lower() in VIDEO_EXTS:
        cap = cv2.VideoCapture(str(source))
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if cap.isOpened() else 0
        cap.release()
        n = n or None
        return n if max_frames is None or n is None else min(n, max_frames)
    return 1


def _pose_entry(p: dict) -> dict:
    e = {"obj_id": int(p["obj_id"]), "score": float(p["score"]), "ok": bool(p["ok"]),
         "confidence": float(p.get("confidence", float("nan"))),
         "R": np.asarray(p["R"]).tolist(), "t": np.asarray(p["t"]).tolist(), "box": np.asarray(p["box"]).tolist()}
    if "source" in p:
        e["source"] = p["source"]
    if "reason" in p:
        e["reason"] = str(p["reason"])
    if "refined" in p:
        e["refined"] = bool(p["refined"])
    return e


def predict_inputs(pipeline, source: str | os.PathLike | int, K: np.ndarray, out_dir: str | os.PathLike,
                   corners: dict[int, np.ndarray], batch_size: int = 4, overlays: bool = True,
                   progress: bool = True, stop_on_error: bool = False, track: dict | None = None,
                   max_frames: int | None = None) -> dict:
    """Run ``pipeline`` on an image / folder / video / camera index and write poses.json, poses.csv and
    overlays to ``out_dir``.

    An unreadable image of a folder is recorded (``poses.json`` ``"errors"``: index, name, why) and
    skipped, unless ``stop_on_error``; whatever was computed is written even when the run stops on an
    error. The returned ``"errors"`` lists the failures (the CLI then exits with status 1).
    ``track``: :class:`kpd6d.tracking.PoseTracker` options (None: every frame on its own with
    ``predict_batch``): the frames are tracked one by one in order. ``max_frames``: stop a video or
    camera after that many frames."""
    from tqdm import tqdm

    from kpd6d.evaluation.results_io import PoseResult, write_bop_results

    camera = is_camera(source)
    source = int(source) if camera else Path(source)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tracker = None
    if track is not None:
        from kpd6d.tracking import PoseTracker

        tracker = PoseTracker(pipeline, **track)
    entries, results, errors = [], [], []
    writer, video_tmp, video_path = None, None, out_dir / "overlay.mp4"
    try:
        with tqdm(total=_count(source, max_frames), desc="predict", unit="frame", disable=not progress) as bar:
            for kind, batch, fps, bad in _frames(source, max(1, int(batch_size)), max_frames):
                for idx, name, why in bad:
                    errors.append({"index": idx, "name": name, "error": why})
                    if stop_on_error:
                        raise ValueError(f"input={str(source)!r}: {why}")
                bar.update(len(bad))
                sizes = {im.shape for _, _, im in batch}
                groups = [batch] if len(sizes) == 1 and tracker is None else [[b] for b in batch]
                for g in groups:
                    t0 = time.perf_counter()
                    if tracker is None:
                        preds, extra = pipeline.predict_batch([im for _, _, im in g], K), [{}] * len(g)
                    else:
                        res = tracker.update(g[0][2], K)
                        preds, extra = [res["poses"]], [{"detected": res["detected"]}]
                    dt = (time.perf_counter() - t0) / len(g)
                    for (idx, name, im), ps, ex in zip(g, preds, extra):
                        entries.append({"index": idx, "name": name, "time": dt, **ex,
                                        "poses": [_pose_entry(p) for p in ps]})
                        results += [PoseResult(0, idx, p["obj_id"], p["score"], p["R"], p["t"], dt) for p in ps if p["ok"]]
                        if overlays:
                            ov = draw_predictions(im, K, ps, corners)
                            if kind == "video":
                                if writer is None:
                                    fd, video_tmp = tempfile.mkstemp(prefix=".overlay.", suffix=".mp4", dir=out_dir)
                                    os.close(fd)
                                    writer = cv2.VideoWriter(video_tmp, cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                                             (ov.shape[1], ov.shape[0]))
                                writer.write(cv2.cvtColor(ov, cv2.COLOR_RGB2BGR))
                            else:
                                atomic_write_image(out_dir / "overlays" / f"{Path(name).stem}.png", ov)
                    bar.update(len(g))
        if writer is not None:
            writer.release()
            writer = None
            os.replace(video_tmp, video_path)
    finally:
        if writer is not None:
            writer.release()
        if video_tmp and os.path.exists(video_tmp):
            os.unlink(video_tmp)
        # everything computed so far, also when an error stops the run
        summary = {"K": K.tolist(), "frames": entries, "errors": errors}
        if tracker is not None:
            summary["tracking"] = {**track, **tracker.stats}
        atomic_write_text(out_dir / "poses.json", json.dumps(summary, indent=1))
        write_bop_results(out_dir / "poses.csv", results)
    info = {"frames": len(entries), "poses": len(results), "out_dir": str(out_dir), "errors": errors}
    if tracker is not None:
        info["detector_calls"] = tracker.stats["detector_calls"]
    return info


def corners_from_kpd(kpd) -> dict[int, np.ndarray]:
    """3D box corners per object from the KPD's surface points (a checkpoint's model points, else its
    keypoints; also for one KPD per object and the exported runtime's KPD)."""
    out = {}
    for oid, kp in kpd.keypoints_3d.items():
        p = np.asarray(kpd.surface_points(int(oid)) if hasattr(kpd, "surface_points") else kp, float).reshape(-1, 3)
        lo, hi = p.min(0), p.max(0)
        out[int(oid)] = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
    return out


def predict_from_config(cfg, out_dir: str | os.PathLike) -> dict:
    """Build the pipeline from a composed ``conf/predict.yaml`` and run :func:`predict_inputs` into ``out_dir``."""
    from omegaconf import OmegaConf

    from kpd6d.detection.detectors import check_detector_overrides
    from kpd6d.pipeline import PosePipeline
    from kpd6d.pnp.estimator import candidate_options
    from kpd6d.refinement import build_refiner

    backend = str(cfg.get("backend") or "torch")
    torch_backend = backend == "torch"  # the other backends run an export (export_dir=): no checkpoints needed
    det = OmegaConf.select(cfg, "detector_ckpt", default=None, throw_on_missing=torch_backend)
    if str(det) == "oracle":
        raise ValueError("kpd6d-predict needs a trained detector (detector_ckpt=<file>): the oracle needs GT boxes")
    K = load_intrinsics(cfg.camera)
    refiner = build_refiner(to_plain(cfg.get("refiner")))  # its meshes, or the error naming them, before the networks
    pipe = PosePipeline.for_backend(backend, detector_ckpt=det,
                                    kpd_ckpt=OmegaConf.select(cfg, "kpd_ckpt", default=None, throw_on_missing=torch_backend),
                                    export_dir=cfg.get("export_dir"), pnp=OmegaConf.to_container(cfg.pnp, resolve=True),
                                    top_l=cfg.select.top_l, refine_boxes=to_int(cfg.get("refine_boxes", 0) or 0, "refine_boxes"),
                                    min_confidence=float(cfg.get("min_confidence", 0.0) or 0.0), device=cfg.device,
                                    box_scale=cfg_float(cfg, "box_scale", 1.0),
                                    crop_tta=to_plain(cfg.get("crop_tta", 1)),
                                    depth_calibration=to_plain(cfg.get("depth_calibration", 1.0)),
                                    **candidate_options(cfg.get("candidates", 1), det, ValueError,
                                                        check_detector_overrides(to_plain(cfg.get("detector_overrides")))))
    pipe.set_refiner(refiner)
    max_frames = cfg.get("max_frames")
    return predict_inputs(pipe, cfg.input, K, out_dir, corners_from_kpd(pipe.kpd), batch_size=cfg_int(cfg, "batch_size"),
                          overlays=bool(cfg.overlays), progress=bool(cfg.progress),
                          stop_on_error=bool(cfg.get("stop_on_error", False)), track=track_options(cfg.get("track")),
                          max_frames=None if max_frames is None else to_int(max_frames, "max_frames"))
