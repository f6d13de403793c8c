"""Settings of the synthetic-data generator (the ``**options`` of :func:`generate_dataset`, and
``conf/generate.yaml``)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

from kpd6d.config import to_fraction, to_int
from kpd6d.geometry import LINEMOD_IMAGE_SIZE, LINEMOD_K
from kpd6d.synth.palette import check_palette
from kpd6d.synth.photometric import PhotometricConfig
from kpd6d.synth.poses import ViewRanges

__all__ = ["LAYOUTS", "LIGHTING_STYLES", "SynthConfig", "default_K"]

LAYOUTS = ("free", "tabletop")
#: options of the table-top layout; with ``layout: free`` they are left out of ``to_dict`` while at
#: their defaults, so that free-layout runs record (and resume with) the same settings as before
_TABLETOP_FIELDS = ("layout", "table_elevation_range", "table_roll_range", "table_size_range",
                    "table_cluster_radius", "table_distractor_rest_prob", "table_upright_prob",
                    "table_room_prob", "table_shadow_prob")
#: ``lighting``: per image Lighting.random, Lighting.random_indoor, one of the two at random, or a constant light
LIGHTING_STYLES = ("random", "indoor", "mixed", "fixed")
#: options added after datasets were made without them: left out of ``to_dict`` while at their
#: defaults, so that those datasets resume with the settings they were made with
_LATER_FIELDS = ("palette", "distractor_refresh", "table_shadow_prob", "distractor_object_colors", "printed_matter",
                 "object_detail", "contrast_lighting", "smooth_objects")


def default_K(width: int, height: int) -> np.ndarray:
    """LineMod's K, scaled to (width, height) (identical at 640x480)."""
    W0, H0 = LINEMOD_IMAGE_SIZE
    K = LINEMOD_K.copy()
    sx, sy = width / W0, height / H0
    K[0, 0] *= sx
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5  # pixel centres at integers: scale about the image corner
    K[1, 1] *= sy
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


def _pair(name: str, v: Any) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair [low, high], got {v!r}") from None
    if not (math.isfinite(a) and math.isfinite(b)) or a > b:
        raise ValueError(f"{name} must be [low, high] with finite low <= high, got {v!r}")
    return a, b


def photometric_settings(cfg: Mapping | None) -> dict:
    """``cfg`` (PhotometricConfig fields, or {} / None for the defaults) validated and spelt out in full
    as plain JSON values: the form SynthConfig holds and dataset_info.json records."""
    pc = PhotometricConfig.from_mapping(dict(cfg or {}) if not isinstance(cfg, PhotometricConfig) else cfg)
    out = {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(pc).items()}
    for k in ("exposure", "saturation"):  # later options stay out while at their defaults (earlier datasets resume)
        if out[k] == [1.0, 1.0]:
            del out[k]
    return out


