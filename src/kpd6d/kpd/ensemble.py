"""One KPD network per object behind the one-network interface (``kpd6d-run kpd_networks=per_object``).

:class:`KPDEnsemble` holds a :class:`~kpd6d.kpd.module.KPDModule` per object and answers the KPD
contract the pipelines use (``predict_keypoints``, ``keypoints_3d``, ``surface_points``) by sending
each box to its object's network. Every member must give the same number of keypoints (the pipeline
solves PnP over one (N, k) batch).

On disk an ensemble is a manifest (``networks.json``, written by :func:`write_manifest`)::

    {"format": "kpd6d-kpd-networks", "version": 1,
     "members": {"1": "obj_000001/checkpoints/best.ckpt", ...}}   # paths relative to the manifest

A member may also be a list of checkpoints trained for the same keypoints: :class:`KPDAverage` runs
them all on each box and takes each keypoint's coordinate-wise median (the mean of two) and its mean
confidence, as test-time crops are combined. A checkpoint named under several objects is loaded once.

:func:`load_kpd` loads either a KPD checkpoint or such a manifest: every place that takes
``kpd_ckpt`` takes both.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["MANIFEST_FORMAT", "KPDAverage", "KPDEnsemble", "is_manifest", "load_kpd", "read_manifest", "write_manifest"]

MANIFEST_FORMAT = "kpd6d-kpd-networks"


class KPDEnsemble(torch.nn.Module):
    """``members``: obj_id -> a KPD module that covers that object (it may cover more; only its
    object's boxes are sent to it)."""

    def __init__(self, members: Mapping[int, Any]) -> None:
        super().__init__()
        if not members:
            raise ValueError("KPDEnsemble needs at least one member network")
        ks = {}
        for oid, m in members.items():
            if int(oid) not in {int(o) for o in m.keypoints_3d}:
                raise ValueError(f"KPDEnsemble: the network given for object {oid} does not cover it "
                                 f"(it covers {sorted(int(o) for o in m.keypoints_3d)})")
            ks[int(oid)] = int(np.asarray(m.keypoints_3d[int(oid)]).reshape(-1, 3).shape[0])
        if len(set(ks.values())) > 1:
            raise ValueError(f"KPDEnsemble: every object needs the same number of keypoints (the pipeline solves "
                             f"PnP over one (N, k) batch); got {ks}")
        self.obj_ids = sorted(ks)
        self.num_keypoints = next(iter(ks.values()))
        self.members = torch.nn.ModuleDict({str(o): members[o] for o in self.obj_ids})
        self._keypoints_3d = {o: np.asarray(members[o].keypoints_3d[o], dtype=np.float64) for o in self.obj_ids}

    @property
    def device(self) -> torch.device:
        return next(iter(self.members.values())).device

    @property
    def keypoints_3d(self) -> dict[int, np.ndarray]:
        """obj_id -> (k, 3) keypoints (model frame, mm), each from its object's network."""
        return self._keypoints_3d

    def member(self, obj_id: int):
        key = str(int(obj_id))
        if key not in self.members:
            raise KeyError(f"KPD networks do not cover object {int(obj_id)}; they cover {self.obj_ids}")
        return self.members[key]

    def surface_points(self, obj_id: int) -> np.ndarray:
        return self.member(obj_id).surface_points(int(obj_id))

    @torch.no_grad()
    def predict_keypoints(self, images: torch.Tensor, boxes, image_index, obj_ids) -> tuple[torch.Tensor, torch.Tensor]:
        """As :meth:`kpd6d.kpd.module.KPDModule.predict_keypoints`: (N, k, 2) image px and (N, k)
        confidences, each box's from its object's network, in the order of the boxes."""
        obj = torch.as_tensor(obj_ids, dtype=torch.long).reshape(-1)
        boxes = torch.as_tensor(boxes, dtype=torch.float32).reshape(-1, 4)
        idx = torch.as_tensor(image_index, dtype=torch.long).reshape(-1)
        n = int(obj.numel())
        kp = torch.zeros((n, self.num_keypoints, 2), dtype=torch.float32, device=images.device)
        conf = torch.zeros((n, self.num_keypoints), dtype=torch.float32, device=images.device)
        for oid in torch.unique(obj.cpu()).tolist():
            m = obj == oid
            p, c = self.member(oid).predict_keypoints(images, boxes[m], idx[m], obj[m])
            kp[m.to(kp.device)] = torch.as_tensor(p).float().to(kp.device)
            conf[m.to(conf.device)] = torch.as_tensor(c).float().to(conf.device)
        return kp, conf


class KPDAverage(torch.nn.Module):
    """Several KPD networks for the same objects and keypoints behind the one-network interface: each
    keypoint is the coordinate-wise median of the networks' estimates, its confidence their mean."""

    def __init__(self, members) -> None:
        super().__init__()
        members = list(members)
        if not members:
            raise ValueError("KPDAverage needs at least one network")
        first = members[0].keypoints_3d
        for i, m in enumerate(members[1:], 1):
            kp = m.keypoints_3d
            if sorted(int(o) for o in kp) != sorted(int(o) for o in first) or any(
                    np.asarray(kp[o]).shape != np.asarray(first[o]).shape
                    or not np.allclose(np.asarray(kp[o], dtype=np.float64), np.asarray(first[o], dtype=np.float64),
                                       atol=1e-6) for o in first):
                raise ValueError(f"KPDAverage: network {i} does not have network 0's objects and keypoints "
                                 f"(objects {sorted(int(o) for o in kp)} vs {sorted(int(o) for o in first)}); "
                                 "only networks trained for the same keypoints can be averaged")
        self.nets = torch.nn.ModuleList(members)
        self.num_keypoints = members[0].num_keypoints

    @property
    def device(self) -> torch.device:
        return self.nets[0].device

    @property
    def keypoints_3d(self) -> dict[int, np.ndarray]:
        return self.nets[0].keypoints_3d

    def surface_points(self, obj_id: int) -> np.ndarray:
        return self.nets[0].surface_points(int(obj_id))

    @torch.no_grad()
    def predict_keypoints(self, images: torch.Tensor, boxes, image_index, obj_ids) -> tuple[torch.Tensor, torch.Tensor]:
        """As :meth:`kpd6d.kpd.module.KPDModule.predict_keypoints`, combined over the networks."""
        outs = [m.predict_keypoints(images, boxes, image_index, obj_ids) for m in self.nets]
        kp = torch.stack([torch.as_tensor(p) for p, _ in outs])
        conf = torch.stack([torch.as_tensor(c) for _, c in outs])
        return torch.quantile(kp.double(), 0.5, dim=0).to(kp.dtype), conf.mean(dim=0)


def is_manifest(path: str | os.PathLike) -> bool:
    """True when ``path`` names a KPD networks manifest (a ``.json`` file), not a checkpoint."""
    return str(path).lower().endswith(".json")


def write_manifest(path: str | os.PathLike, members: Mapping[int, Any]) -> Path:
    """Write ``networks.json`` atomically; ``members``: obj_id -> a checkpoint path, or a list of them
    (averaged, :class:`KPDAverage`); paths are stored relative to the manifest's folder."""
    from kpd6d.io import atomic_write_text

    path = Path(path)

    def rel_path(p):
        return os.path.relpath(Path(p), path.parent)

    rel = {str(int(o)): rel_path(p) if isinstance(p, str | os.PathLike) else [rel_path(q) for q in p]
           for o, p in sorted(members.items())}
    atomic_write_text(path, json.dumps({"format": MANIFEST_FORMAT, "version": 1, "members": rel}, indent=1))
    return path


def read_manifest(path: str | os.PathLike) -> dict[int, Path | list[Path]]:
    """obj_id -> checkpoint path (or list of paths: networks averaged) of a manifest; errors name the
    file and what is wrong."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"KPD networks manifest {str(p)!r} does not exist")
    try:
        doc = json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"KPD networks manifest {str(p)!r} is not valid JSON: {exc}") from exc
    if not isinstance(doc, dict) or doc.get("format") != MANIFEST_FORMAT or not isinstance(doc.get("members"), dict) \
            or not doc["members"]:
        raise ValueError(f"{str(p)!r} is not a KPD networks manifest (expected {{\"format\": \"{MANIFEST_FORMAT}\", "
                         f"\"members\": {{obj_id: checkpoint}}}}, one or more members)")
    out = {}
    for key, rel in doc["members"].items():
        try:
            oid = int(key)
        except ValueError:
            raise ValueError(f"KPD networks manifest {str(p)!r}: member key {key!r} is not an object id") from None
        paths = rel if isinstance(rel, list) else [rel]
        if not paths or not all(isinstance(r, str) for r in paths):
            raise ValueError(f"KPD networks manifest {str(p)!r}: object {oid}'s member must be a checkpoint path "
                             f"or a non-empty list of them, got {rel!r}")
        resolved = [(p.parent / r).resolve() for r in paths]
        out[oid] = resolved if isinstance(rel, list) else resolved[0]
    return out


def load_kpd(path: str | os.PathLike, map_location: Any = "cpu"):
    """A KPD checkpoint (:class:`~kpd6d.kpd.module.KPDModule`) or a networks manifest
    (:class:`KPDEnsemble`), ready for inference."""
    from kpd6d.kpd.module import KPDModule

    if not is_manifest(path):
        return KPDModule.load_checkpoint(path, map_location=map_location)
    members, loaded, averages = {}, {}, {}
    for o, cks in read_manifest(path).items():
        cks = tuple(cks) if isinstance(cks, list) else (cks,)
        for ck in cks:
            if ck not in loaded:
                try:
                    loaded[ck] = KPDModule.load_checkpoint(ck, map_location=map_location)
                except (FileNotFoundError, ValueError) as exc:
                    raise type(exc)(f"KPD networks manifest {str(path)!r}, object {o}: {exc}") from exc
        if len(cks) > 1 and cks not in averages:
            try:
                averages[cks] = KPDAverage([loaded[ck] for ck in cks])
            except ValueError as exc:
                raise ValueError(f"KPD networks manifest {str(path)!r}, object {o}: {exc}") from None
        members[o] = averages[cks] if len(cks) > 1 else loaded[cks[0]]
    return KPDEnsemble(members).eval()
