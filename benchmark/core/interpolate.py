"""Batched interpolation of per-frame variables to other timestamps (SLERP / LERP).

Used by the protocols to bring per-observed-frame variables (VPoser latents' poses, free root
orientation and translation) and fixed-window decoder grids to the output timestamps. Outside the
source span the end values are held (clamped): the same rule for every prior.
"""

from __future__ import annotations

import torch

from benchmark.core.rotations import axis_angle_to_matrix, slerp_matrices


def bracket(src_t: torch.Tensor, dst_t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Indices (i0, i1) of the source frames around each destination time and the weight of i1.

    src_t: (B, n) increasing; dst_t: (B, T). Returns i0, i1 (B, T) long and w (B, T) in [0, 1];
    destinations outside [src_t[0], src_t[-1]] get w = 0 at the nearest end frame.
    """
    src_t = src_t.to(torch.float64).contiguous()
    dst_t = dst_t.to(torch.float64).contiguous()
    n = src_t.shape[1]
    i1 = torch.searchsorted(src_t, dst_t).clamp(1, max(n - 1, 1)) if n > 1 else torch.zeros_like(dst_t, dtype=torch.long)
    i0 = (i1 - 1).clamp_min(0)
    t0 = src_t.gather(1, i0)
    t1 = src_t.gather(1, i1)
    span = (t1 - t0).clamp_min(1e-12)
    w = ((dst_t - t0) / span).clamp(0.0, 1.0)
    w = torch.where(t1 > t0, w, torch.zeros_like(w))
    return i0, i1, w


def _gather_frames(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """x (B, n, ...) gathered along dim 1 with idx (B, T) -> (B, T, ...)."""
    B, T = idx.shape
    flat = idx.reshape(B, T, *([1] * (x.dim() - 2))).expand(B, T, *x.shape[2:])
    return x.gather(1, flat)


def lerp_frames(x: torch.Tensor, src_t: torch.Tensor, dst_t: torch.Tensor) -> torch.Tensor:
    """Linear interpolation of x (B, n, ...) from src_t (B, n) to dst_t (B, T)."""
    i0, i1, w = bracket(src_t, dst_t)
    w = w.to(x.dtype).reshape(*w.shape, *([1] * (x.dim() - 2)))
    return torch.lerp(_gather_frames(x, i0), _gather_frames(x, i1), w)


def slerp_frames(R: torch.Tensor, src_t: torch.Tensor, dst_t: torch.Tensor) -> torch.Tensor:
    """Spherical interpolation of rotations R (B, n, ..., 3, 3) from src_t (B, n) to dst_t (B, T)."""
    i0, i1, w = bracket(src_t, dst_t)
    w = w.to(R.dtype).reshape(*w.shape, *([1] * (R.dim() - 4)))
    return slerp_matrices(_gather_frames(R, i0), _gather_frames(R, i1), w)


def resample_intervals(motion, intervals, anchors: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each [start, end] of ``intervals`` (K, 2) of ``motion`` (a :class:`~benchmark.core.motion.Motion`)
    resampled to ``anchors`` instants uniformly in time (the one-cycle windows of
    :mod:`benchmark.synthetic.cycles`, the structured latent space's anchors).

    Returns local rotations (K, anchors, 22, 3, 3), translation (K, anchors, 3) (float32, SLERP /
    LERP between the motion's frames, clamped at its ends) and the anchor times relative to each
    interval's start (K, anchors) float64, 0 .. end - start.
    """
    iv = torch.as_tensor(intervals, dtype=torch.float64).reshape(-1, 2)
    K = iv.shape[0]
    if K == 0:
        return torch.zeros(0, anchors, 22, 3, 3), torch.zeros(0, anchors, 3), torch.zeros(0, anchors, dtype=torch.float64)
    if anchors < 2:
        raise ValueError(f"anchors must be >= 2, got {anchors}")
    u = torch.linspace(0.0, 1.0, anchors, dtype=torch.float64)
    rel = (iv[:, 1:] - iv[:, :1]) * u  # (K, n)
    dst = (iv[:, :1] + rel).reshape(1, -1)
    src = motion.timestamps.to(torch.float64)[None]
    R = axis_angle_to_matrix(motion.poses.to(torch.float64))[None]
    rot = slerp_frames(R, src, dst)[0].reshape(K, anchors, 22, 3, 3)
    trans = lerp_frames(motion.trans.to(torch.float64)[None], src, dst)[0].reshape(K, anchors, 3)
    return rot.float(), trans.float(), rel
