"""Procedural objects: the library's embedded default set of textured models, made in code.

Six vertex-coloured meshes (mm, centred at the origin, diameters 100-250 mm like LineMod objects),
deterministic by ``seed`` (the seed changes the textures; the shapes are fixed):

====  ===========  ==========================================================  ====================
id    name         shape                                                       symmetry
====  ===========  ==========================================================  ====================
1     lblock       L-shaped block with unequal arms (extruded L profile)       none
2     mug          tapered body of revolution with an off-centre torus handle  none
3     wedge        prism over a scalene triangle                               none
4     duck         union of ellipsoids: body, head, beak, tail                 none
5     zblock       extruded Z profile (two offset arms)                        2-fold about z
6     vase         body of revolution, wider at the bottom, ring texture       continuous about z
====  ===========  ==========================================================  ====================

Textures mix high-frequency patterns (3D checker, stripes, coloured blobs, dark "text-like"
strokes) so that SIFT and the KPD find corners. The asymmetric objects get random blobs and
strokes (asymmetric in texture as well as geometry); the 2-fold object's pattern is evaluated on
the orbit representative of each vertex under the 180° turn about z, and the vase's pattern is a
function of (radius, height) only, so their textures are exactly invariant under their symmetries.
Meshes are subdivided to edges of about 2.5 mm so that the vertex colours resolve the patterns.

Single-part objects (1, 3, 5, 6) are watertight. The composites (2, 4) are unions of closed parts
whose faces lying inside another part are removed (no hidden surface for keypoints), so they are
not watertight along the seams.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from kpd6d.objects.model import ObjectModel

__all__ = ["PROCEDURAL_NAMES", "procedural_objects"]

_MAX_EDGE_MM = 2.6
_MAX_FACES = 120_000

# id -> name (ids 1..N, the order of the table above)
PROCEDURAL_NAMES: dict[int, str] = {1: "lblock", 2: "mug", 3: "wedge", 4: "duck", 5: "zblock", 6: "vase"}


def procedural_objects(seed: int = 0, obj_ids: list[int] | None = None) -> list[ObjectModel]:
    """The procedural object set (ids 1..6, see the module docstring), deterministic by ``seed``.

    ``obj_ids`` selects a subset (in the given order); unknown ids raise ``ValueError`` listing the
    known ones. Each call returns fresh copies (callers may modify them).
    """
    ids = sorted(PROCEDURAL_NAMES) if obj_ids is None else [int(i) for i in obj_ids]
    unknown = [i for i in ids if i not in PROCEDURAL_NAMES]
    if unknown:
        known = ", ".join(f"{k} ({v})" for k, v in PROCEDURAL_NAMES.items())
        raise ValueError(f"unknown procedural object id(s) {unknown}; known: {known}")
    out = []
    for i in ids:
        cached = _build_cached(int(seed), i)
        out.append(
            ObjectModel(
                obj_id=cached.obj_id,
                mesh=cached.mesh.copy(),
                name=cached.name,
                symmetries_discrete=[S.copy() for S in cached.symmetries_discrete],
                symmetries_continuous=[{k: list(v) for k, v in s.items()} for s in cached.symmetries_continuous],
                source=cached.source,
                _diameter=cached.diameter,
            )
        )
    return out


@lru_cache(maxsize=64)
def _build_cached(seed: int, obj_id: int) -> ObjectModel:
    name = PROCEDURAL_NAMES[obj_id]
    rng = np.random.default_rng([int(seed), obj_id])
    mesh, sym_d, sym_c, colour_fn = _BUILDERS[name](rng)
    mesh.visual = _vertex_colours(mesh, colour_fn(np.asarray(mesh.vertices)))
    model = ObjectModel(obj_id=obj_id, mesh=mesh, name=name, symmetries_discrete=sym_d,
                        symmetries_continuous=sym_c, source=f"procedural:{name}:seed={seed}")
    _ = model.diameter  # computed once, copied into every returned model
    return model


# ---------------------------------------------------------------------------------------------
# mesh construction helpers
# ---------------------------------------------------------------------------------------------
def _trimesh(vertices, faces):
    import trimesh

    return trimesh.Trimesh(vertices=np.asarray(vertices, float), faces=np.asarray(faces, np.int64), process=True)


def _subdivide(mesh, max_edge: float = _MAX_EDGE_MM):
    """Split every edge longer than ``max_edge`` at its midpoint until none is left.

    A split edge is split in both of its faces, so the mesh stays watertight; faces are
    re-triangulated by how many of their edges were split (1 -> 2, 2 -> 3, 3 -> 4 triangles),
    keeping their orientation.
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    while len(f) < _MAX_FACES:
        e = np.stack([f[:, [1, 2]], f[:, [2, 0]], f[:, [0, 1]]], axis=1)  # edge i is opposite vertex i
        uniq, inv = np.unique(np.sort(e, axis=2).reshape(-1, 2), axis=0, return_inverse=True)
        inv = inv.reshape(-1, 3)
        long_ = np.linalg.norm(v[uniq[:, 0]] - v[uniq[:, 1]], axis=1) > max_edge
        if not long_.any():
            break
        mid = np.full(len(uniq), -1)
        mid[long_] = len(v) + np.arange(int(long_.sum()))
        v = np.concatenate([v, v[uniq[long_]].mean(axis=1)])
        m = mid[inv]  # (F, 3): midpoint on the edge opposite vertex i, or -1
        split = m >= 0
        nsplit = split.sum(axis=1)
        out = [f[nsplit == 0]]
        s3 = nsplit == 3
        a, b, c = f[s3].T
        ma, mb, mc = m[s3].T
        out += [np.c_[a, mc, mb], np.c_[mc, b, ma], np.c_[mb, ma, c], np.c_[ma, mb, mc]]
        for count, pick in ((1, np.argmax), (2, np.argmin)):
            sel = nsplit == count
            k = pick(split[sel], axis=1)  # 1 split: the split edge; 2 splits: the unsplit edge
            order = (k[:, None] + np.arange(3)) % 3
            a, b, c = np.take_along_axis(f[sel], order, axis=1).T
            ma, mb, mc = np.take_along_axis(m[sel], order, axis=1).T
            if count == 1:  # ma on bc
                out += [np.c_[a, b, ma], np.c_[a, ma, c]]
            else:  # mb on ca, mc on ab; the quad mc-b-c-mb is cut along its shorter diagonal
                out.append(np.c_[a, mc, mb])
                short = np.linalg.norm(v[mc] - v[c], axis=1) <= np.linalg.norm(v[b] - v[mb], axis=1)
                out += [np.c_[mc, b, c][short], np.c_[mc, c, mb][short],
                        np.c_[mc, b, mb][~short], np.c_[b, c, mb][~short]]
        f = np.concatenate(out)
    return _trimesh(v, f)


