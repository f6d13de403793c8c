"""Headless rendering of object models with pyrender (EGL).

``PYOPENGL_PLATFORM=egl`` is set here (unless the user chose a platform): Mesa's software
renderer serves on a CPU-only machine, the NVIDIA driver on a GPU machine. Poses are given in
OpenCV/BOP convention; :mod:`kpd6d.geometry` does the only OpenCV -> OpenGL conversion.
"""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def _load_triton_before_mesa() -> None:
    """Load triton's LLVM before Mesa's llvmpipe brings its own.

    Both bundle LLVM; when Mesa's is loaded first (the first render on a CPU-only machine), a later
    ``import triton`` (torchvision.ops, torch._dynamo) crashes the process with a segmentation fault.
    Loaded in this order both work. Absent triton (CPU torch builds), nothing to do.
    """
    try:
        import triton  # noqa: F401
    except Exception:  # not installed, or unusable here: nothing can conflict then
        pass


_load_triton_before_mesa()

import time  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402

import numpy as np  # noqa: E402

from kpd6d.geometry import LINEMOD_IMAGE_SIZE, LINEMOD_K, cv_pose_to_gl_model_view  # noqa: E402

__all__ = ["Light", "Lighting", "RenderResult", "Renderer", "linear_vertex_colors"]


def _tint(rng: np.random.Generator) -> np.ndarray:
    """A random light colour between roughly 2700 K (warm) and 6500 K (cool), as RGB gains."""
    w = rng.uniform(-1.0, 1.0)
    return np.clip(np.array([1.0 + 0.12 * w, 1.0, 1.0 - 0.15 * w]) * rng.uniform(0.9, 1.0, 3), 0.0, 1.2)


def _light_colour(rng: np.random.Generator) -> tuple[float, float, float]:
    """:func:`_tint` as a light's colour."""
    return tuple(float(c) for c in _tint(rng))


@dataclass
class Light:
    """A directional light, ``direction`` in the OpenCV camera frame (towards where it shines)."""

    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    intensity: float = 3.0


@dataclass
class Lighting:
    ambient: tuple[float, float, float] = (0.35, 0.35, 0.35)
    lights: list[Light] = field(default_factory=lambda: [Light()])
    specular: float = 0.0  # 0: matte (vertex colours as they are); >0 adds a metallic-roughness sheen

    @classmethod
    def random(cls, rng: np.random.Generator, specular_prob: float = 0.3) -> Lighting:
        """Random ambient, 1-2 directional lights (direction, colour, intensity), optional specular."""
        amb = rng.uniform(0.15, 0.6) * rng.uniform(0.85, 1.0, 3)
        lights = []
        for _ in range(int(rng.integers(1, 3))):
            d = rng.normal(size=3)
            d[2] = abs(d[2]) + 0.3  # mostly from behind the camera, towards the scene
            lights.append(Light(tuple(d / np.linalg.norm(d)), tuple(rng.uniform(0.8, 1.0, 3)), float(rng.uniform(1.5, 5.0))))
        spec = float(rng.uniform(0.1, 0.5)) if rng.random() < specular_prob else 0.0
        return cls(tuple(amb), lights, spec)

    @classmethod
    def random_indoor(cls, rng: np.random.Generator, specular_prob: float = 0.3) -> Lighting:
        """Wider, on average dimmer indoor lighting than :meth:`random` (for scanned models whose vertex
        colours already hold their albedo under light): ambient 0.2-0.9 with a colour temperature
        tint, 1-3 directional lights of intensity 0.3-3.5, each tinted warm or cool, mostly from above
        the camera's side of the scene; optional specular sheen."""
        amb = rng.uniform(0.2, 0.9) * _tint(rng)
        lights = []
        for _ in range(int(rng.integers(1, 4))):
            d = rng.normal(size=3)
            d[2] = abs(d[2]) + 0.3
            d[1] = abs(d[1]) * 0.5 + 0.2  # OpenCV y points down: light mostly from above
            lights.append(Light(tuple(d / np.linalg.norm(d)), _light_colour(rng), float(rng.uniform(0.3, 3.5))))
        spec = float(rng.uniform(0.1, 0.5)) if rng.random() < specular_prob else 0.0
        return cls(tuple(float(a) for a in amb), lights, spec)

    @classmethod
    def random_contrast(cls, rng: np.random.Generator, gloss_prob: float = 0.5) -> Lighting:
        """High-contrast lighting: a dim tinted ambient (0.05-0.35), one strong key light (intensity 2-5)
        from above the camera's side of the scene and 0-1 weak fill lights (0.2-1.0), so that the objects
        show strong shading (a lamp or a window beside a table, not the even light of :meth:`random_indoor`);
        with probability ``gloss_prob`` glossy surfaces (roughness 0.1-0.45: specular 0.35-0.7) whose
        highlights are visible."""
        def direction(up: float):
            d = rng.normal(size=3)
            d[2] = abs(d[2]) + 0.2
            d[1] = abs(d[1]) + up  # OpenCV y points down: the light shines down onto the table
            return tuple(float(v) for v in d / np.linalg.norm(d))

        amb = rng.uniform(0.05, 0.35) * _tint(rng)
        lights = [Light(direction(0.3), _light_colour(rng), float(rng.uniform(2.0, 5.0)))]
        for _ in range(int(rng.integers(0, 2))):
            lights.append(Light(direction(0.0), _light_colour(rng), float(rng.uniform(0.2, 1.0))))
        spec = float(rng.uniform(0.35, 0.7)) if rng.random() < gloss_prob else 0.0
        return cls(tuple(float(a) for a in amb), lights, spec)


