"""One training setup for both stages (``kpd6d-train stage=detector|kpd``, :mod:`kpd6d.workflow`).

* **Optimiser and scheduler** (one schema, both LightningModules' ``configure_optimizers``):
  ``optimizer: {name: adam|adamw|sgd|rmsprop, lr, <torch keyword arguments>}`` and
  ``scheduler: {name: ..., <arguments>}`` or null (constant learning rate). Scheduler names:
  torch's ``step``, ``multistep``, ``cosine``, ``exponential``, ``onecycle`` (``interval: epoch``
  by default, ``onecycle`` per step over the run's steps) and the step-wise factors
  ``cosine_steps`` (warm-up + cosine over the run's optimiser steps), ``cosine_time`` (warm-up +
  cosine over the wall-clock budget ``budget_s``, which :func:`resolve_scheduler` takes from
  ``trainer.max_time``; :class:`kpd6d.schedules.WarmupCosine`) and ``constant`` (linear warm-up,
  then constant). :func:`build_optimizer`, :func:`build_scheduler`, :func:`configure_optimization`.
* **Trainer** from one ``trainer:`` node (conf/trainer/default.yaml: Lightning ``Trainer``
  arguments; nulls mean Lightning's defaults) with the same callbacks for both stages: checkpoints
  ``checkpoints/best.ckpt`` (best monitored metric) and ``checkpoints/last.ckpt`` (resume point),
  progress bar, learning-rate monitor and the optional weight average (:mod:`kpd6d.ema`); TensorBoard
  (``tb/``) and CSV (``csv/``) loggers. :func:`build_trainer`, :func:`fit` (resumes from
  ``last.ckpt``).
* **Metrics file**: ``<run dir>/metrics.json`` in one format (:func:`write_metrics`).

Layer: may import torch, Lightning and the shared helpers (schedules, ema, finetune, config), never
a stage package (``kpd6d.kpd``, ``kpd6d.detection``).
"""

from __future__ import annotations

import inspect
import json
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

__all__ = [
    "CHECKPOINT_DIR",
    "OPTIMIZERS",
    "SCHEDULERS",
    "build_optimizer",
    "build_scheduler",
    "build_trainer",
    "check_optimizer",
    "configure_malloc",
    "configure_optimization",
    "ema_callbacks",
    "fit",
    "resolve_scheduler",
    "seed_and_threads",
    "write_metrics",
]

CHECKPOINT_DIR = "checkpoints"
#: step-wise factors of a ``LambdaLR`` (stepped every optimiser step)
_FACTOR_SCHEDULERS = ("constant", "cosine_steps", "cosine_time")
#: the run's optimiser steps when Lightning cannot tell (an infinite ``max_epochs`` with ``max_time``)
_UNKNOWN_TOTAL_STEPS = 100_000


def _torch_optimizers() -> dict[str, Callable]:
    import torch

    return {"adam": torch.optim.Adam, "adamw": torch.optim.AdamW, "sgd": torch.optim.SGD,
            "rmsprop": torch.optim.RMSprop}


def _torch_schedulers() -> dict[str, Callable]:
    import torch

    s = torch.optim.lr_scheduler
    return {"step": s.StepLR, "multistep": s.MultiStepLR, "cosine": s.CosineAnnealingLR,
            "exponential": s.ExponentialLR, "onecycle": s.OneCycleLR}


class _Table(Mapping):
    """A read-only name -> factory table filled on first use (keeps ``import kpd6d.training`` cheap)."""

    def __init__(self, fill: Callable[[], dict]) -> None:
        self._fill, self._data = fill, None

    def _get(self) -> dict:
        if self._data is None:
            self._data = self._fill()
        return self._data

    def __getitem__(self, key):
        return self._get()[key]

    def __iter__(self):
        return iter(self._get())

    def __len__(self) -> int:
        return len(self._get())


#: optimiser name -> torch class (``optimizer.name``)
OPTIMIZERS: Mapping[str, Callable] = _Table(_torch_optimizers)
#: torch scheduler name -> class (``scheduler.name``; plus the factors ``constant``, ``cosine_steps``, ``cosine_time``)
SCHEDULERS: Mapping[str, Callable] = _Table(_torch_schedulers)


# -- optimiser and scheduler ------------------------------------------------------------------------
def _optimizer_class(cfg: Mapping[str, Any]) -> tuple[str, Callable]:
    name = str(cfg.get("name", "adam")).lower()
    if name not in OPTIMIZERS:
        raise ValueError(f"unknown optimizer {name!r}; known: {', '.join(sorted(OPTIMIZERS))}")
    return name, OPTIMIZERS[name]


