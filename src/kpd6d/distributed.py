"""Training across processes (Lightning DDP, ``trainer.strategy=ddp trainer.devices=N``; gloo on CPU).

What both stages need so that DDP gives the numbers one process gives:

* :class:`EvalShardSampler`: validation splits the samples across ranks **without padding** (rank r
  gets r, r + W, r + 2W, ...), so every sample is scored exactly once. Lightning's own
  ``DistributedSampler`` pads the last ranks with repeated samples, which changes the metrics.
  Lightning leaves a loader alone that already has a ``DistributedSampler``, which this is.
* :func:`all_reduce_sum` / :func:`all_gather_objects`: metric sums and lists of matched boxes
  reduced across ranks (identity in one process).
* The one writer of files (exported models, statistics, metrics.json) is rank 0: the stages ask
  their trainer (``trainer.is_global_zero``).

Rank and world size are read when needed (samplers are built before Lightning starts the process
group), from ``torch.distributed`` once it is initialised; before that every process is rank 0 of 1.

Layer: torch only; no stage package.
"""

from __future__ import annotations

from collections.abc import Iterator, Sized
from typing import Any

import torch
from torch.utils.data import DistributedSampler

__all__ = ["EvalShardSampler", "all_gather_objects", "all_reduce_sum", "rank_and_world"]


def _initialised() -> bool:
    return torch.distributed.is_available() and torch.distributed.is_initialized()


def rank_and_world() -> tuple[int, int]:
    """``(rank, world_size)`` of the running process group, ``(0, 1)`` when there is none."""
    if _initialised():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


def all_reduce_sum(values: torch.Tensor) -> torch.Tensor:
    """``values`` summed over all ranks (a new tensor; float64 sums stay float64; gloo reduces on CPU)."""
    out = values.detach().clone()
    if _initialised() and torch.distributed.get_world_size() > 1:
        dev = out.device
        if torch.distributed.get_backend() == "gloo" and dev.type != "cpu":
            out = out.cpu()
        torch.distributed.all_reduce(out, op=torch.distributed.ReduceOp.SUM)
        out = out.to(dev)
    return out


def all_gather_objects(obj: Any) -> list[Any]:
    """``[obj of rank 0, obj of rank 1, ...]`` (picklable objects); ``[obj]`` in one process."""
    if not (_initialised() and torch.distributed.get_world_size() > 1):
        return [obj]
    out: list[Any] = [None] * torch.distributed.get_world_size()
    torch.distributed.all_gather_object(out, obj)
    return out


class EvalShardSampler(DistributedSampler):
    """Sequential evaluation sampler: rank r of W yields ``r, r + W, ...`` of ``len(dataset)``, no
    padding, no shuffling (one process: every index in order). Ranks may get one sample more or less
    than each other; evaluation steps run no collective operation, so uneven shards are safe, and
    metric sums reduced at the epoch's end count each sample once."""

    def __init__(self, dataset: Sized) -> None:  # no super().__init__: it would read the rank now
        self.dataset = dataset
        self.shuffle = False
        self.drop_last = False
        self.seed = 0
        self.epoch = 0

    @property
    def rank(self) -> int:  # DistributedSampler's attributes, read when asked
        return rank_and_world()[0]

    @property
    def num_replicas(self) -> int:
        return rank_and_world()[1]

    @property
    def num_samples(self) -> int:
        return len(range(self.rank, len(self.dataset), self.num_replicas))

    @property
    def total_size(self) -> int:
        return len(self.dataset)

    def __iter__(self) -> Iterator[int]:
        return iter(range(self.rank, len(self.dataset), self.num_replicas))

    def __len__(self) -> int:
        return self.num_samples

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)
