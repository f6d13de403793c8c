"""Table-top scenes (``layout: tabletop``): objects resting on a textured table, seen from above.

Frames. The *table frame* has the table top in its plane z = 0, +z up, and its origin at the point
the camera looks at. The camera is sampled in that frame (:func:`table_camera`): elevation above the
table plane, azimuth about the table normal, distance to the look-at point, roll about the optical
axis; it gives ``(R_w2c, t_w2c)`` with ``x_c = R_w2c x_w + t_w2c`` (OpenCV axes). An object resting
on the table has a pose ``(R_mw, t_mw)`` in the table frame; its ground truth is, as in the free
layout, the camera-frame pose ``R = R_w2c R_mw``, ``t = R_w2c t_mw + t_w2c``.

Resting poses (:func:`stable_poses`) come from the mesh alone: the faces of the convex hull on which
the object can rest (the centre of mass projects inside the face) and the quasi-static probability
of landing on each (solid angle of the hull faces seen from the centre of mass, toppled over the
edges towards the face the centre of mass projects onto; the method of trimesh's
``compute_stable_poses`` / Goldberg et al., done here on scipy's hull). A resting rotation maps the
face's outward normal to -z; after a random rotation about +z the model is translated so that its
lowest hull vertex lies exactly at z = 0.

Footprints. With the rotation fixed, an object lies in the vertical cylinder over a circle in the
table plane (centred under its bounding-box centre, the largest horizontal distance of a hull vertex
as radius). Objects whose circles are disjoint cannot interpenetrate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Footprint", "RestingPoses", "TableScene", "center_of_mass", "footprint", "make_table_mesh", "resting_rotation",
           "shadow_pose", "stable_poses", "table_camera"]


# ---------------------------------------------------------------------------------------------
# resting poses
# ---------------------------------------------------------------------------------------------
def _solid_centroid(points: np.ndarray, simplices: np.ndarray) -> np.ndarray:
    """Centroid of the solid convex polytope with boundary triangles ``points[simplices]``."""
    apex = points.mean(axis=0)
    tri = points[simplices]
    vol = np.abs(np.einsum("ij,ij->i", tri[:, 0] - apex, np.cross(tri[:, 1] - apex, tri[:, 2] - apex))) / 6.0
    cent = (tri.sum(axis=1) + apex) / 4.0
    return (vol[:, None] * cent).sum(axis=0) / max(float(vol.sum()), 1e-300)


def center_of_mass(mesh, hull_points: np.ndarray | None = None) -> np.ndarray:
    """Centre of mass of ``mesh`` (a trimesh) as a uniform solid when it is a closed volume, else that
    of its convex hull (scanned models are often not watertight)."""
    try:
        if mesh is not None and mesh.is_volume:
            return np.asarray(mesh.center_mass, dtype=np.float64)
    except Exception:  # pragma: no cover - trimesh could not decide: use the hull
        pass
    pts = np.asarray(hull_points if hull_points is not None else mesh.vertices, dtype=np.float64)
    from scipy.spatial import ConvexHull, QhullError

    try:
        return _solid_centroid(pts, ConvexHull(pts).simplices)
    except (QhullError, ValueError):  # flat or degenerate: no volume
        return pts.mean(axis=0)


def resting_rotation(normal: np.ndarray) -> np.ndarray:
    """A rotation taking the (outward) face normal ``normal`` to -z (the face then lies on the table)."""
    z = -np.asarray(normal, dtype=np.float64)
    z = z / np.linalg.norm(z)
    a = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(a, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])  # rows: R @ normal = (0, 0, -1)


def _solid_angles(tri: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Solid angle of each triangle (T, 3, 3) seen from ``c`` (Van Oosterom & Strackee)."""
    a, b, d = tri[:, 0] - c, tri[:, 1] - c, tri[:, 2] - c
    la, lb, ld = (np.linalg.norm(v, axis=1) for v in (a, b, d))
    num = np.abs(np.einsum("ij,ij->i", a, np.cross(b, d)))
    den = la * lb * ld + np.einsum("ij,ij->i", a, b) * ld + np.einsum("ij,ij->i", a, d) * lb \
        + np.einsum("ij,ij->i", b, d) * la
    return 2.0 * np.arctan2(num, den)


