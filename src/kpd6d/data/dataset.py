"""Reading BOP datasets: :class:`BopDataset` -> :class:`Frame` -> :class:`Instance`.

Reads what :func:`kpd6d.synth.generate_dataset` writes and published BOP datasets (LM, LM-O, ...)
the same way. Only the three scene JSON files are needed; images and masks are read on demand, so
an annotation-only copy (no ``rgb/``) can still be listed and scored.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kpd6d.data.bop_io import (
    BopFormatError,
    load_camera,
    load_scene_camera,
    load_scene_gt,
    load_scene_gt_info,
    load_targets,
)
from kpd6d.io import read_image

__all__ = ["BopDataset", "Frame", "Instance"]

_RGB_DIRS = ("rgb", "gray")
_RGB_EXTS = (".png", ".jpg", ".jpeg", ".tif")


@dataclass
class Instance:
    """One annotated object instance of a frame (BOP scene_gt + scene_gt_info entry ``gt_index``).

    ``bbox_obj`` / ``bbox_visib`` are BOP (x, y, w, h) int boxes; the gt_info fields are ``None``
    when the scene has no scene_gt_info.json.
    """

    obj_id: int
    R: np.ndarray  # (3, 3) model -> camera
    t: np.ndarray  # (3,) mm
    bbox_obj: np.ndarray | None = None
    bbox_visib: np.ndarray | None = None
    visib_fract: float | None = None
    px_count_visib: int | None = None
    gt_index: int = 0
    px_count_all: int | None = None
    px_count_valid: int | None = None


@dataclass
class Frame:
    """One image of a BOP scene with its camera and annotated instances."""

    scene_id: int
    im_id: int
    rgb_path: Path
    K: np.ndarray  # (3, 3)
    instances: list[Instance] = field(default_factory=list)
    scene_dir: Path | None = None
    depth_scale: float | None = None
    targets: dict[int, int] | None = None  # obj_id -> inst_count when read with a targets file

    def load_rgb(self) -> np.ndarray:
        """The image as RGB uint8 (H, W, 3) (grayscale images are repeated to 3 channels)."""
        img = read_image(self.rgb_path)
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        if img.dtype != np.uint8:
            img = (img / (65535.0 if img.dtype == np.uint16 else img.max() or 1) * 255).round().astype(np.uint8)
        return img

    def mask_visib_path(self, gt_index: int) -> Path:
        return self._dir() / "mask_visib" / f"{self.im_id:06d}_{int(gt_index):06d}.png"

    def load_mask_visib(self, gt_index: int) -> np.ndarray:
        """Visible mask (H, W) bool of instance ``gt_index`` (index into the scene_gt list)."""
        m = read_image(self.mask_visib_path(gt_index))
        return (m if m.ndim == 2 else m[..., 0]) > 0

    def depth_path(self) -> Path:
        return self._dir() / "depth" / f"{self.im_id:06d}.png"

    def load_depth(self) -> np.ndarray:
        """Depth (H, W) float32 in mm (stored value x depth_scale); 0 where unknown."""
        d = read_image(self.depth_path())
        return d.astype(np.float32) * float(self.depth_scale if self.depth_scale is not None else 1.0)

    def _dir(self) -> Path:
        if self.scene_dir is None:
            raise ValueError(f"frame (scene {self.scene_id}, image {self.im_id}) has no scene_dir")
        return self.scene_dir


class BopDataset(Sequence):
    """Frames of ``<root>/<split>/<scene>/`` of a BOP dataset.

    ``obj_ids`` keeps only instances of those objects (and frames holding at least one).
    ``targets`` is a BOP19 targets file (``test_targets_bop19.json``; a relative path is also looked
    up in ``root``): frames are restricted to the listed (scene, image) pairs, instances to the listed
    objects, and ``frame.targets`` holds ``{obj_id: inst_count}``. ``models_dir`` defaults to
    ``<root>/models``.
    """

    def __init__(self, root: str | os.PathLike, split: str = "test", obj_ids: Sequence[int] | None = None,
                 targets: str | os.PathLike | None = None, models_dir: str | os.PathLike | None = None) -> None:
        self.root = Path(root)
        self.split = split
        self._models: dict = {}  # load_models' meshes, by object ids
        self.split_dir = self.root / split
        self.obj_ids = None if obj_ids is None else sorted(int(o) for o in obj_ids)
        self.models_dir = Path(models_dir) if models_dir is not None else self.root / "models"
        if not self.root.is_dir():
            raise FileNotFoundError(f"{self.root}: BOP dataset root does not exist")
        if not self.split_dir.is_dir():
            splits = sorted(p.name for p in self.root.iterdir() if p.is_dir() and any(p.glob("*/scene_gt.json")))
            raise FileNotFoundError(f"{self.split_dir}: split {split!r} does not exist; splits found: {splits or '(none)'}")
        self.targets_path = self._resolve_targets(targets)
        self.targets = load_targets(self.targets_path) if self.targets_path is not None else None
        self.camera = load_camera(self.root / "camera.json") if (self.root / "camera.json").is_file() else None
        self.frames: list[Frame] = []
        scene_dirs = sorted(p for p in self.split_dir.iterdir() if p.is_dir() and p.name.isdigit())
        if not scene_dirs:
            raise FileNotFoundError(f"{self.split_dir}: no scene folders (<scene_id:06d>/) found")
        for sd in scene_dirs:
            self.frames.extend(self._read_scene(sd))
        if self.targets is not None:
            have = {(f.scene_id, f.im_id) for f in self.frames}
            missing = sorted(k for k in self.targets if k not in have and (self.obj_ids is None or set(self.targets[k]) & set(self.obj_ids)))
            if missing:
                raise BopFormatError(
                    f"{self.targets_path}: {len(missing)} target (scene_id, im_id) pair(s) not annotated under "
                    f"{self.split_dir}, e.g. {missing[:5]}"
                )

    # -- construction -------------------------------------------------------------------------
    def _resolve_targets(self, targets) -> Path | None:
        if targets is None:
            return None
        p = Path(targets)
        if not p.is_file() and not p.is_absolute() and (self.root / p).is_file():
            p = self.root / p
        if not p.is_file():
            raise FileNotFoundError(f"{p}: targets file does not exist")
        return p

    def _read_scene(self, sd: Path) -> list[Frame]:
        scene_id = int(sd.name)
        gt_path = sd / "scene_gt.json"
        if not gt_path.is_file():
            raise BopFormatError(f"{gt_path}: scene_gt.json does not exist (every BOP scene folder needs it)")
        gt = load_scene_gt(gt_path)
        cam = load_scene_camera(sd / "scene_camera.json")
        info_path = sd / "scene_gt_info.json"
        info = load_scene_gt_info(info_path) if info_path.is_file() else None
        rgb_dir, ext = _rgb_layout(sd)
        frames = []
        for im_id, insts in gt.items():
            tgt = None
            if self.targets is not None:
                tgt = self.targets.get((scene_id, im_id))
                if tgt is None:
                    continue
            if im_id not in cam:
                raise BopFormatError(f"{sd / 'scene_camera.json'}: no entry for image {im_id} (listed in scene_gt.json)")
            infos = None
            if info is not None:
                infos = info.get(im_id)
                if infos is None:
                    raise BopFormatError(f"{info_path}: no entry for image {im_id} (listed in scene_gt.json)")
                if len(infos) != len(insts):
                    raise BopFormatError(
                        f"{info_path}: image {im_id} has {len(infos)} entries but scene_gt.json lists {len(insts)} instances"
                    )
            instances = []
            for j, g in enumerate(insts):
                if self.obj_ids is not None and g["obj_id"] not in self.obj_ids:
                    continue
                if tgt is not None and g["obj_id"] not in tgt:
                    continue
                inst = Instance(obj_id=g["obj_id"], R=g["R"], t=g["t"], gt_index=j)
                if infos is not None:
                    e = infos[j]
                    inst.bbox_obj, inst.bbox_visib = e["bbox_obj"], e["bbox_visib"]
                    inst.visib_fract, inst.px_count_visib = e["visib_fract"], e["px_count_visib"]
                    inst.px_count_all, inst.px_count_valid = e["px_count_all"], e["px_count_valid"]
                instances.append(inst)
            if (self.obj_ids is not None or tgt is not None) and not instances:
                continue
            if tgt is not None and self.obj_ids is not None:
                tgt = {o: c for o, c in tgt.items() if o in self.obj_ids}
            frames.append(Frame(
                scene_id=scene_id, im_id=im_id, rgb_path=rgb_dir / f"{im_id:06d}{ext}", K=cam[im_id]["K"],
                instances=instances, scene_dir=sd, depth_scale=cam[im_id]["depth_scale"], targets=tgt,
            ))
        return frames

    # -- access ---------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return self.frames[i]
        return self.frames[i]

    def __iter__(self) -> Iterator[Frame]:
        return iter(self.frames)

    def __repr__(self) -> str:
        return f"BopDataset({str(self.root)!r}, split={self.split!r}, frames={len(self)})"

    @property
    def scene_ids(self) -> list[int]:
        return sorted({f.scene_id for f in self.frames})

    def instance_obj_ids(self) -> list[int]:
        """Object ids annotated in the (filtered) frames."""
        return sorted({inst.obj_id for f in self.frames for inst in f.instances})

    def load_models(self, obj_ids: Sequence[int] | None = None):
        """:class:`~kpd6d.objects.ObjectModel` list of ``models_dir`` (default: the dataset's obj_ids).

        Each mesh is read once per dataset object: the evaluation's metrics and the pose refiner
        share the same models."""
        from kpd6d.objects import load_bop_models

        ids = obj_ids if obj_ids is not None else self.obj_ids
        key = None if ids is None else tuple(int(i) for i in ids)
        if key not in self._models:
            self._models[key] = load_bop_models(self.models_dir, ids)
        return list(self._models[key])

    def __getstate__(self) -> dict:  # data-loader workers get the annotations, not the meshes read so far
        return {**self.__dict__, "_models": {}}

    @property
    def keypoints_path(self) -> Path:
        return self.models_dir / "keypoints.json"

    def load_keypoints(self) -> dict[int, np.ndarray]:
        """``{obj_id: (k, 3)}`` designated keypoints from ``<models_dir>/keypoints.json``."""
        from kpd6d.keypoints import load_keypoints

        if not self.keypoints_path.is_file():
            raise FileNotFoundError(
                f"{self.keypoints_path}: keypoints file does not exist (kpd6d-generate writes it; "
                "for another dataset run kpd6d-designate)"
            )
        kps = load_keypoints(self.keypoints_path)
        if self.obj_ids is not None:
            kps = {o: k for o, k in kps.items() if o in self.obj_ids}
        return kps


def _rgb_layout(sd: Path) -> tuple[Path, str]:
    """The image folder (rgb/ or gray/) and file extension of a scene (rgb/*.png when absent)."""
    for name in _RGB_DIRS:
        d = sd / name
        if d.is_dir():
            with os.scandir(d) as it:
                for entry in it:
                    ext = os.path.splitext(entry.name)[1].lower()
                    if ext in _RGB_EXTS:
                        return d, os.path.splitext(entry.name)[1]
            return d, ".png"
    return sd / "rgb", ".png"