def _triangulate_polygon(poly: np.ndarray) -> np.ndarray:
    """Ear clipping of a simple counter-clockwise polygon (n, 2) -> triangles (n-2, 3) of indices."""
    idx = list(range(len(poly)))
    tris = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    guard = 0
    while len(idx) > 3:
        guard += 1
        if guard > 10_000:
            raise ValueError("polygon triangulation failed (polygon not simple or not counter-clockwise)")
        n = len(idx)
        for j in range(n):
            a, b, c = idx[j - 1], idx[j], idx[(j + 1) % n]
            if cross(poly[a], poly[b], poly[c]) <= 1e-12:
                continue  # reflex vertex
            if any(
                cross(poly[a], poly[b], poly[p]) >= 0 and cross(poly[b], poly[c], poly[p]) >= 0
                and cross(poly[c], poly[a], poly[p]) >= 0
                for p in idx if p not in (a, b, c)
            ):
                continue  # another vertex inside the ear
            tris.append((a, b, c))
            idx.pop(j)
            break
    tris.append(tuple(idx))
    return np.asarray(tris, dtype=np.int64)


def _extrude(poly, z0: float, z1: float):
    """Closed prism over a simple polygon (n, 2) between heights z0 < z1."""
    poly = np.asarray(poly, dtype=float)
    x, y = poly[:, 0], poly[:, 1]
    if 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) < 0:
        poly = poly[::-1]
    n = len(poly)
    v = np.concatenate([np.c_[poly, np.full(n, z0)], np.c_[poly, np.full(n, z1)]])
    tri = _triangulate_polygon(poly)
    faces = [tri[:, ::-1], tri + n]
    i = np.arange(n)
    j = (i + 1) % n
    faces += [np.c_[i, j, j + n], np.c_[i, j + n, i + n]]
    return _trimesh(v, np.concatenate(faces))


