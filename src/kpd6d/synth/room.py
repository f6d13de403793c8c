"""A procedural room around the table (``layout: tabletop`` with ``table_room_prob > 0``).

Real table-top photographs show more than a table: the floor beyond its edges, walls, furniture,
posters and screens. Without them, everything a detector learns about "not an object" comes from
the flat backdrop pasted behind the renders. This module builds, from the random generator and the
background source alone (no real image), a room in the *table frame* of :mod:`kpd6d.synth.tabletop`
(table top in z = 0, +z up, origin at the look-at point):

- a floor plane ``table_height`` below the table top, textured;
- four walls (vertical planes) around the look-at point, each far enough that every camera the
  layout can sample stays inside the room, textured (walls and floor with muted colours: a prior
  about rooms, blended towards grey by a random amount);
- posters and screens on the walls (flat textured rectangles a few mm in front of a wall; a screen
  is emissive, so it stays bright whatever the lighting, with a dark bezel);
- furniture: textured boxes standing on the floor along the walls (cabinets, shelves, desks).

Every surface faces the room's inside (pyrender culls back faces). The room is drawn in the colour
pass only, like the table: it never touches the objects (they stand on the table, the room is below
and around it), and wherever it does cover one (furniture between camera and table) the two-pass
occlusion rule of :mod:`kpd6d.synth.scene` removes those pixels from the object's visible mask.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Room", "make_room", "textured_box", "textured_quad"]


def _material(image: np.ndarray, emissive: bool = False):
    import trimesh
    from PIL import Image

    tex = Image.fromarray(np.ascontiguousarray(image))
    if emissive:  # a screen: its picture is emitted (bright under any light), its albedo dark
        dark = Image.fromarray(np.full((4, 4, 3), 12, np.uint8))
        return trimesh.visual.material.PBRMaterial(baseColorTexture=dark, emissiveTexture=tex,
                                                   emissiveFactor=[1.0, 1.0, 1.0], metallicFactor=0.0,
                                                   roughnessFactor=0.3)
    return trimesh.visual.material.PBRMaterial(baseColorTexture=tex, metallicFactor=0.1, roughnessFactor=0.85)


def _quads_mesh(quads: list[tuple[np.ndarray, np.ndarray, np.ndarray]], image: np.ndarray, emissive: bool = False):
    """One mesh of planar quads ``(corner, u, v)`` (corner + a u + b v, a, b in [0, 1]), each showing
    the whole ``image``, front face on the side of ``u x v``."""
    import trimesh

    verts, uvs, faces = [], [], []
    for corner, u, v in quads:
        c = np.asarray(corner, np.float64)
        base = len(verts)
        verts += [c, c + u, c + u + v, c + v]
        uvs += [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]
        faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    mesh = trimesh.Trimesh(vertices=np.array(verts), faces=np.array(faces), process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=np.array(uvs), material=_material(image, emissive))
    return mesh


def _facing(corner, u, v, towards) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(corner, u, v)`` with ``u x v`` pointing to the side of the point ``towards``."""
    corner, u, v = (np.asarray(a, np.float64) for a in (corner, u, v))
    centre = corner + 0.5 * (u + v)
    if np.dot(np.cross(u, v), np.asarray(towards, np.float64) - centre) < 0:
        u, v = v, u
    return corner, u, v


def textured_quad(corner, u, v, image: np.ndarray, towards, emissive: bool = False):
    """The rectangle ``corner + a u + b v`` textured with ``image``, facing the point ``towards``."""
    return _quads_mesh([_facing(corner, u, v, towards)], image, emissive)


def textured_box(lo, hi, image: np.ndarray, bottom: bool = False):
    """The axis-aligned box [lo, hi] (table frame) with every face showing ``image``, faces outwards;
    the bottom face is left out unless ``bottom`` (a box standing on the floor never shows it)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    edges = np.diag(hi - lo)  # the box's three edge vectors
    c, far = (lo + hi) / 2, 10.0 * float((hi - lo).max())
    quads = []
    for axis, (e1, e2) in enumerate(((edges[1], edges[2]), (edges[0], edges[2]), (edges[0], edges[1]))):
        for side in (0, 1):
            if axis == 2 and side == 0 and not bottom:
                continue
            outward = c + (2 * side - 1) * far * np.eye(3)[axis]  # a point outside this face
            quads.append(_facing(lo + side * edges[axis], e1, e2, outward))
    return _quads_mesh(quads, image)


@dataclass
class Room:
    """The meshes of one room (table frame) and its layout, for tests and previews."""

    meshes: list = field(default_factory=list)
    floor_z: float = 0.0  # the floor's height (negative: below the table top)
    walls: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # x0, x1, y0, y1 of the walls
    height: float = 0.0  # wall height above the floor


def _screen_image(rng, backgrounds, w: int, h: int) -> np.ndarray:
    """A screen's picture: a bright procedural image inside a dark bezel."""
    img = backgrounds.sample(rng, w, h).astype(np.float32)
    img = 80.0 + 0.7 * img  # screens are bright
    b = max(2, int(0.04 * min(w, h)))
    img[:b], img[-b:], img[:, :b], img[:, -b:] = 15.0, 15.0, 15.0, 15.0
    return np.clip(img, 0, 255).astype(np.uint8)


def _muted(rng, img: np.ndarray) -> np.ndarray:
    """Walls and floors are mostly plainer than posters: blend towards grey by a random amount."""
    a = np.float32(rng.uniform(0.0, 0.8))
    grey = img.astype(np.float32).mean(axis=2, keepdims=True)
    return np.clip((1 - a) * img + a * grey, 0, 255).astype(np.uint8)