def check_optimizer(cfg: Mapping[str, Any] | None) -> dict[str, Any]:
    """``cfg`` as a dict, checked: an unknown name or setting raises ``ValueError`` listing the known ones."""
    cfg = dict(cfg or {})
    name, cls = _optimizer_class(cfg)
    known = [p for p in inspect.signature(cls).parameters if p != "params"]
    unknown = sorted(set(cfg) - {"name", *known})
    if unknown:
        raise ValueError(f"unknown optimizer setting(s) {unknown} for {name!r}; known: name, {', '.join(known)}")
    return cfg


def build_optimizer(params: Iterable, cfg: Mapping[str, Any] | None):
    """``torch.optim`` optimiser ``cfg["name"]`` (default adam) over ``params`` (tensors or parameter
    groups, e.g. :func:`kpd6d.finetune.param_groups`) with ``lr`` (default 1e-3) and the other keys
    as its keyword arguments."""
    cfg = check_optimizer(cfg)
    _, cls = _optimizer_class(cfg)
    cfg.pop("name", None)
    lr = cfg.pop("lr", 1e-3)
    return cls(params, lr=lr, **cfg)


def _total_steps(total_steps: int | float | Callable[[], int | float] | None, name: str) -> int:
    if callable(total_steps):
        total_steps = total_steps()
    if total_steps is None:
        raise ValueError(f"scheduler {name} needs the run's number of optimiser steps (total_steps)")
    if total_steps == float("inf"):
        return _UNKNOWN_TOTAL_STEPS
    return max(int(total_steps), 1)


def build_scheduler(optimizer, cfg: Mapping[str, Any] | None,
                    total_steps: int | float | Callable[[], int | float] | None = None) -> dict | None:
    """Lightning's ``lr_scheduler`` entry (``{"scheduler", "interval"}``) for ``cfg``, or None when
    ``cfg`` is null. ``total_steps`` (a number or a callable, called only when needed, e.g.
    ``lambda: self.trainer.estimated_stepping_batches``) is the run's number of optimiser steps."""
    import torch

    if not cfg:
        return None
    scfg = dict(cfg)
    name = scfg.pop("name", None)
    interval = scfg.pop("interval", "epoch")
    if name in _FACTOR_SCHEDULERS:
        warm = int(scfg.pop("warmup_steps", 0))
        if name == "constant":
            known = "warmup_steps"

            def factor(it: int) -> float:
                return min(1.0, (it + 1) / warm) if warm else 1.0
        else:
            from kpd6d.schedules import WarmupCosine

            floor = float(scfg.pop("min_factor", 0.02))
            known = "warmup_steps, min_factor"
            if name == "cosine_time":
                known += ", budget_s"
                budget = scfg.pop("budget_s", None)
                if not budget:
                    raise ValueError("scheduler cosine_time needs scheduler.budget_s (kpd6d-train fills it in from "
                                     "trainer.max_time)")
                factor = WarmupCosine(warm, floor, budget_s=float(budget))
            else:
                if scfg:
                    raise ValueError(f"scheduler {name}: unknown option(s) {sorted(scfg)}; known: {known}")
                factor = WarmupCosine(warm, floor, total_steps=_total_steps(total_steps, name))
        if scfg:
            raise ValueError(f"scheduler {name}: unknown option(s) {sorted(scfg)}; known: {known}")
        return {"scheduler": torch.optim.lr_scheduler.LambdaLR(optimizer, factor), "interval": "step"}
    if name not in SCHEDULERS:
        known = ", ".join(sorted([*SCHEDULERS, *_FACTOR_SCHEDULERS]))
        raise ValueError(f"unknown scheduler {name!r}; known: {known}")
    if name == "onecycle" and "total_steps" not in scfg:
        scfg["total_steps"] = _total_steps(total_steps, name)
        interval = "step"
    return {"scheduler": SCHEDULERS[name](optimizer, **scfg), "interval": interval}


def configure_optimization(params: Iterable, optimizer: Mapping[str, Any] | None, scheduler: Mapping[str, Any] | None,
                           total_steps: int | float | Callable[[], int | float] | None = None):
    """What a LightningModule's ``configure_optimizers`` returns: the optimiser alone (no scheduler)
    or ``{"optimizer", "lr_scheduler"}``."""
    opt = build_optimizer(params, optimizer)
    sched = build_scheduler(opt, scheduler, total_steps)
    return opt if sched is None else {"optimizer": opt, "lr_scheduler": sched}