@dataclass
class RenderResult:
    rgb: np.ndarray  # (H, W, 3) uint8; background black
    depth: np.ndarray  # (H, W) float32 mm, 0 where nothing
    masks_visib: list[np.ndarray]  # per instance (H, W) bool: visible pixels
    masks_full: list[np.ndarray | None]  # per instance (H, W) bool: silhouette ignoring occluders (if asked)


def _look_rotation(direction) -> np.ndarray:
    """4x4 GL pose whose -z axis points along ``direction`` (given in OpenCV camera frame)."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    d_gl = d * np.array([1.0, -1.0, -1.0])  # CV -> GL axes (direction only)
    z = -d_gl
    a = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(a, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    return T


def linear_vertex_colors(colors: np.ndarray) -> np.ndarray:
    """Vertex colours (n, 3|4), uint8 or float in [0, 1], as stored in meshes (sRGB-encoded, like
    every photograph and scan) → the linear float32 values pyrender's shader expects.

    pyrender's fragment shader linearises *textures* (``srgb_to_linear``) but multiplies the lit,
    linear colour by the raw vertex colour and then encodes the result with ``pow(c, 1 / 2.2)``: a
    vertex colour of 30/255 under unit light came out as 96/255, every scanned object pale and
    washed out. Raising the RGB to the power 2.2 (the inverse of that encoding) makes a colour
    under unit light come out as itself; alpha is kept.
    """
    c = np.asarray(colors)
    c = (c / 255.0) if np.issubdtype(c.dtype, np.integer) else c.astype(np.float64)
    out = np.array(c, dtype=np.float32)
    out[..., :3] = np.power(np.clip(c[..., :3], 0.0, 1.0), 2.2)
    return out


def _destroy_egl_context(platform) -> None:
    """pyrender's ``EGLPlatform.delete_context`` without its ``eglTerminate`` of the shared display."""
    from OpenGL.EGL import eglDestroyContext

    if platform._egl_display is not None and platform._egl_context is not None:
        eglDestroyContext(platform._egl_display, platform._egl_context)
    platform._egl_context = None


