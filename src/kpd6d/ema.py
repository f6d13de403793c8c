"""Exponential moving average of the weights (Polyak averaging), shared by the detector and KPD stages.

:class:`WeightEMA` is a Lightning callback. After every optimiser step it moves an average of the
module's floating-point state (parameters and BatchNorm statistics) towards the current values,
``ema <- d * ema + (1 - d) * w`` with ``d = min(decay, (1 + n) / (10 + n))`` after ``n`` updates (the
ramp keeps the early average from being dominated by the random initialisation). The average, not
the last step's weights, is what validation measures, what every checkpoint's ``state_dict`` holds
(so ``best.ckpt`` and the exported detector are the averaged network) and what :meth:`apply_to`
writes into the module at the end of training. The raw weights travel in the callback's own state,
so a resumed run continues from the raw weights with its average intact.

Short, capped CPU runs with a constant learning rate gain most from it: the average removes the
step-to-step noise that a decaying learning rate would otherwise remove (measured in
docs/benchmarks.md).
"""

from __future__ import annotations

from typing import Any

import pytorch_lightning as pl
import torch

__all__ = ["WeightEMA", "ema_callback"]


def _float_state(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v for k, v in module.state_dict().items() if torch.is_floating_point(v)}


def _float_copy(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in _float_state(module).items()}


class WeightEMA(pl.Callback):
    """See the module docstring. ``decay`` in (0, 1): about ``1 / (1 - decay)`` steps are averaged."""

    def __init__(self, decay: float = 0.998) -> None:
        if not 0.0 < float(decay) < 1.0:
            raise ValueError(f"WeightEMA: decay must lie in (0, 1), got {decay!r}")
        self.decay = float(decay)
        self.num_updates = 0
        self.ema: dict[str, torch.Tensor] | None = None
        self._raw: dict[str, torch.Tensor] | None = None  # the training weights while the average is swapped in
        self._resume_raw: dict[str, torch.Tensor] | None = None
        self._module: pl.LightningModule | None = None

    # -- the average -------------------------------------------------------------------------------
    def current_decay(self) -> float:
        return min(self.decay, (1.0 + self.num_updates) / (10.0 + self.num_updates))

    @torch.no_grad()
    def update(self, module: torch.nn.Module) -> None:
        """One averaging step towards ``module``'s current floating-point state."""
        cur = _float_state(module)
        if self.ema is None or self.ema.keys() != cur.keys():
            self.ema = _float_copy(module)
            self.num_updates = 0
            return
        self.num_updates += 1
        w = 1.0 - self.current_decay()
        keys = list(cur)
        torch._foreach_lerp_([self.ema[k] for k in keys], [cur[k].detach() for k in keys], w)

    @torch.no_grad()
    def apply_to(self, module: torch.nn.Module) -> None:
        """Write the average into ``module`` (for export after training); the raw weights are dropped."""
        if self.ema is not None:
            self._copy_into(module, self.ema)
        self._raw = None

    @staticmethod
    @torch.no_grad()
    def _copy_into(module: torch.nn.Module, values: dict[str, torch.Tensor]) -> None:
        state = module.state_dict()
        for k, v in values.items():
            state[k].copy_(v)

    def _swap_in(self, module: torch.nn.Module) -> None:
        if self.ema is None or self._raw is not None:
            return
        self._raw = _float_copy(module)
        self._copy_into(module, self.ema)

    def _swap_out(self, module: torch.nn.Module) -> None:
        if self._raw is not None:
            self._copy_into(module, self._raw)
            self._raw = None

    # -- Lightning hooks ---------------------------------------------------------------------------
    def on_fit_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._module = pl_module
        if self._resume_raw is not None:  # resumed: the module holds the checkpoint's average
            self.ema = _float_copy(pl_module)
            self._copy_into(pl_module, {k: v.to(self.ema[k].device) for k, v in self._resume_raw.items()})
            self._resume_raw = None
        elif self.ema is None:
            self.update(pl_module)

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self._swap_out(pl_module)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.update(pl_module)

    def on_validation_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        # swapped back at the next training batch: the checkpoint callbacks, which run after this
        # one, save the averaged weights that were just validated
        self._swap_in(pl_module)

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._swap_out(pl_module)

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: dict[str, Any]) -> None:
        if self.ema is None:
            return
        checkpoint["state_dict"] = {**checkpoint["state_dict"], **self.ema}  # serialised at once: no copy needed

    def state_dict(self) -> dict[str, Any]:
        raw = self._raw
        if raw is None and self._module is not None:
            raw = _float_state(self._module)
        return {"decay": self.decay, "num_updates": self.num_updates,
                "raw": {k: v.detach().cpu().clone() for k, v in raw.items()} if raw is not None else None}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.num_updates = int(state_dict.get("num_updates", 0))
        self._resume_raw = state_dict.get("raw")


def ema_callback(decay: float | None) -> list[WeightEMA]:
    """``[WeightEMA(decay)]``, or ``[]`` when ``decay`` is None / 0 (averaging off)."""
    if decay is None or float(decay) == 0.0:
        return []
    return [WeightEMA(float(decay))]