def _revolve(profile_rz: np.ndarray, step: float = 2.0):
    """Closed body of revolution about z from an (r, z) profile that starts and ends on the axis."""
    import trimesh

    prof = _densify(np.asarray(profile_rz, dtype=float), step)
    sections = int(np.ceil(2 * np.pi * prof[:, 0].max() / step))
    return trimesh.creation.revolve(prof, sections=sections)


def _densify(poly: np.ndarray, step: float) -> np.ndarray:
    out = [poly[0]]
    for a, b in itertools.pairwise(poly):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out += [a + (b - a) * (k / n) for k in range(1, n + 1)]
    return np.asarray(out)


def _ellipsoid(centre, radii, subdivisions: int = 4):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    m.apply_scale(np.asarray(radii, dtype=float))
    m.apply_translation(np.asarray(centre, dtype=float))
    return m


@dataclass
class _Part:
    mesh: object
    inside: Callable[[np.ndarray], np.ndarray]  # (N, 3) -> bool, strictly inside (with a margin)


def _union_of_parts(parts: list[_Part]):
    """Concatenate closed parts and drop each part's faces that lie inside another part."""
    import trimesh

    kept = []
    for k, part in enumerate(parts):
        m = part.mesh.copy()
        centroids = m.triangles_center
        hidden = np.zeros(len(centroids), dtype=bool)
        for j, other in enumerate(parts):
            if j != k:
                hidden |= other.inside(centroids)
        m.update_faces(~hidden)
        m.remove_unreferenced_vertices()
        kept.append(m)
    return trimesh.util.concatenate(kept)


def _inside_ellipsoid(centre, radii, margin: float = 0.3):
    c, r = np.asarray(centre, float), np.asarray(radii, float) - margin
    return lambda p: (((p - c) / r) ** 2).sum(axis=1) < 1.0


def _inside_revolution(profile_rz, margin: float = 0.3):
    """Inside test for a body of revolution about z whose outer radius is a function of z."""
    prof = np.asarray(profile_rz, float)
    outer = prof[1:-1]  # drop the two on-axis points
    order = np.argsort(outer[:, 1])
    zs, rs = outer[order, 1], outer[order, 0]
    zmin, zmax = prof[:, 1].min(), prof[:, 1].max()

    def inside(p):
        r = np.hypot(p[:, 0], p[:, 1])
        return (p[:, 2] > zmin + margin) & (p[:, 2] < zmax - margin) & (r < np.interp(p[:, 2], zs, rs) - margin)

    return inside


def _centre(mesh):
    lo, hi = mesh.bounds
    mesh.apply_translation(-(lo + hi) / 2.0)
    return mesh


def _vertex_colours(mesh, rgb: np.ndarray):
    import trimesh

    rgba = np.concatenate([np.clip(rgb * 255.0, 0, 255), np.full((len(rgb), 1), 255.0)], axis=1)
    return trimesh.visual.ColorVisuals(mesh, vertex_colors=rgba.astype(np.uint8))


# ---------------------------------------------------------------------------------------------
# textures: functions of vertex positions (N, 3) -> RGB in [0, 1]
# ---------------------------------------------------------------------------------------------
def _random_colour(rng, lo: float = 0.25, hi: float = 1.0) -> np.ndarray:
    return rng.uniform(lo, hi, 3)


def _checker(p, size: float, phase) -> np.ndarray:
    q = np.floor((p + phase) / size).astype(np.int64)
    return (q.sum(axis=1) % 2).astype(bool)


def _stripes(p, direction, period: float) -> np.ndarray:
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    return np.sin(2 * np.pi * (p @ d) / period) > 0.0


def _blobs(p, centres, radii) -> np.ndarray:
    """Index of the blob covering each point (-1: none)."""
    out = np.full(len(p), -1)
    for i, (c, r) in enumerate(zip(centres, radii)):
        out[np.linalg.norm(p - c, axis=1) < r] = i
    return out


