"""Arithmetic of a network and the machine's measured limit, for ``kpd6d-benchmark pipeline``.

:func:`count_flops` counts the floating-point operations of one forward pass with PyTorch's own
``torch.utils.flop_counter.FlopCounterMode`` (matrix products and convolutions, 2 per multiply-add;
element-wise work is not counted, so the figure is a lower bound of the work done).
:func:`matmul_peak_gflops` measures what this machine reaches on a large float32 matrix product
with the current torch threads: the practical peak a convolutional network can approach. A
network's achieved GFLOP/s (its FLOPs / its measured time) against that peak shows how far the
implementation is from the machine's limit.
"""

from __future__ import annotations

import statistics
import time

import torch

__all__ = ["count_flops", "matmul_peak_gflops"]


@torch.no_grad()
def count_flops(fn, *args, **kwargs) -> int:
    """Floating-point operations of ``fn(*args, **kwargs)`` (a module or any callable running torch ops)."""
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        fn(*args, **kwargs)
    return int(counter.get_total_flops())


@torch.no_grad()
def matmul_peak_gflops(n: int = 1024, repeats: int = 5, dtype: torch.dtype = torch.float32) -> float:
    """GFLOP/s of an ``n`` x ``n`` matrix product (2 n^3 operations), the median of ``repeats`` timed
    runs after one warm-up, with torch's current thread count."""
    g = torch.Generator().manual_seed(0)
    a = torch.rand(n, n, generator=g, dtype=dtype)
    b = torch.rand(n, n, generator=g, dtype=dtype)
    torch.mm(a, b)
    times = []
    for _ in range(max(1, int(repeats))):
        t0 = time.perf_counter()
        torch.mm(a, b)
        times.append(time.perf_counter() - t0)
    return 2.0 * n**3 / statistics.median(times) / 1e9
