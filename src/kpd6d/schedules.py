"""Learning-rate schedules shared by the detector and KPD stages.

:class:`WarmupCosine` is a ``LambdaLR`` factor: a linear warm-up over ``warmup_steps`` steps, then a
cosine decay from 1 to ``min_factor`` over either ``total_steps`` optimiser steps or a wall-clock
budget of ``budget_s`` seconds. The wall-clock form fits capped CPU runs (Lightning ``max_time``),
where the number of steps is not known in advance: the learning rate reaches its floor exactly when
the budget runs out. It is a callable object, so ``LambdaLR.state_dict`` saves its elapsed time and a
resumed run continues the decay where it stopped.
"""

from __future__ import annotations

import math
import time

__all__ = ["WarmupCosine", "parse_max_time"]


class WarmupCosine:
    """``factor(step)`` for ``torch.optim.lr_scheduler.LambdaLR`` (see the module docstring)."""

    # LambdaLR.state_dict saves ``__dict__``: the clock reading lives in a slot, outside it, so a
    # resumed run does not count the time it was stopped
    __slots__ = ("__dict__", "_last")

    def __init__(self, warmup_steps: int = 0, min_factor: float = 0.02, total_steps: int | None = None,
                 budget_s: float | None = None) -> None:
        if (total_steps is None) == (budget_s is None):
            raise ValueError("WarmupCosine: give exactly one of total_steps and budget_s")
        if total_steps is not None and int(total_steps) <= 0:
            raise ValueError(f"WarmupCosine: total_steps must be > 0, got {total_steps}")
        if budget_s is not None and float(budget_s) <= 0:
            raise ValueError(f"WarmupCosine: budget_s must be > 0, got {budget_s}")
        if not 0.0 <= float(min_factor) <= 1.0:
            raise ValueError(f"WarmupCosine: min_factor must lie in [0, 1], got {min_factor}")
        self.warmup_steps = int(warmup_steps)
        self.min_factor = float(min_factor)
        self.total_steps = int(total_steps) if total_steps is not None else None
        self.budget_s = float(budget_s) if budget_s is not None else None
        self.elapsed_s = 0.0
        self._last: float | None = None

    def progress(self, step: int) -> float:
        """Fraction of the schedule done, in [0, 1]."""
        if self.total_steps is not None:
            return min(max(step, 0) / self.total_steps, 1.0)
        now = time.monotonic()
        if self._last is not None:
            self.elapsed_s += now - self._last
        self._last = now
        return min(self.elapsed_s / self.budget_s, 1.0)

    def __call__(self, step: int) -> float:
        frac = self.progress(step)
        warm = min(1.0, (step + 1) / self.warmup_steps) if self.warmup_steps else 1.0
        return warm * (self.min_factor + (1.0 - self.min_factor) * 0.5 * (1.0 + math.cos(math.pi * frac)))


def parse_max_time(value) -> float | None:
    """Lightning ``max_time`` (``"DD:HH:MM:SS"``, a dict of ``timedelta`` fields, or None) in seconds."""
    if value is None:
        return None
    if isinstance(value, dict):
        from datetime import timedelta

        return timedelta(**value).total_seconds()
    parts = str(value).split(":")
    if len(parts) != 4:
        raise ValueError(f"max_time {value!r}: expected 'DD:HH:MM:SS'")
    try:
        d, h, m, s = (float(p) for p in parts)
    except ValueError as exc:
        raise ValueError(f"max_time {value!r}: expected 'DD:HH:MM:SS' with numbers") from exc
    return ((d * 24 + h) * 60 + m) * 60 + s