def _strokes(p, segments, width: float) -> np.ndarray:
    """Points within ``width / 2`` of any segment ((a, b) pairs): text-like marks."""
    hit = np.zeros(len(p), dtype=bool)
    for a, b in segments:
        ab = b - a
        s = np.clip(((p - a) @ ab) / max(ab @ ab, 1e-9), 0.0, 1.0)
        hit |= np.linalg.norm(p - (a + s[:, None] * ab), axis=1) < width / 2
    return hit


def _text_marks(rng, anchors: np.ndarray, n_words: int, scale: float) -> list:
    """Groups of short strokes around random surface anchors, like letters of a label."""
    segs = []
    for _ in range(n_words):
        c = anchors[rng.integers(len(anchors))]
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        v = np.cross(u, rng.normal(size=3))
        v /= np.linalg.norm(v)
        for k in range(int(rng.integers(3, 6))):  # letters along u
            base = c + u * (k * 0.9 * scale)
            for _ in range(int(rng.integers(1, 3))):  # strokes per letter
                a = base + (rng.uniform(-0.4, 0.4) * u + rng.uniform(-0.6, 0.6) * v) * scale
                b = base + (rng.uniform(-0.4, 0.4) * u + rng.uniform(-0.6, 0.6) * v) * scale
                segs.append((a, b))
    return segs


def _asymmetric_texture(rng, surface_pts: np.ndarray, *, checker: float, stripes: float,
                        n_blobs: int, n_words: int) -> Callable[[np.ndarray], np.ndarray]:
    """A random mix of checker, stripes, blobs and strokes (no symmetry)."""
    c0, c1, c2 = _random_colour(rng), _random_colour(rng, 0.0, 0.7), _random_colour(rng)
    phase = rng.uniform(0, checker, 3)
    sdir = rng.normal(size=3)
    centres = surface_pts[rng.integers(len(surface_pts), size=n_blobs)]
    radii = rng.uniform(5.0, 14.0, n_blobs)
    blob_cols = rng.uniform(0.0, 1.0, (n_blobs, 3))
    segs = _text_marks(rng, surface_pts, n_words, scale=rng.uniform(9.0, 14.0))
    ink = _random_colour(rng, 0.0, 0.2)

    def colour(p):
        rgb = np.where(_checker(p, checker, phase)[:, None], c0, c1)
        rgb = np.where(_stripes(p, sdir, stripes)[:, None] & (p[:, 2] > 0)[:, None], 0.5 * rgb + 0.5 * c2, rgb)
        b = _blobs(p, centres, radii)
        rgb[b >= 0] = blob_cols[b[b >= 0]]
        rgb[_strokes(p, segs, 3.2)] = ink
        return rgb

    return colour


# ---------------------------------------------------------------------------------------------
# the objects: each builder returns (mesh, symmetries_discrete, symmetries_continuous, colour_fn)
# ---------------------------------------------------------------------------------------------
def _surface_pts(mesh, n=2000, seed=0):
    import trimesh

    return trimesh.sample.sample_surface(mesh, n, seed=seed)[0]


def _build_lblock(rng):
    # unequal arms and widths: no 2-fold turn about the L's diagonal
    poly = np.array([[0, 0], [130, 0], [130, 42], [55, 42], [55, 95], [0, 95]], float)
    mesh = _centre(_subdivide(_extrude(poly, 0.0, 48.0)))
    tex = _asymmetric_texture(rng, _surface_pts(mesh), checker=16.0, stripes=11.0, n_blobs=14, n_words=6)
    return mesh, [], [], tex


def _build_mug(rng):
    body_prof = np.array([[0, -55], [38, -55], [46, 50], [0, 50]], float)  # tapered: wider at the top
    body = _revolve(body_prof)
    handle = _torus_part(major=28.0, minor=7.5, centre=(44.0, 0.0, 8.0))
    mesh = _union_of_parts([_Part(body, _inside_revolution(body_prof)), handle])
    mesh = _centre(mesh)
    tex = _asymmetric_texture(rng, _surface_pts(mesh), checker=13.0, stripes=9.0, n_blobs=12, n_words=8)
    return mesh, [], [], tex