def resolve_scheduler(scheduler: Mapping[str, Any] | None, trainer: Mapping[str, Any] | None,
                      where: str = "stage") -> dict | None:
    """``scheduler`` as a plain dict; ``cosine_time`` gets its ``budget_s`` from ``trainer.max_time``
    (``where`` names the config node in the error when neither is set)."""
    from kpd6d.io import to_plain

    scheduler = to_plain(scheduler)
    if scheduler and scheduler.get("name") == "cosine_time" and not scheduler.get("budget_s"):
        from kpd6d.schedules import parse_max_time

        scheduler["budget_s"] = parse_max_time((to_plain(trainer) or {}).get("max_time"))
        if not scheduler["budget_s"]:
            raise ValueError(f"{where}.scheduler cosine_time decays over the wall-clock budget: set "
                             f"{where}.trainer.max_time (e.g. 00:00:15:00) or {where}.scheduler.budget_s")
    return scheduler


# -- process setup ----------------------------------------------------------------------------------
#: the ``malloc`` settings: name -> (glibc's ``mallopt`` parameter (malloc.h), largest value in MiB: 32 is
#: ``DEFAULT_MMAP_THRESHOLD_MAX`` on 64-bit, and mallopt takes a C int of bytes)
_MALLOPT = {"mmap_threshold": (-3, 32), "trim_threshold": (-1, 2047)}


def configure_malloc(malloc: Mapping[str, Any] | None, where: str = "malloc") -> dict[str, int]:
    """Set glibc's allocator thresholds for this process (and the data-loader workers it forks later).

    ``malloc: {mmap_threshold_mb, trim_threshold_mb}`` (null or a missing key: glibc's default).
    By default glibc serves blocks >= 128 KiB (rising with use, up to 32 MiB) from fresh ``mmap``
    pages and returns the top of the heap to the kernel once 2 x that is free: a training step that
    allocates and frees hundreds of MiB of activations faults every page in again each step (about
    40,000 minor page faults per detector step on the LM-O recipe). ``mmap_threshold_mb: 32`` (the
    most glibc allows) and ``trim_threshold_mb: 1024`` keep the freed memory in the heap for the next
    step instead (1-2 faults per step). Measured: 1139 -> 961 ms per detector step in a step probe
    (session 28), no step-count gain visible in whole stages on a host whose speed drifts by more
    (session 29; docs/benchmarks.md): off by default. The same as the
    environment variable ``GLIBC_TUNABLES=glibc.malloc.mmap_threshold=33554432:glibc.malloc.trim_threshold=1073741824``.

    Returns what was set (``{"mmap_threshold": bytes, "trim_threshold": bytes}``; empty when
    nothing was asked). Raises ``ValueError`` naming the field for a value glibc refuses, and
    ``RuntimeError`` on a C library without ``mallopt`` (e.g. macOS, musl) when something was asked.
    """
    from kpd6d.config import to_float
    from kpd6d.io import to_plain

    cfg = to_plain(malloc) or {}
    known = [f"{name}_mb" for name in _MALLOPT]
    unknown = sorted(set(cfg) - set(known))
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; known: {', '.join(known)}")
    asked = {}
    for name, (param, limit) in _MALLOPT.items():
        key = f"{name}_mb"
        if cfg.get(key) is None:
            continue
        mb = to_float(cfg[key], f"{where}.{key}")
        if not 0 <= mb <= limit:
            raise ValueError(f"{where}.{key} must be in [0, {limit}] MiB, got {cfg[key]!r}")
        asked[name] = (param, int(mb * 2 ** 20))
    if not asked:
        return {}
    import ctypes
    import ctypes.util

    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError) as e:
        raise RuntimeError(f"{where}: this C library has no mallopt (glibc only); set {where} to null") from e
    for name, (param, value) in asked.items():
        if mallopt(ctypes.c_int(param), ctypes.c_int(value)) != 1:
            raise ValueError(f"{where}.{name}_mb: glibc's mallopt refused {value} bytes")
    return {name: value for name, (_, value) in asked.items()}


def seed_and_threads(seed: int, num_threads: int | None = None, malloc: Mapping[str, Any] | None = None,
                     where: str = "stage") -> None:
    """torch's intra-op threads (when given), the allocator's thresholds (:func:`configure_malloc`,
    ``<where>.malloc``) and every seed (Lightning's ``seed_everything``)."""
    import pytorch_lightning as pl
    import torch

    if num_threads:
        torch.set_num_threads(int(num_threads))
    done = configure_malloc(malloc, where=f"{where}.malloc")
    if done:
        print(f"{where}: glibc malloc " + ", ".join(f"{k} {v / 2 ** 20:g} MiB" for k, v in done.items()))
    pl.seed_everything(int(seed), workers=True)


