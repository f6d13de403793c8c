"""Object models: a mesh in millimetres with its BOP metadata (id, diameter, box, symmetries)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["MIN_DIAMETER_MM", "ModelError", "ObjectModel", "load_bop_models", "load_models_info"]

_UNIT_SCALE = {"mm": 1.0, "cm": 10.0, "m": 1000.0}

#: A mesh loaded with the default units (millimetres, not stated) whose size (bounding-box
#: diagonal, or its models_info diameter) is below this is an error: it looks like a file in metres.
#: Pose-estimation objects are 20-500 mm (LineMod 100-300 mm), so in metres they measure 0.02-0.5;
#: every object up to 2 m stored in metres is caught, and a real object below 2 mm is not a
#: plausible target. A genuinely tiny object passes when the caller states ``units="mm"``.
MIN_DIAMETER_MM = 2.0

#: A face counts as degenerate when its area is below this fraction of the squared box diagonal.
_DEGENERATE_AREA_RTOL = 1e-12


def _units_message(where: str, size: float) -> str:
    return (f"{where}: the object measures {size:.4g} (mm assumed), implausible for millimetres (< {MIN_DIAMETER_MM:g} mm): "
            f"looks like metres; pass units='m' (or scale the file); a genuinely tiny object: pass units='mm'")


class ModelError(ValueError):
    """A mesh or models_info file that cannot be used; the message names the file and the problem."""


@dataclass
class ObjectModel:
    """A textured / vertex-coloured mesh in millimetres (model frame) and its metadata.

    ``mesh`` is the trimesh object (with its visual: vertex colours or a texture), already scaled
    to mm. ``symmetries_discrete`` holds 4x4 matrices (translation in mm) and
    ``symmetries_continuous`` holds dicts ``{"axis": [x, y, z], "offset": [x, y, z]}`` as in BOP's
    models_info.json.
    """

    obj_id: int
    mesh: Any  # trimesh.Trimesh
    name: str = ""
    symmetries_discrete: list[np.ndarray] = field(default_factory=list)
    symmetries_continuous: list[dict] = field(default_factory=list)
    source: str | None = None
    _diameter: float | None = field(default=None, repr=False)

    # -- geometry ---------------------------------------------------------------------------
    @property
    def vertices(self) -> np.ndarray:
        return np.asarray(self.mesh.vertices, dtype=np.float64)

    @property
    def faces(self) -> np.ndarray:
        return np.asarray(self.mesh.faces, dtype=np.int64)

    @property
    def bbox_min(self) -> np.ndarray:
        return self.vertices.min(axis=0)

    @property
    def bbox_size(self) -> np.ndarray:
        return self.vertices.max(axis=0) - self.bbox_min

    @property
    def bbox_corners(self) -> np.ndarray:
        """The 8 corners (8, 3) of the tight axis-aligned box (model frame), x fastest."""
        lo, hi = self.bbox_min, self.bbox_min + self.bbox_size
        return np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])

    @property
    def diameter(self) -> float:
        """Largest distance between two vertices (mm), as BOP defines it (from models_info when known)."""
        if self._diameter is None:
            self._diameter = _diameter(self.vertices)
        return self._diameter

    @diameter.setter
    def diameter(self, value: float) -> None:
        self._diameter = float(value)

    @property
    def is_symmetric(self) -> bool:
        return bool(self.symmetries_discrete or self.symmetries_continuous)

    def info(self) -> dict:
        """This model's entry in BOP models_info.json form."""
        lo, size = self.bbox_min, self.bbox_size
        d: dict[str, Any] = {
            "diameter": float(self.diameter),
            "min_x": float(lo[0]), "min_y": float(lo[1]), "min_z": float(lo[2]),
            "size_x": float(size[0]), "size_y": float(size[1]), "size_z": float(size[2]),
        }
        if self.symmetries_discrete:
            d["symmetries_discrete"] = [np.asarray(S, dtype=float).reshape(-1).tolist() for S in self.symmetries_discrete]
        if self.symmetries_continuous:
            d["symmetries_continuous"] = [
                {"axis": [float(v) for v in s["axis"]], "offset": [float(v) for v in s.get("offset", [0, 0, 0])]}
                for s in self.symmetries_continuous
            ]
        return d

    def sample_points(self, n: int = 1000, seed: int = 0) -> np.ndarray:
        """``n`` points sampled uniformly on the surface (deterministic by seed)."""
        import trimesh

        pts, _ = trimesh.sample.sample_surface_even(self.mesh, n, seed=seed)
        if len(pts) < n:  # sample_surface_even may return fewer; top up uniformly
            extra, _ = trimesh.sample.sample_surface(self.mesh, n - len(pts), seed=seed + 1)
            pts = np.concatenate([pts, extra])
        return np.asarray(pts, dtype=np.float64)

    # -- I/O ----------------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | os.PathLike, units: str | None = None, obj_id: int | None = None,
             info: dict | None = None) -> ObjectModel:
        """Load a PLY / OBJ / GLB mesh through trimesh, keeping vertex colours or textures.

        ``units`` is the unit the file is stored in ("mm", "cm" or "m"); vertices are scaled to mm.
        None (the default) means millimetres, checked: a mesh (or models_info diameter) below
        :data:`MIN_DIAMETER_MM` raises :class:`ModelError` ("looks like metres"); an explicit
        ``units="mm"`` skips that check (tiny objects). Meshes whose faces are all (or nearly all)
        of zero area raise :class:`ModelError` too.
        ``obj_id`` defaults to the trailing number of the file name (BOP's ``obj_000005.ply`` -> 5).
        ``info`` is this object's models_info.json entry (diameter and symmetries are taken from it).
        """
        import trimesh

        path = Path(path)
        checked = units is None
        units = "mm" if units is None else units
        if units not in _UNIT_SCALE:
            raise ModelError(f"{path}: unknown units {units!r}; use one of {sorted(_UNIT_SCALE)}")
        if not path.exists():
            raise ModelError(f"{path}: mesh file does not exist")
        if path.is_dir():
            raise ModelError(f"{path}: is a directory, not a mesh file")
        if path.stat().st_size == 0:
            raise ModelError(f"{path}: mesh file is empty (0 bytes)")
        try:
            loaded = trimesh.load(path, process=False)
        except Exception as exc:
            raise ModelError(f"{path}: cannot be read as a mesh ({type(exc).__name__}: {exc})") from exc
        if isinstance(loaded, trimesh.Scene):
            geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)] if loaded.geometry else []
            if not geoms:
                raise ModelError(f"{path}: file holds no triangle mesh (empty scene)")
            loaded = geoms[0] if len(geoms) == 1 else trimesh.util.concatenate(geoms)
        if not isinstance(loaded, trimesh.Trimesh):
            raise ModelError(f"{path}: file holds a {type(loaded).__name__}, not a triangle mesh")
        if len(loaded.vertices) == 0 or len(loaded.faces) == 0:
            raise ModelError(
                f"{path}: mesh has {len(loaded.vertices)} vertices and {len(loaded.faces)} faces; need a non-empty triangle mesh"
            )
        if not np.isfinite(np.asarray(loaded.vertices)).all():
            raise ModelError(f"{path}: mesh has non-finite (NaN/inf) vertex coordinates")
        _check_faces(path, loaded)
        scale = _UNIT_SCALE[units]
        if scale != 1.0:
            loaded.apply_scale(scale)
        if checked:
            size = float(np.linalg.norm(np.ptp(np.asarray(loaded.vertices, dtype=np.float64), axis=0)))
            if size < MIN_DIAMETER_MM:
                raise ModelError(_units_message(str(path), size))
            if info and "diameter" in info and float(info["diameter"]) < MIN_DIAMETER_MM:
                raise ModelError(_units_message(f"{path}: models_info diameter {float(info['diameter']):.4g}",
                                                float(info["diameter"])))
        if obj_id is None:
            digits = "".join(ch for ch in path.stem.split("_")[-1] if ch.isdigit())
            obj_id = int(digits) if digits else 0
        model = cls(obj_id=int(obj_id), mesh=loaded, name=path.stem, source=str(path))
        if info:
            model.apply_info(info)
        return model

    def apply_info(self, info: dict) -> None:
        """Take diameter and symmetries from a models_info.json entry."""
        if "diameter" in info:
            self.diameter = float(info["diameter"])
        self.symmetries_discrete = [np.asarray(s, dtype=np.float64).reshape(4, 4) for s in info.get("symmetries_discrete", [])]
        self.symmetries_continuous = [
            {"axis": list(map(float, s["axis"])), "offset": list(map(float, s.get("offset", [0, 0, 0])))}
            for s in info.get("symmetries_continuous", [])
        ]