def _torus_part(major: float, minor: float, centre, margin: float = 0.3) -> _Part:
    """A torus in the x-z plane (its hole axis along y) centred at ``centre``."""
    import trimesh

    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # torus axis z -> y
    T[:3, 3] = centre
    m = trimesh.creation.torus(major, minor, major_sections=int(2 * np.pi * major / 2.2),
                               minor_sections=int(2 * np.pi * minor / 2.0), transform=T)
    c = np.asarray(centre, float)

    def inside(p):
        q = p - c
        rho = np.hypot(q[:, 0], q[:, 2])
        return (rho - major) ** 2 + q[:, 1] ** 2 < (minor - margin) ** 2

    return _Part(m, inside)


def _build_wedge(rng):
    poly = np.array([[0, 0], [150, 0], [38, 82]], float)  # scalene
    mesh = _centre(_subdivide(_extrude(poly, 0.0, 60.0)))
    tex = _asymmetric_texture(rng, _surface_pts(mesh), checker=14.0, stripes=8.0, n_blobs=14, n_words=6)
    return mesh, [], [], tex


def _build_duck(rng):
    specs = [  # (centre, radii, subdivisions)
        ((0.0, 0.0, 0.0), (68.0, 44.0, 38.0), 5),  # body
        ((52.0, 0.0, 48.0), (27.0, 26.0, 27.0), 4),  # head
        ((82.0, 0.0, 42.0), (20.0, 11.0, 5.5), 4),  # beak
        ((-64.0, 0.0, 22.0), (20.0, 13.0, 9.0), 4),  # tail
    ]
    parts = [_Part(_ellipsoid(c, r, s), _inside_ellipsoid(c, r)) for c, r, s in specs]
    mesh = _centre(_union_of_parts(parts))
    tex = _asymmetric_texture(rng, _surface_pts(mesh), checker=12.0, stripes=10.0, n_blobs=16, n_words=6)
    return mesh, [], [], tex


def _build_zblock(rng):
    # Z profile: invariant under (x, y) -> (-x, -y) only
    poly = np.array([[-75, -45], [15, -45], [15, -10], [75, -10], [75, 45], [-15, 45], [-15, 10], [-75, 10]], float)
    mesh = _subdivide(_extrude(poly, -26.0, 26.0))
    Rz = np.diag([-1.0, -1.0, 1.0, 1.0])
    base = _asymmetric_texture(rng, _surface_pts(mesh), checker=15.0, stripes=10.0, n_blobs=10, n_words=5)

    def tex(p):
        flip = (p[:, 0] < 0) | ((p[:, 0] == 0) & (p[:, 1] < 0))
        q = p.copy()
        q[flip, :2] *= -1.0  # orbit representative under the 180° turn about z
        return base(q)

    return mesh, [Rz], [], tex


def _build_vase(rng):
    z = np.linspace(-80.0, 80.0, 33)
    r = 45.0 - 14.0 * (z + 80.0) / 160.0 + 9.0 * np.sin((z + 80.0) / 160.0 * 2.6 * np.pi)  # bottom-heavy
    r[-1] = 24.0  # lip
    prof = np.concatenate([[[0.0, -80.0]], np.c_[r, z], [[0.0, 80.0]]])
    mesh = _revolve(prof)
    # rings: bands of random colours and widths along z, plus radial bands on the flat ends
    edges = np.cumsum(rng.uniform(3.0, 11.0, 80)) - 85.0
    cols = rng.uniform(0.0, 1.0, (len(edges) + 1, 3))
    redges = np.cumsum(rng.uniform(3.0, 8.0, 20))
    rcols = rng.uniform(0.0, 1.0, (len(redges) + 1, 3))

    def tex(p):
        rr = np.hypot(p[:, 0], p[:, 1])
        rgb = cols[np.searchsorted(edges, p[:, 2])]
        flat = (np.abs(p[:, 2]) > 79.9)
        rgb[flat] = rcols[np.searchsorted(redges, rr[flat])]
        return rgb

    return mesh, [], [{"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}], tex


_BUILDERS = {
    "lblock": _build_lblock,
    "mug": _build_mug,
    "wedge": _build_wedge,
    "duck": _build_duck,
    "zblock": _build_zblock,
    "vase": _build_vase,
}
