"""The clock of ``python -m benchmark perf``: CPU seconds of the process on CPU (robust to other
jobs sharing the cores), wall seconds with CUDA; best of a few repeats after a warm-up."""

from __future__ import annotations

import time

import torch


def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


_CLOCK = time.process_time  # CPU seconds of this process: robust to other jobs sharing the cores


def _timeit(fn, repeats: int = 3) -> float:
    """Best-of-``repeats`` seconds of ``fn()`` (CPU time on CPU, wall time with CUDA), after one
    warm-up call."""
    clock = time.perf_counter if torch.cuda.is_available() else _CLOCK
    fn()
    best = float("inf")
    for _ in range(repeats):
        _sync()
        t0 = clock()
        fn()
        _sync()
        best = min(best, clock() - t0)
    return best


__all__ = ["_CLOCK", "_sync", "_timeit"]