class Renderer:
    """Renders meshes at OpenCV poses with intrinsics ``K`` into (width, height) images.

    One OpenGL context per instance (and per process: create it after forking). Meshes are
    converted to pyrender once and cached by identity. ``smooth_models=True`` shades the meshes of
    :class:`~kpd6d.objects.ObjectModel` instances (scans) with interpolated vertex normals instead of
    flat faces (highlights on a glossy scan then spread smoothly instead of sparkling facet by facet);
    bare trimesh meshes (distractors, the table) stay flat. ``antialias=False`` renders into a
    single-sampled framebuffer instead of pyrender's 4x multisampled one (aliased colour edges;
    about 2.5x faster colour passes and cheaper depth / segmentation passes on llvmpipe). Several
    renderers may be open at once; closing one leaves the others working.
    """

    _open = 0  # renderers of this process not yet closed

    def __init__(self, width: int = LINEMOD_IMAGE_SIZE[0], height: int = LINEMOD_IMAGE_SIZE[1],
                 K: np.ndarray = LINEMOD_K, znear: float = 10.0, zfar: float = 20000.0,
                 antialias: bool = True, smooth_models: bool = False) -> None:
        import pyrender

        self.width, self.height = int(width), int(height)
        self.K = np.asarray(K, dtype=np.float64)
        self.znear, self.zfar = znear, zfar
        self.antialias = bool(antialias)
        self.smooth_models = bool(smooth_models)
        self._pyrender = pyrender
        try:
            self._renderer = pyrender.OffscreenRenderer(self.width, self.height)
        except Exception as exc:  # pragma: no cover - depends on the machine's GL stack
            raise RuntimeError(
                f"cannot create a headless OpenGL context (PYOPENGL_PLATFORM={os.environ.get('PYOPENGL_PLATFORM')}): "
                f"{exc}. On Debian/Ubuntu install libegl1 and libgl1-mesa-dri (Mesa's EGL) or an NVIDIA driver."
            ) from exc
        # (id(trimesh), smooth) -> (pyrender mesh, trimesh (kept alive so the id stays unique), base roughness
        # per primitive). Cached meshes stay uploaded to the GL context (see ``render``).
        Renderer._open += 1
        self._cache: dict[tuple[int, bool], tuple] = {}
        #: GL passes drawn so far, by kind ("colour", "segmentation"): (count, seconds incl. read-back)
        self.pass_stats: dict[str, tuple[int, float]] = {}
        if not self.antialias:
            self._single_sample_framebuffer()
        self._keep_cached_meshes_resident()

    def _keep_cached_meshes_resident(self) -> None:
        """Keep every cached mesh's buffers in the GL context between renders.

        pyrender deletes the GL buffers of meshes missing from the scene being rendered and uploads
        them again when they come back (tens of ms for a dense mesh on a CPU). Here its context update
        leaves cached meshes alone; meshes dropped from the cache are deleted as usual.
        """
        inner = getattr(self._renderer, "_renderer", None)
        if inner is None or not hasattr(inner, "_update_context"):  # pragma: no cover
            return
        orig = inner._update_context
        cache = self._cache

        def update_context(scene, flags):
            resident = {entry[0] for entry in cache.values()}
            hold = (inner._meshes - scene.meshes) & resident
            inner._meshes -= hold
            try:
                return orig(scene, flags)
            finally:
                inner._meshes |= hold

        inner._update_context = update_context

    def _single_sample_framebuffer(self) -> None:
        """Create pyrender's main framebuffer now, with 1 sample instead of its hard-coded 4.

        pyrender renders every pass into a 4x multisampled framebuffer and resolves it; on Mesa's
        llvmpipe clearing, shading and resolving 4 samples per pixel costs about 2.5x in the colour
        pass and several ms in every pass. With one sample the colour pass is not anti-aliased;
        depth and segmentation (already sampled at pixel centres) are unchanged. The viewport
        never changes size, so pyrender keeps this framebuffer.
        """
        import pyrender.renderer as prr

        inner = getattr(self._renderer, "_renderer", None)
        if inner is None or not hasattr(inner, "_configure_main_framebuffer"):  # pragma: no cover
            return
        orig = prr.glRenderbufferStorageMultisample

        def storage(target, samples, fmt, w, h):
            return orig(target, 0, fmt, w, h)

        self._renderer._platform.make_current()
        prr.glRenderbufferStorageMultisample = storage
        try:
            inner._configure_main_framebuffer()
        finally:
            prr.glRenderbufferStorageMultisample = orig

    def close(self) -> None:
        if getattr(self, "_renderer", None) is None:
            return
        r, self._renderer = self._renderer, None
        Renderer._open -= 1
        platform = getattr(r, "_platform", None)
        if Renderer._open > 0 and platform is not None and hasattr(platform, "_egl_display"):
            # pyrender's EGL teardown terminates the display, which every context of the process shares:
            # the renderers still open (e.g. a scene renderer beside a pose refiner's) would stop working.
            # Destroy this context only; the last renderer to close terminates the display.
            platform.delete_context = lambda: _destroy_egl_context(platform)
        r.delete()

    def __del__(self) -> None:  # pragma: no cover
        try:
            self.close()
        except Exception:
            pass

    def set_intrinsics(self, K: np.ndarray) -> None:
        self.K = np.asarray(K, dtype=np.float64)

    def _camera(self, K):
        # pixel centres at integer coordinates (OpenCV) vs at +0.5 (GL): shift the principal point
        return self._pyrender.IntrinsicsCamera(
            fx=K[0, 0], fy=K[1, 1], cx=K[0, 2] + 0.5, cy=K[1, 2] + 0.5, znear=self.znear, zfar=self.zfar
        )

    def forget(self, mesh) -> None:
        """Drop ``mesh`` from the cache (a one-image mesh): its GL buffers are released on the next render."""
        for smooth in (False, True):
            self._cache.pop((id(mesh), smooth), None)

    def _pymesh(self, mesh, specular: float, smooth: bool = False):
        """The cached pyrender mesh of ``mesh`` with its shininess set for ``specular``.

        pyrender's own material is kept (it carries the vertex colours / texture; passing a material
        to ``from_trimesh`` would drop them); only its roughness changes, in place (a uniform, so no
        re-upload): ``roughness = max(0.05, base - specular)`` (pyrender's base is 0.8). Vertex and
        face colours are converted to linear values first (:func:`linear_vertex_colors`).
        """
        smooth = bool(smooth)
        key = (id(mesh), smooth)
        entry = self._cache.get(key)
        if entry is None:
            pm = self._pyrender.Mesh.from_trimesh(mesh, smooth=smooth)
            for prim in pm.primitives:
                if prim.color_0 is not None:  # vertex / face colours: sRGB in, linear for the shader
                    prim.color_0 = linear_vertex_colors(prim.color_0)
            base = [getattr(p.material, "roughnessFactor", None) for p in pm.primitives]
            if len(self._cache) >= 256:
                self._cache.clear()  # unused meshes then leave the GL context on the next render
            entry = self._cache[key] = (pm, mesh, base)
        pm, _, base = entry
        for prim, r0 in zip(pm.primitives, base):
            if r0 is not None:
                rough = max(0.05, r0 - specular) if specular > 0 else r0
                if prim.material.roughnessFactor != rough:
                    prim.material.roughnessFactor = rough
        return pm

    def _timed_pass(self, kind: str, scene, **kwargs):
        """One pyrender pass, counted in :attr:`pass_stats` under ``kind``."""
        t0 = time.perf_counter()
        out = self._renderer.render(scene, **kwargs)
        n, s = self.pass_stats.get(kind, (0, 0.0))
        self.pass_stats[kind] = (n + 1, s + time.perf_counter() - t0)
        return out

    def _seg_pass(self, scene, nodes, only=None):
        """Depth (mm) and per-pixel instance ids (0: none) from pyrender's segmentation pass.

        pyrender renders colour with 4x multisampling, and its depth read-back then picks one
        sample, about 0.4 px off the pixel centre; the segmentation pass runs without multisampling,
        so its depth and ids are sampled exactly at pixel centres (consistent with
        :func:`kpd6d.geometry.project_points`). Ids are coded as colours (255, id & 255, id >> 8).
        """
        seg_map = {node: (255, (i + 1) & 255, (i + 1) >> 8) for i, node in enumerate(nodes)
                   if only is None or i == only}  # pyrender's SEG pass draws only mapped nodes
        seg, depth = self._timed_pass("segmentation", scene, flags=self._pyrender.RenderFlags.SEG, seg_node_map=seg_map)
        valid = (seg[..., 0] == 255) & (depth > 0)
        if len(nodes) < 255:  # ids fit the green channel (uint8 arithmetic: several times faster)
            label = np.where(valid, seg[..., 1], np.uint8(0))
        else:
            label = np.where(valid, seg[..., 1].astype(np.int32) | (seg[..., 2].astype(np.int32) << 8), 0)
        return depth, label

    def render(self, instances, *, lighting: Lighting | None = None, K: np.ndarray | None = None,
               full_masks: bool | Sequence[int] = False, depth_only: bool = False,
               masks: bool = True) -> RenderResult:
        """Render ``instances``: a list of ``(mesh_or_model, R, t)`` (R, t: model -> OpenCV camera, mm).

        ``mesh_or_model`` is an :class:`~kpd6d.objects.ObjectModel` or a trimesh mesh (distractors).
        Returns RGB (anti-aliased), depth (mm) and per-instance visible masks (both from one
        segmentation pass, sampled at pixel centres); ``depth_only=True`` skips the colour pass;
        ``full_masks=True`` also renders each instance alone for its unoccluded silhouette (visib ⊆ full);
        a sequence of instance indices renders only those (``masks_full`` holds None for the others).
        ``masks=False`` skips the segmentation pass: no masks, and the depth is the colour pass's,
        which is sampled at pixel centres (equal to the segmentation pass's) only when
        ``antialias=False``.
        """
        pyrender = self._pyrender
        K = self.K if K is None else np.asarray(K, dtype=np.float64)
        lighting = lighting or Lighting()
        scene = pyrender.Scene(ambient_light=np.asarray(lighting.ambient), bg_color=[0.0, 0.0, 0.0, 0.0])
        scene.add(self._camera(K), pose=np.eye(4))
        for light in lighting.lights:
            scene.add(pyrender.DirectionalLight(color=np.asarray(light.color), intensity=light.intensity),
                      pose=_look_rotation(light.direction))
        nodes = []
        for obj, R, t in instances:
            mesh = getattr(obj, "mesh", obj)
            smooth = self.smooth_models and mesh is not obj  # an ObjectModel's mesh (a scan), not a bare trimesh
            node = pyrender.Node(mesh=self._pymesh(mesh, lighting.specular, smooth), matrix=cv_pose_to_gl_model_view(R, t))
            scene.add_node(node)
            nodes.append(node)
        if depth_only:
            rgb = np.zeros((self.height, self.width, 3), np.uint8)
        else:
            rgb, colour_depth = self._timed_pass("colour", scene, flags=pyrender.RenderFlags.NONE)
            if not masks:
                return RenderResult(np.ascontiguousarray(rgb[..., :3]), colour_depth.astype(np.float32, copy=False),
                                    [], [])
        if nodes:
            depth, label = self._seg_pass(scene, nodes)
        else:
            depth, label = np.zeros((self.height, self.width), np.float32), None
        masks_visib = [label == (i + 1) for i in range(len(nodes))]
        masks_full: list[np.ndarray | None] = []
        if full_masks is not False and full_masks is not None and nodes:
            wanted = range(len(nodes)) if full_masks is True else sorted({int(i) for i in full_masks})
            masks_full = [None] * len(nodes)
            for i in wanted:
                if len(nodes) == 1:
                    masks_full[i] = masks_visib[i].copy()
                else:  # a segmentation pass drawing this instance alone (same rasterisation)
                    _, lab = self._seg_pass(scene, nodes, only=i)
                    masks_full[i] = lab > 0
                # a pixel centre covered by a front instance is covered by it alone
                masks_visib[i] = masks_visib[i] & masks_full[i]
        return RenderResult(np.ascontiguousarray(rgb[..., :3]), depth.astype(np.float32, copy=False), masks_visib,
                            masks_full)