def _barycentric(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (T, 3) of points ``p`` (T, 3) in the planes of triangles ``tri``."""
    v0, v1, v2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], p - tri[:, 0]
    d00, d01, d11 = (np.einsum("ij,ij->i", x, y) for x, y in ((v0, v0), (v0, v1), (v1, v1)))
    d20, d21 = np.einsum("ij,ij->i", v2, v0), np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    ok = den > 1e-12 * np.maximum(d00 * d11, 1e-300)
    den = np.where(ok, den, 1.0)
    v = np.where(ok, (d11 * d20 - d01 * d21) / den, -1.0)
    w = np.where(ok, (d00 * d21 - d01 * d20) / den, -1.0)
    return np.stack([1.0 - v - w, v, w], axis=1)


def _flat_poses(points: np.ndarray, com: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A flat (or degenerate) model lies on either side of its plane."""
    _, _, vt = np.linalg.svd(points - com, full_matrices=False)
    n = vt[-1]
    return np.stack([resting_rotation(n), resting_rotation(-n)]), np.array([0.5, 0.5])


def stable_poses(points: np.ndarray, com: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Resting rotations (P, 3, 3) of a rigid body with vertices ``points`` and centre of mass ``com``
    on a horizontal plane, and their probabilities (P,) (sum 1, most probable first).

    Each rotation maps the outward normal of a stable hull face to -z. A face is stable when the
    centre of mass projects inside it; the probability of a face is the solid angle (from the centre
    of mass) of the hull triangles whose quasi-static toppling ends on it.
    """
    from scipy.spatial import ConvexHull, QhullError

    pts = np.asarray(points, dtype=np.float64)
    try:
        hull = ConvexHull(pts)
    except (QhullError, ValueError):
        c = pts.mean(axis=0) if com is None else np.asarray(com, dtype=np.float64)
        return _flat_poses(pts, c)
    c = _solid_centroid(pts, hull.simplices) if com is None else np.asarray(com, dtype=np.float64)
    tri = pts[hull.simplices]
    normals = hull.equations[:, :3]
    dist = np.einsum("ij,ij->i", c - tri[:, 0], normals)  # < 0: c inside
    if not np.all(dist < 0):  # centre of mass not strictly inside (degenerate input): use the hull's
        c = _solid_centroid(pts, hull.simplices)
        dist = np.einsum("ij,ij->i", c - tri[:, 0], normals)
    prob = _solid_angles(tri, c)
    prob = prob / prob.sum()
    foot = c - dist[:, None] * normals
    bary = _barycentric(tri, foot)
    stable = np.all(bary >= -1e-9, axis=1)
    if not stable.any():  # the face nearest the centre of mass is always stable (numerical fallback)
        stable[int(np.argmax(dist))] = True
    # unstable triangle -> the neighbour across the edge that the line from its centroid to the foot
    # of the centre of mass leaves it through (scipy: neighbour k is opposite vertex k)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(bary < 0, (1.0 / 3.0) / (1.0 / 3.0 - bary), np.inf)
    s = np.nan_to_num(s, nan=np.inf)
    succ = hull.neighbors[np.arange(len(tri)), np.argmin(s, axis=1)]
    # follow each triangle's toppling chain to its resting triangle (memoised; cycles lose their mass)
    end = np.full(len(tri), -2, dtype=np.int64)  # -2: unknown, -1: no resting face
    end[stable] = np.nonzero(stable)[0]
    for i in range(len(tri)):
        path, j = [], i
        while end[j] == -2 and j not in path:
            path.append(j)
            j = int(succ[j])
            if j < 0:
                break
        e = end[j] if j >= 0 and end[j] != -2 else -1
        end[path] = e
    mass = np.zeros(len(tri))
    np.add.at(mass, end[end >= 0], prob[end >= 0])
    # merge coplanar resting triangles (same outward normal) into faces
    rest = np.nonzero(mass > 0)[0]
    if len(rest) == 0:  # pragma: no cover - every chain cycled
        rest = np.array([int(np.argmax(dist))])
        mass[rest] = 1.0
    n_rest = normals[rest]
    if len(rest) <= 4096:  # label: the first resting triangle with the same normal
        label = (n_rest @ n_rest.T > 1.0 - 1e-9).argmax(axis=1)
    else:  # pragma: no cover - huge hulls: group by rounded normals
        label = np.unique(np.round(n_rest, 6), axis=0, return_inverse=True)[1].reshape(-1)
    _, first, inverse = np.unique(label, return_index=True, return_inverse=True)
    p = np.zeros(len(first))
    np.add.at(p, inverse.reshape(-1), mass[rest])
    faces_n = n_rest[first]
    order = np.argsort(-p, kind="stable")
    rots = np.stack([resting_rotation(faces_n[i]) for i in order])
    return rots, p[order] / p.sum()


@dataclass
class RestingPoses:
    """Per model, computed once: hull vertices, bounding-box centre, resting rotations and probabilities."""

    hull: np.ndarray  # (N, 3) model-frame hull vertices
    center: np.ndarray  # (3,) bounding-box centre (footprint circles are centred under it)
    radius: float  # bounding-sphere radius about ``center``: bounds every footprint radius
    rotations: np.ndarray  # (P, 3, 3)
    probs: np.ndarray  # (P,)
    _cum: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._cum = np.cumsum(self.probs)
        self._cum[-1] = 1.0

    @classmethod
    def from_geometry(cls, geom, mesh=None) -> RestingPoses:
        """From a :class:`~kpd6d.synth.poses.ModelGeometry` (hull, centre, radius) and its mesh."""
        com = center_of_mass(mesh, geom.hull)
        rots, probs = stable_poses(geom.hull, com)
        return cls(np.asarray(geom.hull, dtype=np.float64), np.asarray(geom.center, dtype=np.float64),
                   float(geom.radius), rots, probs)

    def sample(self, rng: np.random.Generator, upright_prob: float = 0.0) -> np.ndarray:
        """A resting rotation (drawn by probability) followed by a random rotation about +z. With
        probability ``upright_prob`` the object stands as its model frame says instead (model +z along
        the table normal: BOP / LineMod models are modelled standing upright), then turned about +z."""
        if upright_prob > 0 and rng.random() < upright_prob:
            base = np.eye(3)
        else:
            base = self.rotations[min(int(np.searchsorted(self._cum, rng.random(), side="right")), len(self.probs) - 1)]
        a = rng.uniform(0.0, 2.0 * math.pi)
        ca, sa = math.cos(a), math.sin(a)
        Rz = np.array([[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]])
        return Rz @ base


@dataclass
class Footprint:
    """Where a resting object stands on the table (table frame, mm): the convex hull of its vertices
    projected onto the plane (``polygon``, counter-clockwise) and a circle around it."""

    polygon: np.ndarray  # (M, 2)
    center: np.ndarray  # (2,)
    radius: float

    def moved(self, d: np.ndarray) -> Footprint:
        return Footprint(self.polygon + d, self.center + d, self.radius)

    def overlaps(self, other: Footprint, gap: float = 0.0) -> bool:
        """Whether the footprints come closer than ``gap`` (circles first, then separating axes)."""
        if np.hypot(*(self.center - other.center)) >= self.radius + other.radius + gap:
            return False
        for poly in (self.polygon, other.polygon):
            e = np.roll(poly, -1, axis=0) - poly
            n = np.stack([e[:, 1], -e[:, 0]], axis=1)
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            a, b = self.polygon @ n.T, other.polygon @ n.T  # (M, axes) projections
            if np.any(a.max(0) + gap <= b.min(0)) or np.any(b.max(0) + gap <= a.min(0)):
                return False
        return True


def footprint(poses: RestingPoses, R_mw: np.ndarray) -> tuple[Footprint, float]:
    """The footprint of the model rotated by ``R_mw`` (table frame) with its origin above the table
    origin (the circle is centred under the bounding-box centre; its radius is at most
    ``poses.radius``), and the height of the lowest hull vertex."""
    q = poses.hull @ R_mw.T
    xy = q[:, :2]
    c = (R_mw @ poses.center)[:2]
    r = float(np.linalg.norm(xy - c, axis=1).max())
    try:
        from scipy.spatial import ConvexHull

        poly = xy[ConvexHull(xy).vertices]  # counter-clockwise
    except Exception:  # a degenerate footprint (a rod standing up, a sheet on edge): its bounding box
        lo, hi = xy.min(0), xy.max(0)
        poly = np.array([lo, [hi[0], lo[1]], hi, [lo[0], hi[1]]])
    return Footprint(poly, c, r), float(q[:, 2].min())


# ---------------------------------------------------------------------------------------------
# camera and table
# ---------------------------------------------------------------------------------------------
def table_camera(elevation: float, azimuth: float, distance: float, roll: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(R_w2c, t_w2c)`` of a camera looking at the table-frame origin (angles in radians).

    The camera centre is at ``distance`` from the origin, ``elevation`` above the plane z = 0, at
    ``azimuth`` about +z; image x is horizontal and the table normal points up in the image before
    the ``roll`` about the optical axis.
    """
    ce, se, ca, sa = math.cos(elevation), math.sin(elevation), math.cos(azimuth), math.sin(azimuth)
    centre = distance * np.array([ce * ca, ce * sa, se])
    z = -centre / distance
    x = np.array([-sa, ca, 0.0])  # = normalised z x up, also well defined at elevation 90 deg
    y = np.cross(z, x)
    cr, sr = math.cos(roll), math.sin(roll)
    R = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]]) @ np.stack([x, y, z])
    return R, -R @ centre