@dataclass
class SynthConfig:
    """All generator options; see docs/data.md for what each one does."""

    width: int = LINEMOD_IMAGE_SIZE[0]
    height: int = LINEMOD_IMAGE_SIZE[1]
    K: list | None = None  # 3x3 or 9 values; None: LineMod K scaled to width x height
    # objects and occluders
    objects_per_image: Any = (1, 1)  # [min, max] or "all"
    distractors: tuple[int, int] = (0, 2)  # [min, max] random primitive occluders per image
    distractor_pool_size: int = 24
    distractor_refresh: int = 0  # images per distractor pool: a new pool every n images (0: one pool per worker)
    distractor_size: tuple[float, float] = (0.3, 1.0)  # apparent size relative to the occluded object's box
    distractor_object_colors: float = 0.0  # fraction of the occluder pool coloured with a target object's colour
    #                                        layout (transferred onto the primitive) instead of a palette pattern
    visib_fract_range: tuple[float, float] = (0.3, 1.0)  # every object's visible fraction must lie in it
    max_retries: int = 10  # scene re-samples to meet visib_fract_range (then the closest one is kept)
    # poses
    distance_range: tuple[float, float] = (346.0, 1500.0)  # mm
    elevation_range: tuple[float, float] = (-15.0, 90.0)  # degrees
    azimuth_range: tuple[float, float] = (0.0, 360.0)
    inplane_range: tuple[float, float] = (-45.0, 45.0)
    view_margin: float = 0.1  # fraction of the object's box allowed outside the image
    canonicalize_symmetric: bool = True
    # scene layout: "free" (each object posed on its own, floating over the background) or "tabletop"
    # (objects resting on a textured table plane seen from above); the table_* options apply to tabletop
    layout: str = "free"
    table_elevation_range: tuple[float, float] = (15.0, 75.0)  # degrees, camera above the table plane
    table_roll_range: tuple[float, float] = (-15.0, 15.0)  # degrees, camera roll about its optical axis
    table_size_range: tuple[float, float] = (800.0, 2000.0)  # mm, side lengths of the table top
    table_cluster_radius: float = 0.15  # objects within this fraction of the camera distance of the look-at point
    table_distractor_rest_prob: float = 0.5  # chance that a distractor rests on the table (else it floats)
    table_upright_prob: float = 0.0  # chance that an object stands as modelled (model +z up) instead of a random stable pose
    table_shadow_prob: float = 0.0  # chance that the objects and occluders cast shadows of the main light onto the table
    table_room_prob: float = 0.0  # chance that the table stands in a procedural room (floor, walls, posters, screens, furniture)
    # appearance
    lighting: str = "random"  # "random" (Lighting.random per image), "indoor" (Lighting.random_indoor), "mixed" (either, half and half) or "fixed"
    specular_prob: float = 0.3
    contrast_lighting: float = 0.0  # chance per image that Lighting.random_contrast replaces the style's lighting: a dim
    #                                 ambient, one strong key light, glossy surfaces half of the time (strong shading, highlights)
    smooth_objects: bool = False  # shade the target objects' meshes with interpolated vertex normals (not flat facets)
    backgrounds_dir: str | None = None  # folder of images; None: procedural backgrounds
    palette: str = "uniform"  # colours of the procedural content: "uniform" RGB or "natural" (kpd6d.synth.palette)
    printed_matter: float = 0.0  # printed sheets (markers, text, tables, pictures) on this share of the procedural
    #                              backgrounds / table tops / room surfaces, and this fraction of the occluder pool
    #                              printed cards and boxes (kpd6d.synth.prints)
    feather_sigma: float = 0.7  # px; softens the pasted objects' edges (0: hard paste)
    object_detail: float = 0.0  # chance per image that the target objects' pixels get fine grain and sharpening
    #                             (kpd6d.synth.photometric.surface_detail): renders are smoother than photographs
    antialias: bool = False  # 4x multisampled colour pass (smoother edges, ~2.5x slower colour on llvmpipe)
    photometric: dict = field(default_factory=dict)  # PhotometricConfig fields; {"prob": 0} turns off
    # keypoints
    designator: dict | None = field(default_factory=lambda: {"name": "fps", "num_keypoints": 16})
    # output
    rgb_format: str = "jpg"  # jpg (as BOP's PBR training sets) | png
    png_compression: int = 1
    jpg_quality: int = 95
    depth: bool = False
    depth_scale: float = 0.1  # stored depth value x depth_scale = mm
    scene_size: int = 1000  # images per scene folder
    procedural_seed: int = 0  # seed of procedural_objects() when models_dir is None
    mp_start_method: str = "spawn"  # multiprocessing start method of the worker pool
    flush_interval_s: float = 5.0  # how often scene JSON files are rewritten during a run

    @classmethod
    def from_options(cls, options: Mapping[str, Any] | None = None) -> SynthConfig:
        """Build from keyword options; unknown names raise an error listing the known ones."""
        options = dict(options or {})
        known = [f.name for f in fields(cls)]
        unknown = sorted(set(options) - set(known))
        if unknown:
            raise TypeError(f"generate_dataset: unknown option(s) {', '.join(unknown)}; known options: {', '.join(known)}")
        cfg = cls(**options)
        cfg.validate()
        return cfg

    def validate(self) -> None:
        self.width, self.height = to_int(self.width, "width"), to_int(self.height, "height")
        if self.width < 8 or self.height < 8:
            raise ValueError(f"image size must be at least 8x8, got width={self.width}, height={self.height}")
        if self.K is not None:
            K = np.asarray(self.K, dtype=np.float64)
            if K.size != 9 or not np.isfinite(K).all():
                raise ValueError(f"K must be a 3x3 matrix (or 9 values), got {self.K!r}")
            K = K.reshape(3, 3)
            if K[0, 0] <= 0 or K[1, 1] <= 0:
                raise ValueError(f"K must have positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}")
            self.K = K.tolist()
        if isinstance(self.objects_per_image, str):
            if self.objects_per_image != "all":
                raise ValueError(f"objects_per_image must be [min, max] or 'all', got {self.objects_per_image!r}")
        elif isinstance(self.objects_per_image, int | np.integer):
            self.objects_per_image = (int(self.objects_per_image),) * 2
        else:
            lo, hi = _pair("objects_per_image", self.objects_per_image)
            if lo < 1:
                raise ValueError(f"objects_per_image must be at least 1, got {self.objects_per_image!r}")
            self.objects_per_image = (int(lo), int(hi))
        lo, hi = _pair("distractors", self.distractors)
        if lo < 0:
            raise ValueError(f"distractors must be >= 0, got {self.distractors!r}")
        self.distractors = (int(lo), int(hi))
        self.distractor_size = _pair("distractor_size", self.distractor_size)
        self.visib_fract_range = _pair("visib_fract_range", self.visib_fract_range)
        if not (0.0 <= self.visib_fract_range[0] and self.visib_fract_range[1] <= 1.0):
            raise ValueError(f"visib_fract_range must lie within [0, 1], got {list(self.visib_fract_range)}")
        for name in ("distance_range", "elevation_range", "azimuth_range", "inplane_range"):
            setattr(self, name, _pair(name, getattr(self, name)))
        self.view_ranges()  # validates the angle / distance ranges
        self._validate_layout()
        if self.lighting not in LIGHTING_STYLES:
            names = ", ".join(repr(x) for x in LIGHTING_STYLES[:-1])
            raise ValueError(f"lighting must be {names} or {LIGHTING_STYLES[-1]!r}, got {self.lighting!r}")
        check_palette(self.palette)
        self.distractor_refresh = to_int(self.distractor_refresh, "distractor_refresh")
        if self.distractor_refresh < 0:
            raise ValueError(f"distractor_refresh must be >= 0 (0: one pool), got {self.distractor_refresh!r}")
        for name in ("distractor_object_colors", "printed_matter", "object_detail", "contrast_lighting"):
            setattr(self, name, to_fraction(getattr(self, name), name))
        if not isinstance(self.smooth_objects, (bool, np.bool_)):
            raise ValueError(f"smooth_objects must be true or false, got {self.smooth_objects!r}")
        self.smooth_objects = bool(self.smooth_objects)
        if self.rgb_format not in ("png", "jpg"):
            raise ValueError(f"rgb_format must be 'png' or 'jpg', got {self.rgb_format!r}")
        if to_int(self.scene_size, "scene_size") < 1:
            raise ValueError(f"scene_size must be >= 1, got {self.scene_size}")
        if self.depth_scale <= 0:
            raise ValueError(f"depth_scale must be > 0, got {self.depth_scale}")
        if self.max_retries < 0:
            raise ValueError(f"max_retries must be >= 0, got {self.max_retries}")
        if self.mp_start_method not in ("spawn", "forkserver", "fork"):
            raise ValueError(f"mp_start_method must be spawn, forkserver or fork, got {self.mp_start_method!r}")
        if self.designator is not None:  # None: write no keypoints.json
            if not isinstance(self.designator, Mapping) or "name" not in self.designator:
                raise ValueError(f"designator must be a mapping with a 'name' key (or null), got {self.designator!r}")
            self.designator = dict(self.designator)
        # validated and spelt out in full, so the Python API and the YAML (which lists every default)
        # record the same settings in dataset_info.json and can resume each other's datasets
        self.photometric = photometric_settings(self.photometric)
        if self.backgrounds_dir is not None:
            self.backgrounds_dir = str(self.backgrounds_dir)

    def _validate_layout(self) -> None:
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {', '.join(map(repr, LAYOUTS))}, got {self.layout!r}")
        lo, hi = self.table_elevation_range = _pair("table_elevation_range", self.table_elevation_range)
        if not (0.0 < lo and hi <= 90.0):
            raise ValueError(f"table_elevation_range must lie in (0, 90] degrees (camera above the table), "
                             f"got {list(self.table_elevation_range)}")
        lo, hi = self.table_roll_range = _pair("table_roll_range", self.table_roll_range)
        if not (-180.0 <= lo and hi <= 180.0):
            raise ValueError(f"table_roll_range must lie in [-180, 180] degrees, got {list(self.table_roll_range)}")
        lo, hi = self.table_size_range = _pair("table_size_range", self.table_size_range)
        if lo <= 0:
            raise ValueError(f"table_size_range must be positive (mm), got {list(self.table_size_range)}")
        for name in ("table_cluster_radius", "table_distractor_rest_prob", "table_upright_prob",
                    "table_room_prob", "table_shadow_prob"):
            try:
                v = float(getattr(self, name))
            except (TypeError, ValueError):
                raise ValueError(f"{name} must be a number, got {getattr(self, name)!r}") from None
            setattr(self, name, v)
        if not (math.isfinite(self.table_cluster_radius) and self.table_cluster_radius > 0):
            raise ValueError(f"table_cluster_radius must be > 0 (a fraction of the camera distance), "
                             f"got {self.table_cluster_radius!r}")
        if not (0.0 <= self.table_distractor_rest_prob <= 1.0):
            raise ValueError(f"table_distractor_rest_prob must lie in [0, 1], got {self.table_distractor_rest_prob!r}")
        if not (0.0 <= self.table_upright_prob <= 1.0):
            raise ValueError(f"table_upright_prob must lie in [0, 1], got {self.table_upright_prob!r}")
        if not (0.0 <= self.table_shadow_prob <= 1.0):
            raise ValueError(f"table_shadow_prob must lie in [0, 1], got {self.table_shadow_prob!r}")
        if not (0.0 <= self.table_room_prob <= 1.0):
            raise ValueError(f"table_room_prob must lie in [0, 1], got {self.table_room_prob!r}")

    # -- derived ---------------------------------------------------------------------------------
    def camera_K(self) -> np.ndarray:
        return np.asarray(self.K, dtype=np.float64).reshape(3, 3) if self.K is not None else default_K(self.width, self.height)

    def view_ranges(self) -> ViewRanges:
        return ViewRanges(self.distance_range, self.elevation_range, self.azimuth_range, self.inplane_range)

    def photometric_config(self) -> PhotometricConfig:
        return PhotometricConfig.from_mapping(self.photometric)

    def to_dict(self) -> dict:
        def plain(v):
            return list(v) if isinstance(v, tuple) else v

        d = {k: plain(v) for k, v in asdict(self).items()}
        defaults = {f.name: f.default for f in fields(self)}
        # as before these options existed (dataset_info.json, resuming)
        for name in dict.fromkeys((*(_TABLETOP_FIELDS if self.layout == "free" else ()), *_LATER_FIELDS)):
            if d[name] == plain(defaults[name]):
                del d[name]
        return d
