"""Keypoint JSON files: designated 3D keypoints per object, with how they were made.

Format (``<root>/models/keypoints.json`` in a dataset, or the ``kpd6d-designate`` cache)::

    {
      "format": "kpd6d-keypoints", "version": 1,
      "designator": "sift", "params": {"num_keypoints": 50, ...},
      "objects": {"1": {"points": [[x, y, z], ...], "fingerprint": "..."}, ...}
    }

Points are in the model frame, millimetres. ``fingerprint`` (optional) identifies the mesh the
points were designated on (see :func:`model_fingerprint`) so that a cache is not reused for a
changed mesh. Files are written atomically (temporary file + ``os.replace``).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "KeypointFile",
    "KeypointFileError",
    "load_keypoints",
    "model_fingerprint",
    "read_keypoint_file",
    "save_keypoints",
]

FORMAT = "kpd6d-keypoints"
VERSION = 1


class KeypointFileError(ValueError):
    """A keypoint file that cannot be used; the message names the file and the field."""


@dataclass
class KeypointFile:
    """Everything in a keypoint file: points per object id and their provenance."""

    points: dict[int, np.ndarray]
    designator: str | None = None
    params: dict[str, Any] = field(default_factory=dict)
    fingerprints: dict[int, str] = field(default_factory=dict)


def model_fingerprint(model) -> str:
    """A short hash of a model's vertices and faces (identifies the mesh keypoints belong to)."""
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(np.round(model.vertices, 4), dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(model.faces, dtype=np.int64).tobytes())
    return h.hexdigest()[:16]


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (str, int, float, bool)):
        return value
    try:  # OmegaConf containers
        from omegaconf import DictConfig, ListConfig, OmegaConf

        if isinstance(value, (DictConfig, ListConfig)):
            return _jsonable(OmegaConf.to_container(value, resolve=True))
    except ImportError:  # pragma: no cover
        pass
    raise TypeError(f"keypoint file params must be JSON values; got {type(value).__name__}: {value!r}")


def save_keypoints(path: str | os.PathLike, keypoints: dict[int, Any], *, designator: str | None = None,
                   params: dict[str, Any] | None = None, fingerprints: dict[int, str] | None = None) -> Path:
    """Write ``{obj_id: (k, 3) points}`` (model frame, mm) to ``path`` atomically; returns the path."""
    path = Path(path)
    objects = {}
    for oid, pts in sorted(keypoints.items(), key=lambda kv: int(kv[0])):
        arr = np.asarray(pts, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) == 0:
            raise KeypointFileError(f"{path}: keypoints of object {oid} must have shape (k, 3), got {arr.shape}")
        if not np.isfinite(arr).all():
            raise KeypointFileError(f"{path}: keypoints of object {oid} contain NaN/inf")
        entry: dict[str, Any] = {"points": arr.tolist()}
        if fingerprints and int(oid) in fingerprints:
            entry["fingerprint"] = str(fingerprints[int(oid)])
        objects[str(int(oid))] = entry
    doc = {"format": FORMAT, "version": VERSION, "designator": designator,
           "params": _jsonable(dict(params or {})), "objects": objects}
    from kpd6d.io import atomic_write_text

    text = json.dumps(doc, indent=1)
    # one line per point: collapse the innermost numeric lists
    text = re.sub(r"\[\s+([-+0-9.eE,\s]+?)\s+\]", lambda mt: "[" + " ".join(mt.group(1).split()) + "]", text)
    atomic_write_text(path, text)
    return path


def read_keypoint_file(path: str | os.PathLike) -> KeypointFile:
    """Read a keypoint file with its provenance; errors name the file and the offending field."""
    from kpd6d.io import read_json

    path = Path(path)
    doc = read_json(path, what="keypoint file", error=KeypointFileError)
    if not isinstance(doc, dict) or "objects" not in doc:
        raise KeypointFileError(f"{path}: missing field 'objects' (not a kpd6d keypoint file)")
    if doc.get("format", FORMAT) != FORMAT:
        raise KeypointFileError(f"{path}: field 'format' is {doc.get('format')!r}, expected {FORMAT!r}")
    if not isinstance(doc["objects"], dict):
        raise KeypointFileError(f"{path}: field 'objects' must map object ids to entries")
    points: dict[int, np.ndarray] = {}
    fps: dict[int, str] = {}
    for key, entry in doc["objects"].items():
        try:
            oid = int(key)
        except ValueError:
            raise KeypointFileError(f"{path}: object id {key!r} in 'objects' is not an integer") from None
        raw = entry.get("points") if isinstance(entry, dict) else entry
        if raw is None:
            raise KeypointFileError(f"{path}: objects.{key} has no field 'points'")
        try:
            arr = np.asarray(raw, dtype=np.float64)
        except (TypeError, ValueError):
            raise KeypointFileError(f"{path}: objects.{key}.points is not a list of numbers") from None
        if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) == 0:
            raise KeypointFileError(f"{path}: objects.{key}.points must have shape (k, 3), got {arr.shape}")
        if not np.isfinite(arr).all():
            raise KeypointFileError(f"{path}: objects.{key}.points contains NaN/inf")
        points[oid] = arr
        if isinstance(entry, dict) and "fingerprint" in entry:
            fps[oid] = str(entry["fingerprint"])
    params = doc.get("params") or {}
    if not isinstance(params, dict):
        raise KeypointFileError(f"{path}: field 'params' must be an object, got {type(params).__name__}")
    return KeypointFile(points, doc.get("designator"), params, fps)


def load_keypoints(path: str | os.PathLike) -> dict[int, np.ndarray]:
    """``{obj_id: (k, 3) points}`` (model frame, mm) from a keypoint file."""
    return read_keypoint_file(path).points
