"""File I/O for every package: atomic writes, JSON / image reading, plain values for files.

A leaf module (standard library, numpy and OpenCV only; no other kpd6d module), so any layer may
use it. Every writer puts its file in place atomically: it writes a temporary file in the same
folder and renames it (``os.replace``), so no half-written file ever sits under its final name.
BOP file formats (scene_gt.json, camera.json, ...) live in :mod:`kpd6d.data.bop_io`.
"""

from __future__ import annotations

import errno
import json
import os
import sys
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "FileFormatError",
    "atomic_write_bytes",
    "atomic_write_image",
    "atomic_write_json",
    "atomic_write_text",
    "dumps_json",
    "read_image",
    "read_json",
    "stack_rgb_images",
    "to_plain",
    "write_error",
]


def _default_file_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


_FILE_MODE = _default_file_mode()


class FileFormatError(ValueError):
    """A file that is missing, malformed or not of the expected kind; the message names the file."""


def to_plain(x: Any) -> Any:
    """OmegaConf nodes, numpy arrays / scalars, mappings and sequences -> plain Python values
    (so hyper-parameters pickle, and JSON / YAML files are written cleanly)."""
    oc = sys.modules.get("omegaconf")  # an OmegaConf node implies omegaconf is imported
    if oc is not None and isinstance(x, (oc.DictConfig, oc.ListConfig)):
        return oc.OmegaConf.to_container(x, resolve=True)
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, Mapping):
        return {k: to_plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_plain(v) for v in x]
    return x


# ---------------------------------------------------------------------------------------------
# atomic writes
# ---------------------------------------------------------------------------------------------
_WRITE_HINTS = {
    errno.ENOSPC: "the disk is full: free space there or choose another output folder",
    errno.EDQUOT: "the disk quota is exceeded: free space there or choose another output folder",
    errno.EROFS: "the file system is read-only: choose another output folder",
    errno.EACCES: "the folder is not writable: fix its permissions or choose another output folder",
    errno.EPERM: "the folder is not writable: fix its permissions or choose another output folder",
}


def write_error(path: str | os.PathLike, exc: OSError) -> OSError:
    """``exc`` (from writing ``path``) as an OSError of the same kind (same errno, so ENOSPC stays
    ENOSPC and EACCES a PermissionError) whose message names the destination and what to do."""
    hint = _WRITE_HINTS.get(exc.errno or -1)
    why = exc.strerror or str(exc)
    msg = f"cannot write '{path}': {why}" + (f"; {hint}" if hint else "")
    return OSError(exc.errno, msg) if exc.errno is not None else OSError(msg)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder + ``os.replace``.

    An OSError (full disk, read-only or unwritable folder, ...) is re-raised by :func:`write_error`:
    same errno, message naming ``path`` with a hint; no temporary file is left behind."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise write_error(path, exc) from exc
    try:
        os.fchmod(fd, _FILE_MODE)  # mkstemp makes 0600 files; give the usual permissions
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(exc, OSError):
            raise write_error(path, exc) from exc
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode())


def dumps_json(data: Any) -> str:
    """JSON text as bop_toolkit writes it: a dict puts one key per line, values compact."""
    if isinstance(data, Mapping):
        items = [f"  {json.dumps(str(k))}: {json.dumps(to_plain(v), sort_keys=True)}" for k, v in data.items()]
        return "{\n" + ",\n".join(items) + "\n}\n"
    if isinstance(data, list):
        return "[\n" + ",\n".join("  " + json.dumps(to_plain(v), sort_keys=True) for v in data) + "\n]\n"
    return json.dumps(to_plain(data), sort_keys=True, indent=2) + "\n"


def atomic_write_json(path: str | os.PathLike, data: Any) -> Path:
    """Write ``data`` as JSON (bop_toolkit style, :func:`dumps_json`) atomically."""
    return atomic_write_bytes(path, dumps_json(data).encode())


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


# ---------------------------------------------------------------------------------------------
# readers
# ---------------------------------------------------------------------------------------------
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


def read_json(path: str | os.PathLike, *, what: str = "JSON file", error: type[Exception] = FileFormatError) -> Any:
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


def stack_rgb_images(images, error: type[Exception] = ValueError) -> np.ndarray:
    """uint8 RGB images (H, W, 3) (a list or a (B, H, W, 3) array, equal sizes) -> uint8 (B, H, W, 3);
    a wrong shape, dtype or a mixed-size batch raises ``error`` naming the image."""
    arr = [np.asarray(im) for im in (images if isinstance(images, (list, tuple)) else list(np.asarray(images)))]
    for i, im in enumerate(arr):
        if im.ndim != 3 or im.shape[2] != 3:
            raise error(f"image {i} must be (H, W, 3) RGB, got shape {im.shape}")
        if im.dtype != np.uint8:
            raise error(f"image {i} must be uint8 RGB (0..255), got dtype {im.dtype}")
        if im.shape != arr[0].shape:
            raise error(f"images of one batch must have one size: image 0 is {arr[0].shape}, image {i} is {im.shape}")
    return np.stack(arr)
