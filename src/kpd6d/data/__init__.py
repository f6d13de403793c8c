"""BOP datasets: the reader (:class:`BopDataset`, :class:`Frame`, :class:`Instance`) and the BOP
JSON readers and writers (:mod:`kpd6d.data.bop_io`) -- the one place for BOP formats. The generic
file helpers (atomic writes, ``read_json``, ``read_image``) are :mod:`kpd6d.io`; they are
re-exported here so old imports keep working."""

from kpd6d.data.bop_io import (
    BopFormatError,
    bbox_from_mask,
    load_camera,
    load_scene_camera,
    load_scene_gt,
    load_scene_gt_info,
    load_targets,
    save_camera,
    save_scene_camera,
    save_scene_gt,
    save_scene_gt_info,
)
from kpd6d.data.dataset import BopDataset, Frame, Instance
from kpd6d.io import (
    atomic_write_bytes,
    atomic_write_image,
    atomic_write_json,
    atomic_write_text,
    read_image,
    read_json,
)

__all__ = [
    "BopDataset",
    "BopFormatError",
    "Frame",
    "Instance",
    "atomic_write_bytes",
    "atomic_write_image",
    "atomic_write_json",
    "atomic_write_text",
    "bbox_from_mask",
    "load_camera",
    "load_scene_camera",
    "load_scene_gt",
    "load_scene_gt_info",
    "load_targets",
    "read_image",
    "read_json",
    "save_camera",
    "save_scene_camera",
    "save_scene_gt",
    "save_scene_gt_info",
]
