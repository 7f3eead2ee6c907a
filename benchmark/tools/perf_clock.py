"""The clock of ``python -m benchmark perf``: CPU seconds of the process on CPU (robust to other
jobs sharing the cores), wall seconds with CUDA; best of a few repeats after a warm-up."""

from __future__ import annotations

import time

import torch


def sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


CLOCK = time.process_time  # CPU seconds of this process: robust to other jobs sharing the cores


def timeit(fn, repeats: int = 3) -> float:
    """Best-of-``repeats`` seconds of ``fn()`` (CPU time on CPU, wall time with CUDA), after one
    warm-up call."""
    clock = time.perf_counter if torch.cuda.is_available() else CLOCK
    fn()
    best = float("inf")
    for _ in range(repeats):
        sync()
        t0 = clock()
        fn()
        sync()
        best = min(best, clock() - t0)
    return best


__all__ = ["CLOCK", "sync", "timeit"]