def make_table_mesh(image: np.ndarray, x0: float, x1: float, y0: float, y1: float):
    """The table top: the rectangle [x0, x1] x [y0, y1] of the plane z = 0 (normal +z), two triangles
    textured with ``image`` (RGB uint8), matte like the vertex-coloured models."""
    import trimesh
    from PIL import Image

    v = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    mesh = trimesh.Trimesh(vertices=v, faces=np.array([[0, 1, 2], [0, 2, 3]]), process=False)
    material = trimesh.visual.material.PBRMaterial(baseColorTexture=Image.fromarray(np.ascontiguousarray(image)),
                                                   metallicFactor=0.2, roughnessFactor=0.8)
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv, material=material)
    return mesh


@dataclass
class TableScene:
    """The table of one image and, once an attempt is made, the camera: ``x_c = R_w2c x_w + t_w2c``."""

    mesh: object  # trimesh of the table top (table frame)
    extent: tuple[float, float, float, float]  # x0, x1, y0, y1 (mm, table frame)
    R_w2c: np.ndarray | None = None
    t_w2c: np.ndarray | None = None
    elevation_deg: float | None = None
    distance: float | None = None
    room: tuple = ()  # meshes of the room around the table (table frame; :mod:`kpd6d.synth.room`), drawn in colour only

    def world_to_camera(self, R_mw: np.ndarray, t_mw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.R_w2c @ R_mw, self.R_w2c @ t_mw + self.t_w2c

    def camera_to_world(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.R_w2c.T @ R, self.R_w2c.T @ (t - self.t_w2c)

    def holds(self, foot: Footprint) -> bool:
        """Whether ``foot`` lies on the table top."""
        x0, x1, y0, y1 = self.extent
        lo, hi = foot.polygon.min(axis=0), foot.polygon.max(axis=0)
        return x0 <= lo[0] and hi[0] <= x1 and y0 <= lo[1] and hi[1] <= y1


def plane_depth(K: np.ndarray, R_w2c: np.ndarray, t_w2c: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Camera depth (mm) where the rays through pixels (u, v) meet the table plane z = 0 (the whole
    plane, not only the table top); ``inf`` where a ray does not meet it in front of the camera."""
    n = R_w2c[:, 2]  # the table normal in the camera frame; the plane is n . x = n . t_w2c
    rays = np.linalg.inv(K) @ np.stack([np.asarray(u, np.float64), np.asarray(v, np.float64), np.ones(np.shape(u))])
    denom = n @ rays
    with np.errstate(divide="ignore", invalid="ignore"):
        z = float(n @ t_w2c) / denom  # rays have z = 1: the ray parameter is the depth
    return np.where(np.isfinite(z) & (z > 0), z, np.inf)


def shadow_pose(R: np.ndarray, t: np.ndarray, R_w2c: np.ndarray, t_w2c: np.ndarray,
                light_dir: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The model-to-camera map ``(A, b)`` (``x_c = A x_m + b``, ``A`` singular) that flattens a mesh
    posed ``(R, t)`` onto the table plane z = 0 along ``light_dir`` (camera frame, towards where the
    light shines): drawn with it, the mesh is its own cast shadow (a planar projection shadow).
    ``None`` when the light does not shine down onto the plane (grazing within ~6 degrees, or from
    below)."""
    n = R_w2c[:, 2]  # the table normal (camera frame); the plane is n . x = c
    c = float(n @ t_w2c)
    d = np.asarray(light_dir, np.float64) / np.linalg.norm(light_dir)
    nd = float(n @ d)
    if nd > -0.1:
        return None
    M = np.eye(3) - np.outer(d, n) / nd  # x -> x - ((n . x - c) / (n . d)) d
    return M @ np.asarray(R, np.float64), M @ np.asarray(t, np.float64) + (c / nd) * d


def depth_tolerance(z: np.ndarray, znear: float) -> np.ndarray:
    """Slack (mm) for comparing rendered depths with :func:`plane_depth`: a 24-bit depth buffer's step
    at depth z is about z^2 / (znear 2^24); a few steps plus 1e-4 z."""
    z = np.asarray(z, dtype=np.float64)
    return 1e-4 * z + 8.0 * z * z / (znear * 2.0**24) + 1e-3
