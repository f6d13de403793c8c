"""BOP datasets: the reader (:class:`BopDataset`, :class:`Frame`, :class:`Instance`) and the BOP
JSON / image readers and atomic writers (:mod:`kpd6d.data.bop_io`) -- the one place for BOP I/O."""

from kpd6d.data.bop_io import (
    BopFormatError,
    atomic_write_bytes,
    atomic_write_image,
    atomic_write_json,
    atomic_write_text,
    bbox_from_mask,
    load_camera,
    load_scene_camera,
    load_scene_gt,
    load_scene_gt_info,
    load_targets,
    read_image,
    read_json,
    save_camera,
    save_scene_camera,
    save_scene_gt,
    save_scene_gt_info,
)
from kpd6d.data.dataset import BopDataset, Frame, Instance

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
