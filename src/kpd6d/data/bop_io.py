"""BOP file formats: JSON readers/writers and atomic file writes -- the one place for BOP I/O.

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
Every writer puts its file in place atomically: it writes ``<name>.tmp-<pid>`` in the same folder and
renames it (``os.replace``), so no half-written file ever sits under its final name.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kpd6d.config import to_plain

__all__ = [
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


def _default_file_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


_FILE_MODE = _default_file_mode()


class BopFormatError(ValueError):
    """A BOP file that is missing, malformed or lacks a field; the message names the file and field."""


# ---------------------------------------------------------------------------------------------
# atomic writes
# ---------------------------------------------------------------------------------------------
def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder + ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, _FILE_MODE)  # mkstemp makes 0600 files; give the usual permissions
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode())


def dumps_bop_json(data: Any) -> str:
    """JSON text as bop_toolkit writes it: a dict puts one key per line, values compact."""
    if isinstance(data, Mapping):
        items = [f"  {json.dumps(str(k))}: {json.dumps(to_plain(v), sort_keys=True)}" for k, v in data.items()]
        return "{\n" + ",\n".join(items) + "\n}\n"
    if isinstance(data, list):
        return "[\n" + ",\n".join("  " + json.dumps(to_plain(v), sort_keys=True) for v in data) + "\n]\n"
    return json.dumps(to_plain(data), sort_keys=True, indent=2) + "\n"


def atomic_write_json(path: str | os.PathLike, data: Any) -> Path:
    """Write ``data`` as JSON (bop_toolkit style) atomically."""
    return atomic_write_bytes(path, dumps_bop_json(data).encode())


def atomic_write_image(path: str | os.PathLike, image: np.ndarray, *, png_compression: int = 1,
                       jpg_quality: int = 95) -> Path:
    """Encode ``image`` (RGB uint8 (H, W, 3), or a (H, W) uint8/uint16 single channel) by the
    extension of ``path`` (.png / .jpg) and write it atomically."""
    import cv2

    path = Path(path)
    ext = path.suffix.lower()
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., ::-1]  # RGB -> BGR for OpenCV
    if ext == ".png":
        params = [cv2.IMWRITE_PNG_COMPRESSION, int(png_compression)]
    elif ext in (".jpg", ".jpeg"):
        params = [cv2.IMWRITE_JPEG_QUALITY, int(jpg_quality)]
    else:
        raise ValueError(f"{path}: unsupported image extension {ext!r}; use .png or .jpg")
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(img), params)
    if not ok:
        raise OSError(f"{path}: OpenCV could not encode a {img.dtype} image of shape {img.shape}")
    return atomic_write_bytes(path, buf.tobytes())


def read_image(path: str | os.PathLike, *, flags: int | None = None) -> np.ndarray:
    """Read an image with OpenCV; colour images come back RGB uint8. Errors name the path."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image file does not exist")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED if flags is None else flags)
    if img is None:
        raise OSError(f"{path}: cannot be read as an image (corrupt or unsupported format)")
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = img[..., :3]
        img = np.ascontiguousarray(img[..., ::-1])
    return img


# ---------------------------------------------------------------------------------------------
# readers
# ---------------------------------------------------------------------------------------------
def read_json(path: str | os.PathLike, *, what: str = "JSON file", error: type[Exception] = BopFormatError) -> Any:
    """Parse a JSON file; a missing, non-text or malformed file raises ``error`` naming the file."""
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: {what} does not exist")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise error(f"{path}: invalid JSON ({exc})") from exc
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not a text file ({exc})") from exc


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
    raw = _im_dict(path, read_json(path, what="scene_gt.json"))
    out: dict[int, list[dict]] = {}
    for im_id, entries in raw.items():
        if not isinstance(entries, list):
            raise BopFormatError(f"{path}: image {im_id} holds a {type(entries).__name__}, expected a list of instances")
        insts = []
        for j, e in enumerate(entries):
            where = f"image {im_id} instance {j}"
            insts.append({
                "obj_id": _field(path, where, e, "obj_id", kind=int),
                "R": _field(path, where, e, "cam_R_m2c", 9).reshape(3, 3),
                "t": _field(path, where, e, "cam_t_m2c", 3),
            })
        out[im_id] = insts
    return out


def load_scene_camera(path: str | os.PathLike) -> dict[int, dict]:
    """``scene_camera.json`` -> ``{im_id: {"K": (3, 3), "depth_scale": float | None}}``."""
    path = Path(path)
    raw = _im_dict(path, read_json(path, what="scene_camera.json"))
    out = {}
    for im_id, e in raw.items():
        where = f"image {im_id}"
        K = _field(path, where, e, "cam_K", 9).reshape(3, 3)
        ds = _field(path, where, e, "depth_scale") if isinstance(e, dict) and "depth_scale" in e else None
        out[im_id] = {"K": K, "depth_scale": ds}
    return out


_GT_INFO_FIELDS = ("bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib", "visib_fract")


def load_scene_gt_info(path: str | os.PathLike) -> dict[int, list[dict]]:
    """``scene_gt_info.json`` -> ``{im_id: [{"bbox_obj": (4,) int, "bbox_visib", "px_count_all",
    "px_count_valid", "px_count_visib", "visib_fract"}, ...]}``."""
    path = Path(path)
    raw = _im_dict(path, read_json(path, what="scene_gt_info.json"))
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
    e = read_json(path, what="camera.json")
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
    raw = read_json(path, what="targets file")
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