# -- trainer ----------------------------------------------------------------------------------------
def build_trainer(run_dir: str | Path, trainer: Mapping[str, Any] | None, *, monitor: str, mode: str = "max",
                  ema_decay: float | None = None, progress_refresh: int = 1, log_versions: bool = True):
    """A Lightning ``Trainer`` from a ``trainer:`` node (nulls dropped: Lightning's defaults).

    Callbacks: the weight average (``ema_decay``, :func:`kpd6d.ema.ema_callback`), ``ModelCheckpoint`` s
    writing ``<run_dir>/checkpoints/best.ckpt`` (best ``monitor``, ``mode`` max|min;
    ``trainer.checkpoint_callback``) and ``last.ckpt`` (every epoch), a progress bar and a
    learning-rate monitor. Loggers: TensorBoard
    ``tb/`` and CSV ``csv/``, a new ``version_N`` per (re)start with ``log_versions`` (resuming keeps
    the earlier logs), else one folder (``csv/metrics.csv``).
    """
    import pytorch_lightning as pl
    from pytorch_lightning.callbacks import LearningRateMonitor, ModelCheckpoint, TQDMProgressBar
    from pytorch_lightning.loggers import CSVLogger, TensorBoardLogger

    from kpd6d.ema import ema_callback
    from kpd6d.io import to_plain

    run_dir = Path(run_dir)
    if mode not in ("max", "min"):
        raise ValueError(f"build_trainer: mode must be 'max' or 'min', got {mode!r}")
    kwargs = {k: v for k, v in (to_plain(trainer) or {}).items() if v is not None}
    callbacks = [
        *ema_callback(ema_decay),  # checkpoints then hold the weight average
        ModelCheckpoint(dirpath=run_dir / CHECKPOINT_DIR, filename="best", monitor=monitor, mode=mode, save_top_k=1),
        # every epoch, whether or not the monitored metric improved (Lightning's save_last only
        # follows a top-k save): the resume point
        ModelCheckpoint(dirpath=run_dir / CHECKPOINT_DIR, filename="last", monitor=None, save_top_k=1,
                        enable_version_counter=False),
        LearningRateMonitor(logging_interval="epoch"),
    ]
    if kwargs.get("enable_progress_bar", True):
        callbacks.append(TQDMProgressBar(refresh_rate=max(1, int(progress_refresh or 1))))
    version = None if log_versions else ""
    loggers = [TensorBoardLogger(str(run_dir), name="tb", version=version),
               CSVLogger(str(run_dir), name="csv", version=version)]
    return pl.Trainer(default_root_dir=str(run_dir), logger=loggers, callbacks=callbacks, **kwargs)


def fit(trainer, module, train_loader, val_loader=None, resume: bool = True, tag: str = "kpd6d-train") -> str | None:
    """``trainer.fit``, resuming from ``<run dir>/checkpoints/last.ckpt`` when ``resume`` and it exists;
    returns the checkpoint resumed from (or None)."""
    last = Path(trainer.default_root_dir) / CHECKPOINT_DIR / "last.ckpt"
    ckpt = str(last) if resume and last.is_file() else None
    if ckpt:
        print(f"{tag}: resuming from {ckpt}")
    trainer.fit(module, train_loader, val_loader, ckpt_path=ckpt)
    return ckpt


def ema_callbacks(trainer) -> list:
    """The trainer's weight-average callbacks (to write the average into the module for export)."""
    from kpd6d.ema import WeightEMA

    return [cb for cb in trainer.callbacks if isinstance(cb, WeightEMA)]


# -- metrics file -----------------------------------------------------------------------------------
def write_metrics(run_dir: str | Path, trainer, *, stage: str, t0: float, **fields: Any) -> dict:
    """Write ``<run_dir>/metrics.json`` (atomically) and return it: ``stage``, ``fields`` (stage
    specifics: data root, object ids, dataset sizes, ...), ``epochs``, ``global_step``,
    ``wall_time_s`` (since ``t0``), ``best_checkpoint``, ``best_<monitor>``, ``last_checkpoint`` and
    ``final_metrics`` (the trainer's last scalar metrics)."""
    from kpd6d.io import atomic_write_json

    run_dir = Path(run_dir)
    best = trainer.checkpoint_callback
    last = run_dir / CHECKPOINT_DIR / "last.ckpt"
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if hasattr(v, "item") and v.numel() == 1}
    summary = {
        "stage": stage,
        **fields,
        "epochs": int(trainer.current_epoch),
        "global_step": int(trainer.global_step),
        "wall_time_s": round(time.time() - t0, 1),
        "best_checkpoint": best.best_model_path or None,
        "best_" + best.monitor.replace("/", "_"): float(best.best_model_score)
        if best.best_model_score is not None else None,
        "last_checkpoint": str(last) if last.is_file() else None,
        "final_metrics": metrics,
    }
    atomic_write_json(run_dir / "metrics.json", summary)
    print(json.dumps({k: v for k, v in summary.items() if k != "final_metrics"}, indent=1, default=str))
    if metrics:
        print("final metrics: " + ", ".join(f"{k}={v:.4g}" for k, v in sorted(metrics.items())))
    return summary
