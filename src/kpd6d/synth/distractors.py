"""Distractor occluders: random textured primitive shapes (vertex-coloured trimesh meshes).

A fixed pool is made once per process from the generation seed (so renderers can cache the meshes);
each image picks from it with its own random generator.
"""

from __future__ import annotations

import numpy as np

from kpd6d.synth.palette import random_color

__all__ = ["distractor_pool", "make_distractor"]

_SHAPES = ("box", "sphere", "cylinder", "cone", "capsule", "blob", "torus")


def _base_mesh(rng: np.random.Generator, kind: str):
    import trimesh

    if kind == "box":
        m = trimesh.creation.box(extents=rng.uniform(0.3, 1.0, 3))
    elif kind == "sphere":
        m = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
        m.apply_scale(rng.uniform(0.4, 1.0, 3))
    elif kind == "cylinder":
        m = trimesh.creation.cylinder(radius=rng.uniform(0.1, 0.4), height=rng.uniform(0.3, 1.0), sections=24)
    elif kind == "cone":
        m = trimesh.creation.cone(radius=rng.uniform(0.2, 0.5), height=rng.uniform(0.3, 1.0), sections=24)
    elif kind == "capsule":
        m = trimesh.creation.capsule(height=rng.uniform(0.2, 0.7), radius=rng.uniform(0.1, 0.3), count=[16, 16])
    elif kind == "torus":
        m = trimesh.creation.torus(major_radius=0.35, minor_radius=rng.uniform(0.06, 0.15),
                                   major_sections=24, minor_sections=12)
    else:  # blob: convex hull of random points
        m = trimesh.convex.convex_hull(rng.normal(size=(int(rng.integers(12, 40)), 3)) * rng.uniform(0.3, 1.0, 3))
    # subdivide so that vertex-colour patterns show up as texture
    while len(m.faces) < 600:
        m = m.subdivide()
    return m


def make_distractor(rng: np.random.Generator, diameter: float, palette: str = "uniform"):
    """A random primitive (box, sphere, cylinder, cone, capsule, torus, convex blob) of about
    ``diameter`` mm with a random vertex-colour texture (plain, stripes, checker, or noise) in
    ``palette`` (:mod:`kpd6d.synth.palette`)."""
    import trimesh

    kind = _SHAPES[int(rng.integers(len(_SHAPES)))]
    m = _base_mesh(rng, kind)
    m.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    v = np.asarray(m.vertices)
    m.apply_translation(-(v.min(0) + v.max(0)) / 2)
    ext = float(np.linalg.norm(np.ptp(np.asarray(m.vertices), axis=0)))
    m.apply_scale(diameter / max(ext, 1e-9))
    v = np.asarray(m.vertices) / diameter
    c0, c1 = random_color(rng, palette), random_color(rng, palette)
    pattern = int(rng.integers(4))
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    if pattern == 0:
        s = np.zeros(len(v))
    elif pattern == 1:  # stripes
        s = (np.sin(v @ d * rng.uniform(8, 40)) > 0).astype(np.float64)
    elif pattern == 2:  # 3D checker
        f = rng.uniform(3, 12)
        s = (np.floor(v * f).sum(1) % 2).astype(np.float64)
    else:  # noise
        s = rng.random(len(v))
    col = c0 + s[:, None] * (c1 - c0)
    rgba = np.concatenate([np.clip(col, 0, 255), np.full((len(v), 1), 255.0)], axis=1).astype(np.uint8)
    m.visual = trimesh.visual.ColorVisuals(mesh=m, vertex_colors=rgba)
    return m


def distractor_pool(seed: int, size: int = 24, diameter_range: tuple[float, float] = (40.0, 200.0),
                    palette: str = "uniform", block: int = 0) -> list:
    """``size`` distractor meshes, deterministic for ``(seed, block)``: ``block`` numbers the pools of
    a run that refreshes its distractors (``distractor_refresh``); block 0 is the run's first pool."""
    rng = np.random.default_rng([int(seed), 0xD15] + ([int(block)] if block else []))
    return [make_distractor(rng, float(rng.uniform(*diameter_range)), palette) for _ in range(int(size))]
