"""Bootstrap intervals over sequences (pure numpy): the uncertainty of a table cell.

A cell's number is a frame-weighted mean over its sequences, ``sum(w_i v_i) / sum(w_i)`` with
``v_i`` a sequence's mean and ``w_i`` its frames. Its interval is a *percentile bootstrap*:
resample the sequences (value and weight together) with replacement, recompute the weighted mean,
and take the ``(1 - level) / 2`` and ``(1 + level) / 2`` quantiles of the resampled means.

A *paired* comparison of two cells on the same sequences bootstraps the per-sequence differences
``a_i - b_i``: resampling a sequence index draws both of its values at once, so what the two cells
share (a hard sequence is hard for every prior) cancels out of the interval.

Every function takes the :class:`numpy.random.Generator` it draws from: the caller seeds it, so an
interval is the same on every machine. A bad input raises ``ValueError`` saying what is wrong.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

RESAMPLES = 2000  # bootstrap resamples per interval
LEVEL = 0.95  # the intervals' coverage
# The fewest paired sequences a significance claim needs. A percentile bootstrap interval of the
# differences excludes 0 whenever every difference has the same sign, at any count; with n sequences
# whose differences are signs of noise that happens with probability 2 / 2**n, above 5 % for n <= 5
# (50 % with 2 sequences). Below this count a comparison keeps its difference and interval and
# claims no significance.
MIN_SIGNIFICANCE_SEQUENCES = 6


def _check(values, weights, what: str) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(values, dtype=float)
    w = np.asarray(weights, dtype=float)
    if v.ndim != 1 or w.shape != v.shape:
        raise ValueError(f"{what}: values and weights must be 1-D of the same length, got shapes {v.shape} and {w.shape}")
    if len(v) < 2:
        raise ValueError(f"{what}: a bootstrap needs at least 2 sequences, got {len(v)}")
    if not np.isfinite(v).all():
        raise ValueError(f"{what}: values must be finite numbers")
    if not (np.isfinite(w).all() and (w > 0).all()):
        raise ValueError(f"{what}: weights must be finite and > 0 (the sequences' frames)")
    return v, w


def _check_options(rng, n: int, level: float, what: str) -> None:
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"{what}: rng must be a numpy.random.Generator (numpy.random.default_rng(seed)), "
                         f"got {type(rng).__name__}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"{what}: n (the number of resamples) must be an integer >= 1, got {n!r}")
    if not (isinstance(level, (int, float)) and 0.0 < float(level) < 1.0):
        raise ValueError(f"{what}: level must be a number in (0, 1), got {level!r}")


def weighted_mean(values: Sequence[float], weights: Sequence[float]) -> float:
    """``sum(w v) / sum(w)`` (the cell's frame-weighted mean from its sequences' means and frames)."""
    v = np.asarray(values, dtype=float)
    w = np.asarray(weights, dtype=float)
    if v.ndim != 1 or w.shape != v.shape or not len(v):
        raise ValueError(f"weighted_mean: values and weights must be 1-D, non-empty and of the same length, "
                         f"got shapes {v.shape} and {w.shape}")
    if not (np.isfinite(w).all() and (w > 0).all()):
        raise ValueError("weighted_mean: weights must be finite and > 0")
    return float(np.dot(w, v) / w.sum())


def bootstrap_ci(values: Sequence[float], weights: Sequence[float], rng: np.random.Generator, n: int = RESAMPLES,
                 level: float = LEVEL) -> tuple[float, float]:
    """Percentile bootstrap interval ``(lo, hi)`` of the weighted mean of ``values``.

    values: one number per sequence (its mean); weights: its frames (> 0); at least 2 sequences.
    Draws ``n`` resamples of the sequences with replacement from ``rng``.
    """
    v, w = _check(values, weights, "bootstrap_ci")
    _check_options(rng, n, level, "bootstrap_ci")
    idx = rng.integers(0, len(v), size=(int(n), len(v)))
    wi = w[idx]
    means = (wi * v[idx]).sum(axis=1) / wi.sum(axis=1)
    lo, hi = np.quantile(means, [(1.0 - level) / 2.0, (1.0 + level) / 2.0])
    return float(lo), float(hi)


def paired_bootstrap(a: Sequence[float], b: Sequence[float], weights: Sequence[float], rng: np.random.Generator,
                     n: int = RESAMPLES, level: float = LEVEL) -> tuple[float, tuple[float, float]]:
    """The weighted mean of ``a - b`` and its percentile bootstrap interval: ``(diff, (lo, hi))``.

    a, b: the two cells' values on the same sequences, in the same order; weights: the sequences'
    frames. The sequence indices are resampled jointly (one draw picks ``a_i`` and ``b_i``).
    """
    va = np.asarray(a, dtype=float)
    vb = np.asarray(b, dtype=float)
    if va.shape != vb.shape:
        raise ValueError(f"paired_bootstrap: a and b must hold the same sequences, got shapes {va.shape} and {vb.shape}")
    d, w = _check(va - vb, weights, "paired_bootstrap")
    return weighted_mean(d, w), bootstrap_ci(d, w, rng, n=n, level=level)


def excludes_zero(interval: Sequence[float]) -> bool:
    """Whether ``(lo, hi)`` lies wholly above or wholly below 0."""
    lo, hi = interval
    return lo > 0.0 or hi < 0.0
