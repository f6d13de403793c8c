"""Helpers for the synth / data tests: a tiny BOP models folder made of trimesh primitives."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def write_models(folder: Path) -> Path:
    """obj 1: a box (no symmetry declared), obj 2: a cylinder declared continuously symmetric about z.
    Both vertex-coloured with a gradient so that they are not flat-shaded blobs."""
    import trimesh

    from kpd6d.objects import ObjectModel

    folder.mkdir(parents=True, exist_ok=True)
    info = {}
    box = trimesh.creation.box((60.0, 40.0, 30.0)).subdivide().subdivide()
    cyl = trimesh.creation.cylinder(radius=25.0, height=70.0, sections=32)
    for oid, m in ((1, box), (2, cyl)):
        v = np.asarray(m.vertices)
        rgb = (v - v.min(0)) / np.ptp(v, 0) * 200 + 30
        m.visual = trimesh.visual.ColorVisuals(mesh=m, vertex_colors=np.c_[rgb, np.full(len(v), 255)].astype(np.uint8))
        (folder / f"obj_{oid:06d}.ply").write_bytes(m.export(file_type="ply"))
        info[str(oid)] = ObjectModel(oid, m).info()
    info["2"]["symmetries_continuous"] = [{"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}]
    (folder / "models_info.json").write_text(json.dumps(info))
    return folder


def tree_bytes(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (relative path -> bytes)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


#: small, fast generator settings for tests (160x120, objects close enough to be ~20-60 px)
SMALL = dict(width=160, height=120, distance_range=(180.0, 400.0), designator=None, flush_interval_s=0.0)
