"""Distractor occluders: random textured primitive shapes (vertex-coloured trimesh meshes).

A fixed pool is made once per process from the generation seed (so renderers can cache the meshes);
each image picks from it with its own random generator.

With ``object_colors`` a fraction of the pool wears a target object's colours instead of a palette
pattern: the object's colour layout is carried onto the primitive (each primitive vertex takes the
colour of the nearest object vertex, both shapes scaled to the unit cube, the object turned at
random first). Such clutter has exactly the objects' colours and not their shapes, so a detector
cannot tell an object by colour alone. Measured for LM-O (session 21, docs/benchmarks.md): a tie on
synthetic validation, no gain on the real frames, so ``experiment=lmo`` does not use it.
"""

from __future__ import annotations

import numpy as np

from kpd6d.synth.palette import random_color

__all__ = ["color_source", "distractor_pool", "make_distractor", "make_printed_distractor", "transfer_colors"]

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


def color_source(mesh) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (N, 3) scaled into the unit cube, RGB colours (N, 3) float in [0, 255])`` of a
    coloured mesh (vertex, face or texture colours), the input of :func:`transfer_colors`."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    visual = mesh.visual.to_color() if hasattr(mesh.visual, "to_color") else mesh.visual  # textures: sampled
    rgb = np.asarray(visual.vertex_colors, dtype=np.float64)[:, :3]
    if len(rgb) != len(v):
        raise ValueError(f"mesh has {len(v)} vertices but {len(rgb)} vertex colours")
    return _unit_cube(v), rgb


def _unit_cube(p: np.ndarray) -> np.ndarray:
    """Points (N, 3) scaled per axis so that their bounding box is the unit cube."""
    p = np.asarray(p, dtype=np.float64)
    return (p - p.min(0)) / np.maximum(np.ptp(p, axis=0), 1e-9)


def transfer_colors(rng: np.random.Generator, vertices: np.ndarray, source: tuple[np.ndarray, np.ndarray]
                    ) -> np.ndarray:
    """Colours (N, 3) for ``vertices``: those of the nearest ``source`` vertex (:func:`color_source`),
    after turning the source by a random rotation and scaling both point sets into the unit cube."""
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    sv, rgb = source
    sv = _unit_cube((sv - 0.5) @ Rotation.random(random_state=rng).as_matrix().T)
    return rgb[cKDTree(sv).query(_unit_cube(vertices))[1]]


def make_distractor(rng: np.random.Generator, diameter: float, palette: str = "uniform",
                    colors: tuple[np.ndarray, np.ndarray] | None = None):
    """A random primitive (box, sphere, cylinder, cone, capsule, torus, convex blob) of about
    ``diameter`` mm with a random vertex-colour texture (plain, stripes, checker, or noise) in
    ``palette`` (:mod:`kpd6d.synth.palette`), or, given ``colors`` (:func:`color_source`), that
    object's colour layout (:func:`transfer_colors`)."""
    kind = _SHAPES[int(rng.integers(len(_SHAPES)))]
    m = _turned_and_centred(rng, _base_mesh(rng, kind))
    ext = float(np.linalg.norm(np.ptp(np.asarray(m.vertices), axis=0)))
    m.apply_scale(diameter / max(ext, 1e-9))
    v = np.asarray(m.vertices) / diameter
    if colors is not None:
        _set_colors(m, transfer_colors(rng, v, colors))
        return m
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
    _set_colors(m, c0 + s[:, None] * (c1 - c0))
    return m


def make_printed_distractor(rng: np.random.Generator, diameter: float, palette: str = "uniform"):
    """A printed card or box of about ``diameter`` mm (a packaging box, a book, a leaflet) with a
    printed sheet (:func:`kpd6d.synth.prints.printed_sheet`: markers, text, a table or a picture) as
    the texture of every face, centred on the origin in a random orientation."""

    from kpd6d.synth.prints import printed_sheet
    from kpd6d.synth.room import textured_box

    ext = rng.uniform(0.3, 1.0, 3)
    if rng.random() < 0.5:  # a card or leaflet
        ext[int(rng.integers(3))] = rng.uniform(0.005, 0.03)
    ext *= diameter / float(np.linalg.norm(ext))
    side = int(rng.integers(96, 257))
    return _turned_and_centred(rng, textured_box(-ext / 2, ext / 2, printed_sheet(rng, side, side, palette), bottom=True))


def _turned_and_centred(rng: np.random.Generator, m):
    """``m`` turned by a random rotation, its bounding box then centred on the origin (in place)."""
    import trimesh

    m.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    v = np.asarray(m.vertices)
    m.apply_translation(-(v.min(0) + v.max(0)) / 2)
    return m


def _set_colors(m, col: np.ndarray) -> None:
    import trimesh

    rgba = np.concatenate([np.clip(col, 0, 255), np.full((len(col), 1), 255.0)], axis=1).astype(np.uint8)
    m.visual = trimesh.visual.ColorVisuals(mesh=m, vertex_colors=rgba)


def distractor_pool(seed: int, size: int = 24, diameter_range: tuple[float, float] = (40.0, 200.0),
                    palette: str = "uniform", block: int = 0, object_colors: float = 0.0,
                    color_sources: list | None = None, printed: float = 0.0) -> list:
    """``size`` distractor meshes, deterministic for ``(seed, block)``: ``block`` numbers the pools of
    a run that refreshes its distractors (``distractor_refresh``); block 0 is the run's first pool.
    ``object_colors``: the fraction of them (rounded) coloured like one of ``color_sources``
    (:func:`color_source` of the target objects; required when the fraction is > 0); ``printed``: the
    fraction (rounded, of the rest) that are printed cards and boxes (:func:`make_printed_distractor`)."""
    rng = np.random.default_rng([int(seed), 0xD15] + ([int(block)] if block else []))
    n_obj = round(float(object_colors) * int(size))
    if n_obj and not color_sources:
        raise ValueError("distractor_pool: object_colors > 0 needs color_sources (the target objects' colours)")
    n_print = min(round(float(printed) * int(size)), int(size) - n_obj)
    pool = []
    for i in range(int(size)):
        diameter = float(rng.uniform(*diameter_range))
        if n_obj <= i < n_obj + n_print:
            pool.append(make_printed_distractor(rng, diameter, palette))
            continue
        src = color_sources[int(rng.integers(len(color_sources)))] if i < n_obj else None
        pool.append(make_distractor(rng, diameter, palette, colors=src))
    return pool