def _check_faces(path: Path, mesh) -> None:
    """A mesh must have faces of non-zero area (a mesh of zero-area faces designates identical keypoints)."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise ModelError(f"{path}: faces refer to vertex {int(f.max()) if f.max() >= len(v) else int(f.min())}; "
                         f"the mesh has {len(v)} vertices")
    diag2 = float(np.sum(np.ptp(v, axis=0) ** 2))
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    good = int(np.sum(area > _DEGENERATE_AREA_RTOL * diag2)) if diag2 > 0 else 0
    if good < 4 or good < 0.01 * len(f):
        raise ModelError(f"{path}: degenerate mesh: {len(f) - good} of {len(f)} faces have zero area "
                         f"({good} usable; need >= 4 and >= 1 %); the file is broken or its vertices collapsed")


def _diameter(v: np.ndarray) -> float:
    """Exact max pairwise distance over the convex hull's vertices (falls back to all vertices)."""
    pts = v
    try:
        from scipy.spatial import ConvexHull

        if len(v) > 4:
            pts = v[ConvexHull(v).vertices]
    except Exception:  # degenerate (flat) point sets: use all of them
        pts = v
    from scipy.spatial.distance import cdist

    best = 0.0
    for i in range(0, len(pts), 2048):  # chunked to bound memory
        best = max(best, float(cdist(pts[i : i + 2048], pts, "sqeuclidean").max()))
    return best ** 0.5


