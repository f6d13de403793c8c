"""``KPDModule``: the keypoint-detector LightningModule — the network, the heatmap loss and the
Lightning plumbing (training / validation steps, optimizers, inference on boxes).

What it shares with the crop dataset and inference — crop size, output stride, σ, crop scale and the
decoder — is one :class:`~kpd6d.kpd.codec.HeatmapCodec` (``codec=``; the separate ``input_size`` /
``out_stride`` / ``sigma`` / ``crop_scale`` / ``decoder`` arguments map onto one). Everything
inference needs is a constructor argument, recorded as the checkpoint's hyper-parameters
(:mod:`kpd6d.kpd.checkpoint`: the schema, reading, validating, older checkpoints), so
``KPDModule.load_checkpoint(path)`` rebuilds the module without any training config. The validation
pose metrics are :mod:`kpd6d.evaluation.kpd_metrics`.

No device-specific code: bf16 mixed precision and DDP are trainer settings.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pytorch_lightning as pl
import torch

from kpd6d.finetune import apply_freeze_stages, apply_train_mode, param_groups
from kpd6d.geometry import affine_apply, invert_affine
from kpd6d.io import to_plain
from kpd6d.kpd.checkpoint import kpd_hparams
from kpd6d.kpd.codec import HeatmapCodec, build_codec
from kpd6d.kpd.decoders import SoftArgmaxDecoder
from kpd6d.kpd.heads import KeypointNet
from kpd6d.kpd.heatmaps import crop_to_heatmap

__all__ = ["KPDModule"]

GROUPINGS = ("per_object", "shared")


class KPDModule(pl.LightningModule):
    """Heatmap keypoint detector for the objects ``obj_ids``.

    ``keypoints_3d``, ``diameters``, ``symmetric`` and ``model_points`` are lists aligned with
    ``obj_ids`` ((k, 3) mm, mm, bool, (P, 3) mm). ``grouping="per_object"`` gives one heatmap group
    per object (selected by the object's index), ``"shared"`` one group for all. ``codec`` is a
    :class:`~kpd6d.kpd.codec.HeatmapCodec` or its config (default: the paper's, subpixel decoding);
    ``input_size`` / ``out_stride`` / ``sigma`` / ``crop_scale`` / ``decoder`` are the older spelling
    of the same (None: not given).
    """

    def __init__(self, obj_ids: Sequence[int], keypoints_3d: Sequence, diameters: Sequence[float],
                 symmetric: Sequence[bool] | None = None, model_points: Sequence | None = None,
                 symmetries: Sequence[Mapping] | None = None,
                 backbone: Mapping | None = None, head: Mapping | None = None, grouping: str = "per_object",
                 input_size: int | None = None, out_stride: int | None = None, sigma: float | None = None,
                 crop_scale: float | None = None, decoder: Mapping | None = None, loss: Mapping | None = None,
                 optimizer: Mapping | None = None, scheduler: Mapping | None = None, augment: Mapping | None = None,
                 top_l: int | None = None, pnp: Mapping | None = None, channels_last: bool = True,
                 finetune: Mapping | None = None, codec: Mapping | HeatmapCodec | None = None) -> None:
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
        self.codec = build_codec(codec, what="KPDModule", input_size=input_size, out_stride=out_stride,
                                 sigma=sigma, crop_scale=crop_scale, decoder=decoder)
        self.save_hyperparameters(kpd_hparams(
            obj_ids=obj_ids, keypoints_3d=kps, diameters=diameters, symmetric=symmetric, model_points=model_points,
            symmetries=symmetries, backbone=backbone, head=head, grouping=grouping, codec=self.codec.config(),
            loss=loss, optimizer=optimizer, scheduler=scheduler, augment=augment, top_l=top_l, pnp=pnp,
            channels_last=channels_last, finetune=finetune,
        ))
        hp = self.hparams
        self.num_keypoints = kps[0].shape[0]
        self.net = KeypointNet(hp.backbone, hp.head, self.num_keypoints,
                               num_groups=n if grouping == "per_object" else 1, out_stride=self.codec.out_stride)
        # the checkpoint records the backbone's input normalisation, so it predicts the same even if a
        # default changes (and never needs the pretrained weights again: see load_checkpoint)
        hp.backbone = {**hp.backbone, "mean": self.net.mean.flatten().tolist(), "std": self.net.std.flatten().tolist()}
        apply_freeze_stages(self.net.backbone, hp.finetune["freeze_stages"])
        if hp.channels_last:  # NHWC convolutions: markedly faster on CPU (oneDNN), neutral elsewhere
            self.net.to(memory_format=torch.channels_last)
        self.augment = None
        if hp.augment:
            from kpd6d.kpd.augment import BatchAugment

            self.augment = BatchAugment(**hp.augment)
        lcfg = dict(hp.loss)
        self.visibility_weighted = bool(lcfg.pop("visibility_weighted", False))
        self.invisible_weight = float(lcfg.pop("invisible_weight", 0.0))
        self.loss_scale = float(lcfg.pop("scale", 1.0))
        self.coord_weight = float(lcfg.pop("coord_weight", 0.0))
        coord_window = lcfg.pop("coord_window", 2)
        if lcfg:
            raise ValueError(f"KPDModule: unknown loss option(s) {sorted(lcfg)}; known: visibility_weighted, "
                             "invisible_weight, scale, coord_weight, coord_window")
        if not (np.isfinite(self.coord_weight) and self.coord_weight >= 0):
            raise ValueError(f"KPDModule: loss.coord_weight must be a number >= 0, got {self.coord_weight}")
        if isinstance(coord_window, bool) or not isinstance(coord_window, int) or coord_window < 1:
            raise ValueError(f"KPDModule: loss.coord_window must be an integer >= 1 (heatmap px), got {coord_window!r}")
        self._coord_reader = SoftArgmaxDecoder(temperature=1.0, window=coord_window)
        self._obj_index = {o: i for i, o in enumerate(obj_ids)}
        self._pnp = None
        self._sym_cache: dict[int, Any] = {}  # object index -> symmetry transforms (validation's 2D error)

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
        return self.codec.heatmap_size

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
        """Load a checkpoint for inference (eval mode); no training config needed
        (:func:`kpd6d.kpd.checkpoint.load_kpd_module`: also checkpoints from before the codec)."""
        from kpd6d.kpd.checkpoint import load_kpd_module

        return load_kpd_module(cls, path, map_location=map_location)

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
        """The codec's target heatmaps of keypoints (B, k, 2) crop px."""
        return self.codec.encode(keypoints_crop)[0]

    def heatmap_loss(self, pred: torch.Tensor, target: torch.Tensor, visibility: torch.Tensor | None) -> torch.Tensor:
        """MSE over heatmap pixels (paper); visibility-weighted: invisible keypoints weigh ``invisible_weight``."""
        num, den = self._loss_terms(pred, target, visibility)
        return self.loss_scale * num / den.clamp(min=1.0)

    def _loss_terms(self, pred, target, visibility) -> tuple[torch.Tensor, torch.Tensor]:
        """The loss as (weighted sum of per-keypoint MSEs, sum of weights): sums over samples, so that
        validation can add them up across batches and processes."""
        se = (pred.float() - target.float()) ** 2
        per_kp = se.mean(dim=(-1, -2))  # (B, k)
        w = self._visibility_weights(visibility)
        if w is not None:
            return (per_kp * w).sum(), w.sum()
        return per_kp.sum(), per_kp.new_tensor(float(per_kp.numel()))

    def _visibility_weights(self, visibility: torch.Tensor | None) -> torch.Tensor | None:
        """Per-keypoint loss weights with ``visibility_weighted``: 1 visible, ``invisible_weight``
        invisible; None when the losses do not weigh by visibility."""
        if not self.visibility_weighted or visibility is None:
            return None
        v = visibility.float()
        return v + self.invisible_weight * (1 - v)

    def coordinate_loss_terms(self, pred: torch.Tensor, keypoints_crop: torch.Tensor, visibility: torch.Tensor | None,
                              sample_weight: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The coordinate loss (``loss.coord_weight``) as (weighted sum, sum of weights): the L1 distance
        (heatmap px) between the centroid of ``max(pred, 0)`` in a (2·``coord_window``+1)² window around
        each heatmap's maximum (the ``soft_argmax`` decoder; integral regression as in DSNT / Sun et
        al. 2018, differentiable in ``pred``) and ``keypoints_crop``. Keypoints outside the heatmap,
        which no centroid can reach, weigh 0; with ``visibility_weighted`` invisible ones weigh
        ``invisible_weight``; ``sample_weight`` (B,) scales each crop's (0: a negative crop). Inference
        decodes with the codec's decoder, whatever it is."""
        coords, _ = self._coord_reader(pred)
        target = crop_to_heatmap(keypoints_crop.float(), self.codec.out_stride)
        S = self.codec.heatmap_size
        w = ((target >= -0.5) & (target <= S - 0.5)).all(-1).float()
        vis_w = self._visibility_weights(visibility)
        if vis_w is not None:
            w = w * vis_w
        if sample_weight is not None:
            w = w * sample_weight[:, None].to(w.dtype)
        err = (coords - target).abs().sum(-1)
        return (err * w).sum(), w.sum()

    def decode(self, heatmaps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Heatmaps → (keypoints (B, k, 2) crop px, confidences (B, k)): the codec's decoding."""
        return self.codec.decode(heatmaps)

    # -- training --------------------------------------------------------------------------------
    def training_step(self, batch: Mapping[str, Any], batch_idx: int) -> torch.Tensor:
        images, kps, vis = batch["image"], batch["keypoints"], batch["visibility"]
        if self.augment is not None:
            images, moved, _ = self.augment(images, kps)
            if self.augment.geometric is not None:
                S = self.codec.input_size
                inside = ((moved >= -0.5) & (moved < S - 0.5)).all(-1)
                vis = vis * inside.to(vis.dtype)
                kps = moved
        target = batch["heatmaps"] if ("heatmaps" in batch and (self.augment is None or self.augment.geometric is None)) \
            else self.targets(kps)
        positive = None  # negative crops (kpd6d.kpd.crops): empty targets that count in full, no coordinates
        negative = batch.get("negative")
        negative = None if negative is None else torch.as_tensor(negative, dtype=target.dtype, device=target.device)
        if negative is not None and bool(negative.any()):
            positive = 1.0 - negative
            target = target * positive[:, None, None, None]
            vis = torch.where(positive[:, None] > 0, vis, torch.ones_like(vis))
        pred = self(images, batch["obj_index"])
        loss = self.heatmap_loss(pred, target, vis)
        if self.coord_weight > 0:
            num, den = self.coordinate_loss_terms(pred, kps, vis, positive)
            coord = num / den.clamp(min=1.0)
            self.log("train/coord_loss", coord, on_step=True, on_epoch=True, batch_size=images.shape[0])
            loss = loss + self.coord_weight * coord
        self.log("train/loss", loss, prog_bar=True, on_step=True, on_epoch=True, batch_size=images.shape[0])
        return loss

    #: validation sums, in this order (reduced across processes at the epoch's end)
    _VAL_SUMS = ("instances", "loss_num", "loss_den", "kp_err_px", "proj2d_acc_5px", "add_acc_0.1d", "pnp_fail_rate")

    def on_validation_epoch_start(self) -> None:
        self._val_sums = torch.zeros(len(self._VAL_SUMS), dtype=torch.float64)

    def validation_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        images = batch["image"]
        B = images.shape[0]
        pred = self(images, batch["obj_index"])
        target = batch["heatmaps"] if "heatmaps" in batch else self.targets(batch["keypoints"])
        num, den = self._loss_terms(pred, target, batch["visibility"])
        from kpd6d.evaluation.kpd_metrics import keypoint_error_px

        kp_crop, conf = self.decode(pred)
        kp_err, kp_img = keypoint_error_px(kp_crop, batch["affine"], batch["keypoints_image"])
        m = self.pose_metrics(kp_img, conf, batch["obj_id"], batch["K"], batch["R"], batch["t"])
        # per-sample means times B: sums over samples (every sample has the same k keypoints)
        self._val_sums += torch.tensor([B, float(num), float(den), float(kp_err) * B, m["proj2d_acc_5px"] * B,
                                        m["add_acc_0.1d"] * B, m["pnp_fail_rate"] * B], dtype=torch.float64)

    def on_validation_epoch_end(self) -> None:
        """Means over every validation sample, summed across processes first: the same figures in one
        process or under DDP (with :class:`kpd6d.distributed.EvalShardSampler`), for any batch size."""
        from kpd6d.distributed import all_reduce_sum

        s = dict(zip(self._VAL_SUMS, all_reduce_sum(self._val_sums).tolist()))
        n = max(s.pop("instances"), 1.0)
        num, den = s.pop("loss_num"), s.pop("loss_den")
        values = {"loss": self.loss_scale * num / max(den, 1.0), **{k: v / n for k, v in s.items()}}
        self.val_metrics = values
        for name, value in values.items():  # equal on every rank; sync_dist only keeps Lightning quiet
            self.log(f"val/{name}", float(value), prog_bar=name in ("loss", "kp_err_px", "proj2d_acc_5px"),
                     sync_dist=True)

    def pose_metrics(self, kp_img, conf, obj_ids, K, R_gt, t_gt) -> dict[str, float]:
        """top-l + PnP per instance (the checkpoint's ``pnp`` and ``top_l``) →
        :func:`kpd6d.evaluation.kpd_metrics.pose_metrics`: mean 2-D projection accuracy at 5 px (for
        symmetric objects the minimum over their symmetry transforms, as the evaluation's),
        ADD(-S) accuracy at 0.1 d, and the PnP failure rate (a failed PnP counts as a miss)."""
        from kpd6d.evaluation.kpd_metrics import pose_metrics
        from kpd6d.pnp.top_l import solve_top_l

        if self._pnp is None:
            from kpd6d.registry import PNP_SOLVERS, build_from_cfg

            self._pnp = build_from_cfg(PNP_SOLVERS, self.hparams.pnp)
        hp = self.hparams
        idx = self.obj_indices(obj_ids).tolist()
        kp3 = np.stack([np.asarray(hp.keypoints_3d[i], dtype=np.float64) for i in idx])
        Kn, Rg, tg = (x.detach().cpu().double().numpy() for x in (K, R_gt, t_gt))
        poses = solve_top_l(self._pnp, kp3, kp_img, Kn, conf.float(), l=hp.top_l)
        return pose_metrics(poses, Rg, tg, Kn, [self.surface_points(hp.obj_ids[i]) for i in idx],
                            [hp.symmetric[i] for i in idx], [hp.diameters[i] for i in idx],
                            [self._symmetry_transforms(i) for i in idx])

    def _symmetry_transforms(self, i: int):
        """(S, 4, 4) symmetry transforms of the checkpoint's i-th object for the symmetric 2D error
        (None: not symmetric, or a checkpoint without its symmetries)."""
        if i not in self._sym_cache:
            from kpd6d.evaluation.errors import symmetry_transforms

            hp = self.hparams
            sym = hp.symmetries[i] if hp.get("symmetries") is not None else None
            self._sym_cache[i] = symmetry_transforms(sym) if hp.symmetric[i] and sym else None
        return self._sym_cache[i]

    def configure_optimizers(self):
        from kpd6d.training import configure_optimization

        lr = dict(self.hparams.optimizer).get("lr", 1e-3)
        params = param_groups(self, self.net.backbone, lr, self.hparams.finetune["backbone_lr_mult"])
        return configure_optimization(params, self.hparams.optimizer, self.hparams.scheduler,
                                      total_steps=lambda: self.trainer.estimated_stepping_batches)

    def train(self, mode: bool = True):
        super().train(mode)
        if mode:
            apply_train_mode(self.net.backbone, self.hparams.finetune)  # keep the pretrained BatchNorm statistics
        return self

    def on_train_epoch_start(self) -> None:
        self.train()  # Lightning leaves the modules' modes as they are: finetune's frozen BatchNorm is applied here

    # -- inference -------------------------------------------------------------------------------
    @torch.no_grad()
    def predict_keypoints(self, images: torch.Tensor, boxes, image_index, obj_ids) -> tuple[torch.Tensor, torch.Tensor]:
        """Keypoints in image px for N boxes over a batch of B images.

        ``images`` (B, 3, H, W) float [0, 1]; ``boxes`` (N, 4) xywh px; ``image_index`` (N,) which image
        each box is in; ``obj_ids`` (N,). Crops are made on the images' device with kornia's
        ``warp_affine`` (the same affine as the training crops). Returns ``keypoints_2d`` (N, k, 2)
        image px and ``confidences`` (N, k).
        """
        from kpd6d.kpd.crops import inference_crops

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
        crops, A = inference_crops(images, boxes, image_index, self.codec)
        kp_crop, conf = self.decode(self(crops.to(images.dtype), oi))
        kp_img = affine_apply(invert_affine(A), kp_crop.double())
        return kp_img.to(images.dtype), conf.to(images.dtype)
