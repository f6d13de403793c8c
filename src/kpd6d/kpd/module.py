"""``KPDModule``: the keypoint-detector LightningModule (training, validation, inference).

Everything inference needs is a constructor argument, so Lightning stores it in the checkpoint's
hyper-parameters and ``KPDModule.load_checkpoint(path)`` rebuilds the module without any training
config: covered object ids, their 3-D keypoints, diameters, symmetries and sample points (for ADD(-S)
and 2-D projection metrics), input size, output stride, σ, crop scale, decoder, backbone and head.

No device-specific code: bf16 mixed precision and DDP are trainer settings.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytorch_lightning as pl
import torch

from kpd6d.config import to_plain
from kpd6d.finetune import apply_freeze_bn, finetune_config, param_groups
from kpd6d.geometry import affine_apply, box_to_crop_affine, invert_affine
from kpd6d.kpd.heads import KeypointNet
from kpd6d.kpd.heatmaps import crop_to_heatmap, gaussian_heatmaps, heatmap_to_crop

__all__ = ["KPDModule"]

GROUPINGS = ("per_object", "shared")


def _takes_pretrained(backbone_cfg: Mapping) -> bool:
    import inspect

    from kpd6d.registry import BACKBONES

    name = backbone_cfg.get("name")
    if "pretrained" in backbone_cfg:
        return True
    if name not in BACKBONES:
        return False
    try:
        return "pretrained" in inspect.signature(BACKBONES.get(name)).parameters
    except (TypeError, ValueError):
        return False


class KPDModule(pl.LightningModule):
    """Heatmap keypoint detector for the objects ``obj_ids``.

    ``keypoints_3d``, ``diameters``, ``symmetric`` and ``model_points`` are lists aligned with
    ``obj_ids`` ((k, 3) mm, mm, bool, (P, 3) mm). ``grouping="per_object"`` gives one heatmap group
    per object (selected by the object's index), ``"shared"`` one group for all.
    """

    def __init__(self, obj_ids: Sequence[int], keypoints_3d: Sequence, diameters: Sequence[float],
                 symmetric: Sequence[bool] | None = None, model_points: Sequence | None = None,
                 symmetries: Sequence[Mapping] | None = None,
                 backbone: Mapping | None = None, head: Mapping | None = None, grouping: str = "per_object",
                 input_size: int = 256, out_stride: int = 4, sigma: float = 2.0, crop_scale: float = 1.25,
                 decoder: Mapping | None = None, loss: Mapping | None = None, optimizer: Mapping | None = None,
                 scheduler: Mapping | None = None, augment: Mapping | None = None, top_l: int | None = None,
                 pnp: Mapping | None = None, channels_last: bool = True, finetune: Mapping | None = None) -> None:
        super().__init__()
        obj_ids = [int(o) for o in obj_ids]
        n = len(obj_ids)
        if n == 0:
            raise ValueError("KPDModule: obj_ids is empty")
        if grouping not in GROUPINGS:
            raise ValueError(f"KPDModule: grouping {grouping!r} unknown; known: {', '.join(GROUPINGS)}")
        kps = [np.asarray(k, dtype=np.float64) for k in keypoints_3d]
        if len(kps) != n or len(diameters) != n:
            raise ValueError(f"KPDModule: keypoints_3d ({len(kps)}) and diameters ({len(diameters)}) must have "
                             f"one entry per obj_id ({n})")
        ks = {o: k.shape for o, k in zip(obj_ids, kps)}
        if any(len(s) != 2 or s[1] != 3 for s in ks.values()) or len({s[0] for s in ks.values()}) != 1:
            raise ValueError(f"KPDModule: keypoints_3d must be (k, 3) with the same k for every object, got {ks}")
        if input_size % out_stride:
            raise ValueError(f"KPDModule: input_size {input_size} must be a multiple of out_stride {out_stride}")
        self.save_hyperparameters({
            "obj_ids": obj_ids, "keypoints_3d": to_plain(kps), "diameters": [float(d) for d in diameters],
            "symmetric": [bool(s) for s in (symmetric if symmetric is not None else [False] * n)],
            "model_points": to_plain(model_points) if model_points is not None else None,
            "symmetries": to_plain(symmetries) if symmetries is not None else None,
            "backbone": to_plain(backbone) or {"name": "resnet101"}, "head": to_plain(head) or {"name": "deconv"},
            "grouping": grouping, "input_size": int(input_size), "out_stride": int(out_stride),
            "sigma": float(sigma), "crop_scale": float(crop_scale),
            "decoder": to_plain(decoder) or {"name": "subpixel"},
            "loss": to_plain(loss) or {}, "optimizer": to_plain(optimizer) or {"name": "adam", "lr": 1e-3},
            "scheduler": to_plain(scheduler), "augment": to_plain(augment), "top_l": top_l,
            "pnp": to_plain(pnp) or {"name": "epnp"}, "channels_last": bool(channels_last),
            "finetune": finetune_config(to_plain(finetune), "KPDModule finetune"),
        })
        hp = self.hparams
        self.num_keypoints = kps[0].shape[0]
        self.net = KeypointNet(hp.backbone, hp.head, self.num_keypoints,
                               num_groups=n if grouping == "per_object" else 1, out_stride=hp.out_stride)
        # the checkpoint records the backbone's input normalisation, so it predicts the same even if a
        # default changes (and never needs the pretrained weights again: see load_checkpoint)
        hp.backbone = {**hp.backbone, "mean": self.net.mean.flatten().tolist(), "std": self.net.std.flatten().tolist()}
        if hp.channels_last:  # NHWC convolutions: markedly faster on CPU (oneDNN), neutral elsewhere
            self.net.to(memory_format=torch.channels_last)
        from kpd6d.registry import DECODERS, build_from_cfg

        self.decoder = build_from_cfg(DECODERS, hp.decoder)
        self.augment = None
        if hp.augment:
            from kpd6d.kpd.augment import BatchAugment

            self.augment = BatchAugment(**hp.augment)
        lcfg = dict(hp.loss)
        self.visibility_weighted = bool(lcfg.pop("visibility_weighted", False))
        self.invisible_weight = float(lcfg.pop("invisible_weight", 0.0))
        self.loss_scale = float(lcfg.pop("scale", 1.0))
        if lcfg:
            raise ValueError(f"KPDModule: unknown loss option(s) {sorted(lcfg)}; known: visibility_weighted, "
                             "invisible_weight, scale")
        self._obj_index = {o: i for i, o in enumerate(obj_ids)}
        self._pnp = None

    # -- what the checkpoint covers --------------------------------------------------------------
    @property
    def obj_ids(self) -> list[int]:
        return list(self.hparams.obj_ids)

    @property
    def keypoints_3d(self) -> dict[int, np.ndarray]:
        """obj_id → (k, 3) keypoints (model frame, mm)."""
        return {o: np.asarray(k, dtype=np.float64) for o, k in zip(self.hparams.obj_ids, self.hparams.keypoints_3d)}

    def surface_points(self, obj_id: int) -> np.ndarray:
        """(P, 3) points on the object's surface (model frame, mm): the model points the checkpoint
        carries for its metrics, else the keypoints."""
        i = self._obj_index[int(obj_id)]
        pts = self.hparams.model_points[i] if self.hparams.model_points is not None else self.hparams.keypoints_3d[i]
        return np.asarray(pts, dtype=np.float64)

    @property
    def heatmap_size(self) -> int:
        return self.hparams.input_size // self.hparams.out_stride

    @classmethod
    def from_models(cls, models: Sequence, keypoints_3d: Mapping[int, Any], num_points: int = 500,
                    **kwargs: Any) -> KPDModule:
        """Build from :class:`~kpd6d.objects.ObjectModel` s and ``{obj_id: (k, 3)}`` keypoints."""
        models = sorted(models, key=lambda m: m.obj_id)
        missing = [m.obj_id for m in models if m.obj_id not in keypoints_3d]
        if missing:
            raise KeyError(f"KPDModule.from_models: no keypoints for object(s) {missing}")
        return cls(
            obj_ids=[m.obj_id for m in models], keypoints_3d=[keypoints_3d[m.obj_id] for m in models],
            diameters=[m.diameter for m in models], symmetric=[m.is_symmetric for m in models],
            model_points=[m.sample_points(num_points, seed=0) for m in models],
            symmetries=[{"symmetries_discrete": [np.asarray(s).reshape(-1).tolist() for s in m.symmetries_discrete],
                         "symmetries_continuous": to_plain(m.symmetries_continuous)} for m in models],
            **kwargs,
        )

    @classmethod
    def load_checkpoint(cls, path: str | os.PathLike, map_location: Any = "cpu") -> KPDModule:
        """Load a checkpoint for inference (eval mode); no training config needed."""
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"KPD checkpoint {str(p)!r} does not exist")
        if p.stat().st_size == 0:
            raise ValueError(f"KPD checkpoint {str(p)!r} is empty (0 bytes): an interrupted copy or save?")
        try:
            ckpt = torch.load(str(p), map_location="cpu", weights_only=False)
        except Exception as exc:
            raise ValueError(f"KPD checkpoint {str(p)!r} cannot be read (truncated, or not a torch checkpoint): "
                             f"{type(exc).__name__}: {exc}") from exc
        if isinstance(ckpt, dict) and "kpd6d_detector" in ckpt:
            raise ValueError(f"{str(p)!r} is a detector checkpoint, not a KPD one: pass it as detector_ckpt "
                             "(kpd_ckpt takes kpd/checkpoints/best.ckpt of a KPD run)")
        hparams = ckpt.get("hyper_parameters") if isinstance(ckpt, dict) else None
        if not isinstance(hparams, Mapping) or not {"obj_ids", "keypoints_3d"} <= set(hparams) \
                or not isinstance(ckpt.get("state_dict"), Mapping):
            found = sorted(ckpt) if isinstance(ckpt, dict) else type(ckpt).__name__
            raise ValueError(f"{str(p)!r} is not a kpd6d KPD checkpoint (expected a Lightning checkpoint of KPDModule "
                             f"with hyper_parameters obj_ids / keypoints_3d and a state_dict; found {found})")
        extra = {}
        backbone = hparams.get("backbone")
        if isinstance(backbone, Mapping) and _takes_pretrained(backbone):
            # the weights are in the checkpoint: never consult a pretrained file or package again
            extra["backbone"] = {**dict(backbone), "pretrained": None}
        # built from the checkpoint already read (Lightning's load_from_checkpoint would read the file again)
        module = cls(**{**dict(hparams), **extra})
        try:
            module.load_state_dict(ckpt["state_dict"])
        except RuntimeError as exc:  # weights that do not fit the recorded network
            raise ValueError(f"KPD checkpoint {str(p)!r}: its weights do not fit the network its hyper-parameters "
                             f"describe: {exc}") from exc
        if isinstance(map_location, (str, torch.device)):
            module.to(map_location)
        return module.eval()

    def obj_indices(self, obj_ids) -> torch.Tensor:
        ids = obj_ids.tolist() if isinstance(obj_ids, torch.Tensor) else list(obj_ids)
        unknown = sorted({int(o) for o in ids} - set(self._obj_index))
        if unknown:
            raise KeyError(f"KPD model does not cover object(s) {unknown}; it covers {self.obj_ids}")
        return torch.tensor([self._obj_index[int(o)] for o in ids], dtype=torch.long, device=self.device)

    # -- network ---------------------------------------------------------------------------------
    def forward(self, images: torch.Tensor, obj_index: torch.Tensor | None = None) -> torch.Tensor:
        """Crops (B, 3, S, S) in [0, 1] → heatmaps (B, k, S/s, S/s) of each sample's object group."""
        if self.hparams.get("channels_last", False):
            images = images.contiguous(memory_format=torch.channels_last)
        return self.net.select(self.net(images), obj_index)

    def targets(self, keypoints_crop: torch.Tensor) -> torch.Tensor:
        return gaussian_heatmaps(crop_to_heatmap(keypoints_crop.float(), self.hparams.out_stride),
                                 self.heatmap_size, self.hparams.sigma)

    def heatmap_loss(self, pred: torch.Tensor, target: torch.Tensor, visibility: torch.Tensor | None) -> torch.Tensor:
        """MSE over heatmap pixels (paper); visibility-weighted: invisible keypoints weigh ``invisible_weight``."""
        se = (pred.float() - target.float()) ** 2
        per_kp = se.mean(dim=(-1, -2))  # (B, k)
        if self.visibility_weighted and visibility is not None:
            w = visibility.float() + self.invisible_weight * (1 - visibility.float())
            return self.loss_scale * (per_kp * w).sum() / w.sum().clamp(min=1.0)
        return self.loss_scale * per_kp.mean()

    def decode(self, heatmaps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Heatmaps → (keypoints (B, k, 2) crop px, confidences (B, k))."""
        coords, conf = self.decoder(heatmaps.float())
        return heatmap_to_crop(coords, self.hparams.out_stride), conf

    # -- training --------------------------------------------------------------------------------
    def training_step(self, batch: Mapping[str, Any], batch_idx: int) -> torch.Tensor:
        images, kps, vis = batch["image"], batch["keypoints"], batch["visibility"]
        if self.augment is not None:
            images, moved, _ = self.augment(images, kps)
            if self.augment.geometric is not None:
                S = self.hparams.input_size
                inside = ((moved >= -0.5) & (moved < S - 0.5)).all(-1)
                vis = vis * inside.to(vis.dtype)
                kps = moved
        target = batch["heatmaps"] if ("heatmaps" in batch and (self.augment is None or self.augment.geometric is None)) \
            else self.targets(kps)
        pred = self(images, batch["obj_index"])
        loss = self.heatmap_loss(pred, target, vis)
        self.log("train/loss", loss, prog_bar=True, on_step=True, on_epoch=True, batch_size=images.shape[0])
        return loss

    def validation_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        images = batch["image"]
        B = images.shape[0]
        pred = self(images, batch["obj_index"])
        target = batch["heatmaps"] if "heatmaps" in batch else self.targets(batch["keypoints"])
        self.log("val/loss", self.heatmap_loss(pred, target, batch["visibility"]), prog_bar=True, batch_size=B,
                 sync_dist=True)
        kp_crop, conf = self.decode(pred)
        kp_img = affine_apply(invert_affine(batch["affine"].double()), kp_crop.double())
        kp_err = (kp_img - batch["keypoints_image"].double()).norm(dim=-1).mean()
        self.log("val/kp_err_px", kp_err.float(), prog_bar=True, batch_size=B, sync_dist=True)
        m = self.pose_metrics(kp_img, conf, batch["obj_id"], batch["K"], batch["R"], batch["t"])
        for name, value in m.items():
            self.log(f"val/{name}", value, prog_bar=name == "proj2d_acc_5px", batch_size=B, sync_dist=True)

    def pose_metrics(self, kp_img, conf, obj_ids, K, R_gt, t_gt) -> dict[str, float]:
        """top-l + PnP per instance → mean 2-D projection accuracy at 5 px, ADD(-S) accuracy at 0.1 d,
        and the PnP failure rate (a failed PnP counts as a miss)."""
        from kpd6d.evaluation.errors import add_error, adds_error, proj2d_error
        from kpd6d.kpd.select import solve_top_l

        if self._pnp is None:
            from kpd6d.registry import PNP_SOLVERS, build_from_cfg

            self._pnp = build_from_cfg(PNP_SOLVERS, self.hparams.pnp)
        hp = self.hparams
        idx = self.obj_indices(obj_ids).tolist()
        kp3 = np.stack([np.asarray(hp.keypoints_3d[i], dtype=np.float64) for i in idx])
        Kn, Rg, tg = (x.detach().cpu().double().numpy() for x in (K, R_gt, t_gt))
        poses = solve_top_l(self._pnp, kp3, kp_img, Kn, conf.float(), l=hp.top_l)
        hit2d, hitadd, fail = [], [], []
        for j, (i, est) in enumerate(zip(idx, poses)):
            if not est.ok:
                hit2d.append(0.0)
                hitadd.append(0.0)
                fail.append(1.0)
                continue
            pts = np.asarray(hp.model_points[i] if hp.model_points is not None else hp.keypoints_3d[i], dtype=np.float64)
            Re, te = np.asarray(est.R, dtype=np.float64), np.asarray(est.t, dtype=np.float64)
            e2d = proj2d_error(Re, te, Rg[j], tg[j], pts, Kn[j])
            ead = (adds_error if hp.symmetric[i] else add_error)(Re, te, Rg[j], tg[j], pts)
            hit2d.append(float(e2d < 5.0))
            hitadd.append(float(ead < 0.1 * hp.diameters[i]))
            fail.append(0.0)
        return {"proj2d_acc_5px": float(np.mean(hit2d)), "add_acc_0.1d": float(np.mean(hitadd)),
                "pnp_fail_rate": float(np.mean(fail))}

    def configure_optimizers(self):
        from kpd6d.training import configure_optimization

        lr = dict(self.hparams.optimizer).get("lr", 1e-3)
        params = param_groups(self, self.net.backbone, lr, self.hparams.finetune["backbone_lr_mult"])
        return configure_optimization(params, self.hparams.optimizer, self.hparams.scheduler,
                                      total_steps=lambda: self.trainer.estimated_stepping_batches)

    def train(self, mode: bool = True):
        super().train(mode)
        if mode and self.hparams.finetune["freeze_bn"]:
            apply_freeze_bn(self.net.backbone)  # keep the pretrained BatchNorm statistics
        return self

    # -- inference -------------------------------------------------------------------------------
    @torch.no_grad()
    def predict_keypoints(self, images: torch.Tensor, boxes, image_index, obj_ids) -> tuple[torch.Tensor, torch.Tensor]:
        """Keypoints in image px for N boxes over a batch of B images.

        ``images`` (B, 3, H, W) float [0, 1]; ``boxes`` (N, 4) xywh px; ``image_index`` (N,) which image
        each box is in; ``obj_ids`` (N,). Crops are made on the images' device with kornia's
        ``warp_affine`` (the same affine as the training crops). Returns ``keypoints_2d`` (N, k, 2)
        image px and ``confidences`` (N, k).
        """
        from kornia.geometry.transform import warp_affine

        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"predict_keypoints: images must be (B, 3, H, W), got {tuple(images.shape)}")
        dev = self.device
        images = images.to(dev)
        boxes = torch.as_tensor(boxes, dtype=torch.float64, device=dev).reshape(-1, 4)
        image_index = torch.as_tensor(image_index, dtype=torch.long, device=dev).reshape(-1)
        N = boxes.shape[0]
        if len(image_index) != N or len(obj_ids) != N:
            raise ValueError(f"predict_keypoints: {N} boxes but {len(image_index)} image indices and "
                             f"{len(obj_ids)} obj_ids")
        k = self.num_keypoints
        if N == 0:
            return images.new_zeros(0, k, 2), images.new_zeros(0, k)
        if (image_index < 0).any() or (image_index >= images.shape[0]).any():
            raise ValueError(f"predict_keypoints: image_index out of range [0, {images.shape[0]})")
        oi = self.obj_indices(obj_ids)
        S = self.hparams.input_size
        A = box_to_crop_affine(boxes, S, scale=self.hparams.crop_scale)
        crops = warp_affine(images[image_index].float(), A.float(), (S, S), align_corners=True)
        kp_crop, conf = self.decode(self(crops.to(images.dtype), oi))
        kp_img = affine_apply(invert_affine(A), kp_crop.double())
        return kp_img.to(images.dtype), conf.to(images.dtype)