def load_models_info(path: str | os.PathLike) -> dict[int, dict]:
    """Read BOP ``models_info.json`` into ``{obj_id: entry}``; errors name the file and field."""
    from kpd6d.io import read_json

    path = Path(path)
    raw = read_json(path, what="models_info.json", error=ModelError)
    if not isinstance(raw, dict):
        raise ModelError(f"{path}: expected an object mapping object ids to entries, got {type(raw).__name__}")
    out: dict[int, dict] = {}
    for key, entry in raw.items():
        try:
            oid = int(key)
        except ValueError:
            raise ModelError(f"{path}: object id {key!r} is not an integer") from None
        if not isinstance(entry, dict) or "diameter" not in entry:
            raise ModelError(f"{path}: entry {key!r} has no 'diameter' field")
        d = entry["diameter"]
        if isinstance(d, bool) or not isinstance(d, (int, float)):
            raise ModelError(f"{path}: object {key} field 'diameter' = {d!r} is not a number")
        if not (np.isfinite(d) and d > 0):
            raise ModelError(f"{path}: object {key} field 'diameter' = {d!r}; must be a finite number > 0 (mm)")
        for j, s in enumerate(entry.get("symmetries_discrete", [])):
            if len(s) != 16:
                raise ModelError(f"{path}: object {key} symmetries_discrete[{j}] has {len(s)} values, expected 16")
        for j, s in enumerate(entry.get("symmetries_continuous", [])):
            if "axis" not in s or len(s["axis"]) != 3:
                raise ModelError(f"{path}: object {key} symmetries_continuous[{j}] needs a 3-vector 'axis'")
        out[oid] = entry
    return out


def load_bop_models(models_dir: str | os.PathLike, obj_ids: list[int] | None = None,
                    units: str | None = None) -> list[ObjectModel]:
    """Load ``obj_XXXXXX.ply`` meshes of a BOP models folder with their models_info.json entries.

    ``units`` as in :meth:`ObjectModel.load` (None: millimetres, checked for plausibility)."""
    models_dir = Path(models_dir)
    info = load_models_info(models_dir / "models_info.json")
    ids = sorted(info) if obj_ids is None else list(obj_ids)
    missing = [i for i in ids if i not in info]
    if missing:
        raise ModelError(f"{models_dir / 'models_info.json'}: no entry for object id(s) {missing}; known: {sorted(info)}")
    if units is None:
        small = [(i, float(info[i]["diameter"])) for i in ids if float(info[i]["diameter"]) < MIN_DIAMETER_MM]
        if small:
            raise ModelError(_units_message(f"{models_dir / 'models_info.json'}: object {small[0][0]} diameter "
                                            f"{small[0][1]:.4g}", small[0][1]))
    return [ObjectModel.load(models_dir / f"obj_{i:06d}.ply", units=units, obj_id=i, info=info[i]) for i in ids]
