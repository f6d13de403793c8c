"""BOP file formats: the JSON readers and writers -- the one place for BOP formats (generic file
I/O, atomic writes included, is :mod:`kpd6d.io`).

Layout (https://github.com/thodan/bop_toolkit/blob/master/docs/bop_datasets_format.md)::

    <root>/camera.json                     fx, fy, cx, cy, width, height, depth_scale
    <root>/models/models_info.json         (+ obj_XXXXXX.ply, keypoints.json)
    <root>/<split>/<scene:06d>/scene_gt.json        {im_id: [{cam_R_m2c, cam_t_m2c, obj_id}, ...]}
    <root>/<split>/<scene:06d>/scene_camera.json    {im_id: {cam_K, depth_scale}}
    <root>/<split>/<scene:06d>/scene_gt_info.json   {im_id: [{bbox_obj, bbox_visib, px_count_*, visib_fract}]}
    <root>/<split>/<scene:06d>/rgb/<im:06d>.png     (or .jpg)
    <root>/<split>/<scene:06d>/mask_visib/<im:06d>_<gt:06d>.png
    <root>/<split>/<scene:06d>/depth/<im:06d>.png   uint16, depth_mm = value * depth_scale

``cam_R_m2c`` is a row-major 3x3 rotation, ``cam_t_m2c`` a translation in mm (model -> OpenCV camera).
Every writer puts its file in place atomically (:func:`kpd6d.io.atomic_write_json`: a temporary file in
the same folder, then ``os.replace``), so no half-written file ever sits under its final name.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kpd6d.geometry import rotation_problem

# the generic file helpers live in kpd6d.io; re-exported here for old import paths
from kpd6d.io import (
    FileFormatError,
    atomic_write_bytes,
    atomic_write_image,
    atomic_write_json,
    atomic_write_text,
    dumps_json,
    read_image,
    read_json,
)

__all__ = [
    "BOX_FIELDS",
    "DEFAULT_BOX_FIELD",
    "BopFormatError",
    "atomic_write_bytes",
    "atomic_write_image",
    "atomic_write_json",
    "atomic_write_text",
    "bbox_from_mask",
    "dumps_bop_json",
    "load_camera",
    "load_scene_camera",
    "load_scene_gt",
    "load_scene_gt_info",
    "load_targets",
    "read_image",
    "read_json",
    "save_camera",
    "save_scene_camera",
    "save_scene_gt",
    "save_scene_gt_info",
]


class BopFormatError(FileFormatError):
    """A BOP file that is missing, malformed or lacks a field; the message names the file and field."""


dumps_bop_json = dumps_json  # the JSON layout bop_toolkit writes (kpd6d.io.dumps_json)


def _read_bop_json(path: Path, what: str) -> Any:
    return read_json(path, what=what, error=BopFormatError)


def _im_dict(path: Path, raw: Any) -> dict[int, Any]:
    if not isinstance(raw, dict):
        raise BopFormatError(f"{path}: expected an object mapping image ids to entries, got {type(raw).__name__}")
    out = {}
    for key, v in raw.items():
        try:
            out[int(key)] = v
        except ValueError:
            raise BopFormatError(f"{path}: image id {key!r} is not an integer") from None
    return dict(sorted(out.items()))


def _field(path: Path, where: str, entry: Any, name: str, length: int | None = None,
           kind: type = float) -> Any:
    if not isinstance(entry, dict):
        raise BopFormatError(f"{path}: {where} is a {type(entry).__name__}, expected an object")
    if name not in entry:
        raise BopFormatError(f"{path}: {where} has no field {name!r} (fields: {sorted(entry)})")
    v = entry[name]
    if length is None:
        try:
            return kind(v)
        except (TypeError, ValueError):
            raise BopFormatError(f"{path}: {where} field {name!r} = {v!r} is not a {kind.__name__}") from None
    try:
        arr = np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise BopFormatError(f"{path}: {where} field {name!r} is not a list of numbers: {v!r}") from None
    if arr.size != length:
        raise BopFormatError(f"{path}: {where} field {name!r} has {arr.size} values, expected {length}")
    if not np.isfinite(arr).all():
        raise BopFormatError(f"{path}: {where} field {name!r} has non-finite values: {v!r}")
    return arr


def load_scene_gt(path: str | os.PathLike) -> dict[int, list[dict]]:
    """``scene_gt.json`` -> ``{im_id: [{"obj_id": int, "R": (3, 3), "t": (3,) mm}, ...]}``."""
    path = Path(path)
    raw = _im_dict(path, _read_bop_json(path, "scene_gt.json"))
    out: dict[int, list[dict]] = {}
    for im_id, entries in raw.items():
        if not isinstance(entries, list):
            raise BopFormatError(f"{path}: image {im_id} holds a {type(entries).__name__}, expected a list of instances")
        insts = []
        for j, e in enumerate(entries):
            where = f"image {im_id} instance {j}"
            R = _field(path, where, e, "cam_R_m2c", 9).reshape(3, 3)
            why = rotation_problem(R)
            if why:
                raise BopFormatError(f"{path}: {where} field 'cam_R_m2c' {why}: {e['cam_R_m2c']!r}")
            insts.append({
                "obj_id": _field(path, where, e, "obj_id", kind=int),
                "R": R,
                "t": _field(path, where, e, "cam_t_m2c", 3),
            })
        out[im_id] = insts
    return out


def load_scene_camera(path: str | os.PathLike) -> dict[int, dict]:
    """``scene_camera.json`` -> ``{im_id: {"K": (3, 3), "depth_scale": float | None}}``."""
    path = Path(path)
    raw = _im_dict(path, _read_bop_json(path, "scene_camera.json"))
    out = {}
    for im_id, e in raw.items():
        where = f"image {im_id}"
        K = _field(path, where, e, "cam_K", 9).reshape(3, 3)
        ds = _field(path, where, e, "depth_scale") if isinstance(e, dict) and "depth_scale" in e else None
        out[im_id] = {"K": K, "depth_scale": ds}
    return out


# the GT boxes of scene_gt_info.json a detector can be trained on and an oracle can give: the visible part's box
# (the default: what BOP's detections and the paper's crops are) and the whole object's (amodal) box
BOX_FIELDS = ("bbox_visib", "bbox_obj")
DEFAULT_BOX_FIELD = "bbox_visib"

_GT_INFO_FIELDS = ("bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib", "visib_fract")


def load_scene_gt_info(path: str | os.PathLike) -> dict[int, list[dict]]:
    """``scene_gt_info.json`` -> ``{im_id: [{"bbox_obj": (4,) int, "bbox_visib", "px_count_all",
    "px_count_valid", "px_count_visib", "visib_fract"}, ...]}``."""
    path = Path(path)
    raw = _im_dict(path, _read_bop_json(path, "scene_gt_info.json"))
    out: dict[int, list[dict]] = {}
    for im_id, entries in raw.items():
        if not isinstance(entries, list):
            raise BopFormatError(f"{path}: image {im_id} holds a {type(entries).__name__}, expected a list of instances")
        infos = []
        for j, e in enumerate(entries):
            where = f"image {im_id} instance {j}"
            d = {
                "bbox_obj": _field(path, where, e, "bbox_obj", 4).astype(np.int64),
                "bbox_visib": _field(path, where, e, "bbox_visib", 4).astype(np.int64),
                "px_count_visib": _field(path, where, e, "px_count_visib", kind=int),
                "visib_fract": _field(path, where, e, "visib_fract"),
            }
            for name in ("px_count_all", "px_count_valid"):
                d[name] = _field(path, where, e, name, kind=int) if name in e else None
            infos.append(d)
        out[im_id] = infos
    return out


def load_camera(path: str | os.PathLike) -> dict:
    """BOP ``camera.json`` -> ``{"K": (3, 3), "width", "height", "depth_scale"}``."""
    path = Path(path)
    e = _read_bop_json(path, "camera.json")
    where = "camera"
    fx, fy, cx, cy = (_field(path, where, e, k) for k in ("fx", "fy", "cx", "cy"))
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return {
        "K": K,
        "width": _field(path, where, e, "width", kind=int),
        "height": _field(path, where, e, "height", kind=int),
        "depth_scale": float(e.get("depth_scale", 1.0)),
    }


def load_targets(path: str | os.PathLike) -> dict[tuple[int, int], dict[int, int]]:
    """BOP19 ``test_targets_bop19.json`` -> ``{(scene_id, im_id): {obj_id: inst_count}}``."""
    path = Path(path)
    raw = _read_bop_json(path, "targets file")
    if not isinstance(raw, list):
        raise BopFormatError(f"{path}: expected a list of targets, got {type(raw).__name__}")
    out: dict[tuple[int, int], dict[int, int]] = {}
    for j, e in enumerate(raw):
        where = f"target {j}"
        key = (_field(path, where, e, "scene_id", kind=int), _field(path, where, e, "im_id", kind=int))
        oid = _field(path, where, e, "obj_id", kind=int)
        cnt = _field(path, where, e, "inst_count", kind=int)
        out.setdefault(key, {})
        out[key][oid] = out[key].get(oid, 0) + cnt
    return out


# ---------------------------------------------------------------------------------------------
# writers
# ---------------------------------------------------------------------------------------------
def _floats(a: Any) -> list[float]:
    return [float(x) for x in np.asarray(a, dtype=np.float64).reshape(-1)]


def save_scene_gt(path: str | os.PathLike, scene_gt: Mapping[int, Sequence[Mapping]]) -> Path:
    """Write ``{im_id: [{"obj_id", "R" (3, 3), "t" (3,) mm}]}`` as BOP ``scene_gt.json``."""
    data = {
        str(int(im)): [
            {"cam_R_m2c": _floats(e["R"]), "cam_t_m2c": _floats(e["t"]), "obj_id": int(e["obj_id"])} for e in insts
        ]
        for im, insts in sorted(scene_gt.items())
    }
    return atomic_write_json(path, data)


def save_scene_camera(path: str | os.PathLike, scene_camera: Mapping[int, Mapping]) -> Path:
    """Write ``{im_id: {"K" (3, 3), "depth_scale"}}`` as BOP ``scene_camera.json``."""
    data = {}
    for im, e in sorted(scene_camera.items()):
        d: dict[str, Any] = {"cam_K": _floats(e["K"])}
        if e.get("depth_scale") is not None:
            d["depth_scale"] = float(e["depth_scale"])
        data[str(int(im))] = d
    return atomic_write_json(path, data)


def save_scene_gt_info(path: str | os.PathLike, scene_gt_info: Mapping[int, Sequence[Mapping]]) -> Path:
    """Write ``{im_id: [{bbox_obj, bbox_visib, px_count_all, px_count_valid, px_count_visib, visib_fract}]}``."""
    data = {}
    for im, infos in sorted(scene_gt_info.items()):
        rows = []
        for e in infos:
            row = {
                "bbox_obj": [int(v) for v in e["bbox_obj"]],
                "bbox_visib": [int(v) for v in e["bbox_visib"]],
                "px_count_visib": int(e["px_count_visib"]),
                "visib_fract": float(e["visib_fract"]),
            }
            for name in ("px_count_all", "px_count_valid"):
                if e.get(name) is not None:
                    row[name] = int(e[name])
            rows.append(row)
        data[str(int(im))] = rows
    return atomic_write_json(path, data)


def save_camera(path: str | os.PathLike, K: np.ndarray, width: int, height: int, depth_scale: float = 1.0) -> Path:
    """Write a BOP dataset ``camera.json``."""
    K = np.asarray(K, dtype=np.float64)
    return atomic_write_json(path, {
        "cx": float(K[0, 2]), "cy": float(K[1, 2]), "depth_scale": float(depth_scale),
        "fx": float(K[0, 0]), "fy": float(K[1, 1]), "height": int(height), "width": int(width),
    })


def bbox_from_mask(mask: np.ndarray) -> list[int]:
    """BOP box (x, y, w, h) of a mask's pixels as bop_toolkit's ``calc_2d_bbox``: w = x_max - x_min
    (pixel indices); ``[-1, -1, -1, -1]`` for an empty mask."""
    ys = np.flatnonzero(mask.any(axis=1))
    if ys.size == 0:
        return [-1, -1, -1, -1]
    xs = np.flatnonzero(mask.any(axis=0))
    return [int(xs[0]), int(ys[0]), int(xs[-1] - xs[0]), int(ys[-1] - ys[0])]