def make_room(rng: np.random.Generator, backgrounds, table_extent, clear_radius: float,
              table_height_range: tuple[float, float] = (650.0, 800.0),
              depth_range: tuple[float, float] = (300.0, 2500.0),
              height_range: tuple[float, float] = (2200.0, 3000.0),
              wall_items: tuple[int, int] = (2, 8), furniture: tuple[int, int] = (1, 5),
              texture_px: int = 256) -> Room:
    """A random room around a table of extent ``(x0, x1, y0, y1)`` (table frame, mm).

    Each wall stands ``clear_radius`` plus a depth drawn from ``depth_range`` away from the look-at
    point (and at least ``depth_range[0]`` beyond the table's edge), so a camera within
    ``clear_radius`` of the look-at point (horizontally) is inside the room. Textures come from
    ``backgrounds`` at ``texture_px`` on their long side (walls and floor twice that).
    """
    x0, x1, y0, y1 = (float(a) for a in table_extent)
    floor_z = -float(rng.uniform(*table_height_range))
    height = float(rng.uniform(*height_range))
    top = floor_z + height
    near = float(depth_range[0])
    wx0 = min(x0 - near, -clear_radius) - float(rng.uniform(*depth_range))
    wx1 = max(x1 + near, clear_radius) + float(rng.uniform(*depth_range))
    wy0 = min(y0 - near, -clear_radius) - float(rng.uniform(*depth_range))
    wy1 = max(y1 + near, clear_radius) + float(rng.uniform(*depth_range))
    inside = np.array([0.0, 0.0, floor_z + 1000.0])
    big = 2 * texture_px
    meshes = [textured_quad([wx0, wy0, floor_z], [wx1 - wx0, 0, 0], [0, wy1 - wy0, 0],
                            _muted(rng, backgrounds.sample(rng, big, big)), inside)]
    # walls: (corner, along, inward normal)
    walls = [((wx0, wy0), (wx1 - wx0, 0.0), (0.0, 1.0)), ((wx0, wy1), (wx1 - wx0, 0.0), (0.0, -1.0)),
             ((wx0, wy0), (0.0, wy1 - wy0), (1.0, 0.0)), ((wx1, wy0), (0.0, wy1 - wy0), (-1.0, 0.0))]
    for (cx, cy), (ax, ay), _ in walls:
        length = math.hypot(ax, ay)
        tw, th = big, max(8, round(big * height / length))
        meshes.append(textured_quad([cx, cy, floor_z], [ax, ay, 0.0], [0.0, 0.0, height],
                                    _muted(rng, backgrounds.sample(rng, tw, th)), inside))
    # posters and screens on the walls, a few mm in front of them
    for _ in range(int(rng.integers(wall_items[0], wall_items[1] + 1))):
        (cx, cy), (ax, ay), (nx, ny) = walls[int(rng.integers(4))]
        length = math.hypot(ax, ay)
        w = float(rng.uniform(250.0, min(1600.0, 0.8 * length)))
        h = float(rng.uniform(0.4, 1.2)) * w
        h = min(h, 0.8 * height)
        s = float(rng.uniform(0.0, max(length - w, 0.0)))
        z = float(rng.uniform(floor_z + 500.0, max(floor_z + 500.0, top - h - 100.0)))
        off = float(rng.uniform(3.0, 40.0))
        d = np.array([ax, ay, 0.0]) / length
        corner = np.array([cx, cy, 0.0]) + s * d + off * np.array([nx, ny, 0.0])
        corner[2] = z
        px_w = texture_px
        px_h = max(8, round(texture_px * h / w))
        screen = rng.random() < 0.35
        img = _screen_image(rng, backgrounds, px_w, px_h) if screen else backgrounds.sample(rng, px_w, px_h)
        meshes.append(textured_quad(corner, w * d, [0.0, 0.0, h], img, inside, emissive=screen))
    # furniture: boxes on the floor against a wall (they may stand behind or beside the table)
    for _ in range(int(rng.integers(furniture[0], furniture[1] + 1))):
        (cx, cy), (ax, ay), (nx, ny) = walls[int(rng.integers(4))]
        length = math.hypot(ax, ay)
        w = float(rng.uniform(400.0, min(2000.0, length)))
        dep = float(rng.uniform(300.0, 700.0))
        hgt = float(rng.uniform(400.0, min(2000.0, 0.9 * height)))
        s = float(rng.uniform(0.0, max(length - w, 0.0)))
        d = np.array([ax, ay]) / length
        n = np.array([nx, ny])
        p0 = np.array([cx, cy]) + s * d + 5.0 * n
        p1 = p0 + w * d + dep * n
        lo2, hi2 = np.minimum(p0, p1), np.maximum(p0, p1)
        # keep the box clear of the camera region and the table (it stands against the wall)
        if lo2[0] < x1 + near and hi2[0] > x0 - near and lo2[1] < y1 + near and hi2[1] > y0 - near:
            continue
        if np.all(np.abs(np.clip([0.0, 0.0], lo2, hi2)) < clear_radius):
            continue
        meshes.append(textured_box([lo2[0], lo2[1], floor_z], [hi2[0], hi2[1], floor_z + hgt],
                                   backgrounds.sample(rng, texture_px, texture_px)))
    return Room(meshes=meshes, floor_z=floor_z, walls=(wx0, wx1, wy0, wy1), height=height)
