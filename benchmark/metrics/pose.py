"""Pose and motion metrics on batched sequences (docs/protocol.md): MPJPE, PA-MPJPE, V2V, acceleration.

Inputs are positions in metres, (B, T, J, 3) (joints, or vertices for V2V), with an optional
``mask`` (B, T) bool of valid frames (None = all valid). Outputs are metres (m/s^2 for
acceleration); the table writer converts to mm.

Reductions (argument ``reduction``, the same for every metric):

- ``"frame"``: (B, T) per-frame values (mean over joints), NaN at invalid frames, so that a padded
  frame can never slip into a mean unnoticed. For the acceleration metrics the frame axis has
  T - 2 entries, entry ``t`` centred on frame ``t + 1``; an entry is valid when frames
  ``t, t + 1, t + 2`` all are.
- ``"sequence"`` (default): (B,) mean over the valid frames of each sequence.
- ``"sum"``: (B,) sum over the valid frames of each sequence; with :func:`valid_frame_counts`
  this is the sum-reducible state an accumulator keeps (merging workers is addition).
- ``"mean"``: scalar mean over all valid frames of all sequences, the number docs/protocol.md puts
  in a table (a frame-weighted mean, never a mean of per-sequence means).

:func:`reduce_frames` applies the same reductions to any per-frame metric (e.g. a per-frame
Chamfer distance reshaped to (B, T)).
"""

from __future__ import annotations

import math

import roma
import torch

REDUCTIONS = ("frame", "sequence", "sum", "mean")


# ----------------------------------------------------------------------------- validation


def _validate_positions(x, name: str, caller: str, what: str = "J") -> None:
    if not isinstance(x, torch.Tensor):
        raise ValueError(f"{caller}: `{name}` must be a torch.Tensor of shape (B, T, {what}, 3) in metres; "
                         f"got {type(x).__name__}.")
    if x.dim() != 4 or x.shape[-1] != 3:
        raise ValueError(f"{caller}: `{name}` must have shape (B, T, {what}, 3) (batch, frames, points, xyz in "
                         f"metres); got {tuple(x.shape)}. Add missing batch/time dimensions with `{name}[None]`.")
    if not x.is_floating_point():
        raise ValueError(f"{caller}: `{name}` must be a floating-point tensor; got dtype {x.dtype}.")
    if x.shape[0] == 0 or x.shape[1] == 0 or x.shape[2] == 0:
        raise ValueError(f"{caller}: `{name}` is empty (shape {tuple(x.shape)}).")


def _validate_pair(pred, gt, caller: str, what: str = "J") -> None:
    _validate_positions(pred, "pred", caller, what)
    _validate_positions(gt, "gt", caller, what)
    if pred.shape != gt.shape:
        raise ValueError(f"{caller}: `pred` and `gt` must have the same shape; got {tuple(pred.shape)} and "
                         f"{tuple(gt.shape)}.")
    if pred.device != gt.device:
        raise ValueError(f"{caller}: `pred` and `gt` must be on the same device; got {pred.device} and {gt.device}.")


def _validate_mask(mask, batch: int, frames: int, caller: str, device) -> torch.Tensor:
    if mask is None:
        return torch.ones((batch, frames), dtype=torch.bool, device=device)
    if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
        got = mask.dtype if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise ValueError(f"{caller}: `mask` must be a (B, T) bool tensor of valid frames or None; got {got}.")
    if mask.shape != (batch, frames):
        raise ValueError(f"{caller}: `mask` must have shape (B, T) = ({batch}, {frames}); got {tuple(mask.shape)}.")
    return mask.to(device)


def _validate_fps(fps, caller: str) -> float:
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"{caller}: `fps` must be a positive number (frames per second); got {fps!r}.")
    return float(fps)


# ----------------------------------------------------------------------------- reductions


def reduce_frames(values: torch.Tensor, valid: torch.Tensor, reduction: str = "sequence",
                  caller: str = "reduce_frames") -> torch.Tensor:
    """Reduce per-frame values (B, T) over the valid frames (B, T) bool (see module docstring).

    "sequence" and "mean" need at least one valid frame per sequence / overall, else ValueError
    (a sequence without a valid frame has no value, and a bad input never produces a number).
    """
    if reduction not in REDUCTIONS:
        raise ValueError(f"{caller}: `reduction` must be one of {REDUCTIONS}; got {reduction!r}.")
    if values.shape != valid.shape or values.dim() != 2:
        raise ValueError(f"{caller}: `values` and `valid` must both have shape (B, T); got {tuple(values.shape)} "
                         f"and {tuple(valid.shape)}.")
    zero = torch.zeros((), dtype=values.dtype, device=values.device)
    if reduction == "frame":
        return torch.where(valid, values, torch.full((), math.nan, dtype=values.dtype, device=values.device))
    sums = torch.where(valid, values, zero).sum(dim=1)
    if reduction == "sum":
        return sums
    counts = valid.sum(dim=1)
    if reduction == "sequence":
        if bool((counts == 0).any()):
            bad = torch.nonzero(counts == 0).flatten().tolist()
            raise ValueError(f"{caller}: sequences {bad} have no valid frame (mask all False"
                             f"{', or fewer than 3 consecutive valid frames for acceleration' if 'accel' in caller else ''}); "
                             "drop them or fix `mask`.")
        return sums / counts.to(values.dtype)
    total = counts.sum()
    if int(total) == 0:
        raise ValueError(f"{caller}: no valid frame in the whole batch; fix `mask`.")
    return sums.sum() / total.to(values.dtype)


def valid_frame_counts(mask: torch.Tensor | None, batch: int, frames: int, acceleration: bool = False) -> torch.Tensor:
    """(B,) number of valid frames per sequence that ``reduction="sum"`` summed over.

    With ``acceleration=True``: the number of valid second differences (three consecutive valid
    frames), as the acceleration metrics count them.
    """
    valid = _validate_mask(mask, batch, frames, "valid_frame_counts", "cpu" if mask is None else mask.device)
    if acceleration:
        valid = _acceleration_valid(valid)
    return valid.sum(dim=1)


def _acceleration_valid(mask: torch.Tensor) -> torch.Tensor:
    """(B, T - 2) True where frames t, t + 1, t + 2 are all valid."""
    return mask[:, :-2] & mask[:, 1:-1] & mask[:, 2:]


def _mean_point_error(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """(B, T) mean over points of the Euclidean error."""
    return (pred - gt).norm(dim=-1).mean(dim=-1)


# ----------------------------------------------------------------------------- metrics


def mpjpe(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None,
          reduction: str = "sequence") -> torch.Tensor:
    """Mean per-joint position error (no alignment), metres.

    Args:
        pred, gt: (B, T, J, 3) joint positions, metres.
        mask: (B, T) bool valid frames, or None (all valid).
        reduction: "frame" | "sequence" | "sum" | "mean" (module docstring).

    Returns:
        (B, T), (B,) or scalar, metres.
    """
    caller = "mpjpe"
    _validate_pair(pred, gt, caller)
    valid = _validate_mask(mask, pred.shape[0], pred.shape[1], caller, pred.device)
    return reduce_frames(_mean_point_error(pred, gt), valid, reduction, caller)


def v2v(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None,
        reduction: str = "sequence") -> torch.Tensor:
    """Mean per-vertex error (vertex-to-vertex, same topology, no alignment), metres.

    Args:
        pred, gt: (B, T, V, 3) mesh vertices in correspondence, metres.
        mask: (B, T) bool valid frames, or None (all valid).
        reduction: "frame" | "sequence" | "sum" | "mean" (module docstring).

    Returns:
        (B, T), (B,) or scalar, metres.
    """
    caller = "v2v"
    _validate_pair(pred, gt, caller, what="V")
    valid = _validate_mask(mask, pred.shape[0], pred.shape[1], caller, pred.device)
    return reduce_frames(_mean_point_error(pred, gt), valid, reduction, caller)


def procrustes_align(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Align each frame of ``pred`` to ``gt`` by the best similarity (rotation, translation, scale).

    Per frame, minimises sum_j |s R pred_j + t - gt_j|^2 over proper rotations R (det +1, no
    reflection), translations t and scales s > 0 (Umeyama; ``roma.rigid_points_registration``).

    Args:
        pred, gt: (..., J, 3) point sets in correspondence, J >= 3 not all collinear.

    Returns:
        (..., J, 3) aligned ``pred``.
    """
    rotation, translation, scale = roma.rigid_points_registration(pred, gt, compute_scaling=True)
    return scale[..., None, None] * torch.einsum("...ij,...nj->...ni", rotation, pred) + translation[..., None, :]


def pa_mpjpe(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None,
             reduction: str = "sequence") -> torch.Tensor:
    """MPJPE after per-frame Procrustes alignment of ``pred`` to ``gt`` (rotation, translation,
    scale; see :func:`procrustes_align`), metres.

    Args:
        pred, gt: (B, T, J, 3) joint positions, metres.
        mask: (B, T) bool valid frames, or None (all valid). Invalid frames are never aligned
            (their contents may be anything).
        reduction: "frame" | "sequence" | "sum" | "mean" (module docstring).

    Returns:
        (B, T), (B,) or scalar, metres.
    """
    caller = "pa_mpjpe"
    _validate_pair(pred, gt, caller)
    if pred.shape[2] < 3:
        raise ValueError(f"{caller}: Procrustes alignment needs at least 3 joints; got J = {pred.shape[2]}.")
    valid = _validate_mask(mask, pred.shape[0], pred.shape[1], caller, pred.device)
    # Invalid frames (padding) may be degenerate (all zeros): give them a harmless stand-in.
    keep = valid[..., None, None]
    gt_safe = torch.where(keep, gt, _reference_points(pred.shape[2], pred))
    pred_safe = torch.where(keep, pred, gt_safe)
    aligned = procrustes_align(pred_safe, gt_safe)
    return reduce_frames(_mean_point_error(aligned, gt_safe), valid, reduction, caller)


def _reference_points(n: int, like: torch.Tensor) -> torch.Tensor:
    """(n, 3) fixed, non-degenerate points (a helix) standing in for padded frames."""
    t = torch.arange(n, dtype=like.dtype, device=like.device)
    return torch.stack([torch.cos(t), torch.sin(t), 0.1 * t], dim=-1)


def _acceleration(x: torch.Tensor, fps: float) -> torch.Tensor:
    """(B, T - 2, J, 3) second finite difference times fps^2, m/s^2 (centred on frames 1..T-2)."""
    return (x[:, 2:] - 2 * x[:, 1:-1] + x[:, :-2]) * (fps * fps)


def mean_acceleration(x: torch.Tensor, fps: float, mask: torch.Tensor | None = None,
                      reduction: str = "sequence") -> torch.Tensor:
    """Mean acceleration magnitude |x[t+1] - 2 x[t] + x[t-1]| * fps^2 over joints and frames, m/s^2.

    Args:
        x: (B, T, J, 3) positions, metres, T >= 3, sampled at ``fps``.
        fps: frames per second.
        mask: (B, T) bool valid frames, or None. A second difference counts when its three
            frames are valid.
        reduction: "frame" (B, T - 2) | "sequence" | "sum" | "mean" (module docstring).

    Returns:
        (B, T - 2), (B,) or scalar, m/s^2.
    """
    caller = "mean_acceleration"
    _validate_positions(x, "x", caller)
    fps = _validate_fps(fps, caller)
    if x.shape[1] < 3:
        raise ValueError(f"{caller}: acceleration needs T >= 3 frames; got T = {x.shape[1]}.")
    valid = _acceleration_valid(_validate_mask(mask, x.shape[0], x.shape[1], caller, x.device))
    values = _acceleration(x, fps).norm(dim=-1).mean(dim=-1)
    return reduce_frames(values, valid, reduction, caller)


def acceleration_error(pred: torch.Tensor, gt: torch.Tensor, fps: float, mask: torch.Tensor | None = None,
                       reduction: str = "sequence") -> torch.Tensor:
    """Mean magnitude of the difference of accelerations |a_pred - a_gt| over joints and frames, m/s^2.

    Args:
        pred, gt: (B, T, J, 3) positions, metres, T >= 3, sampled at ``fps``.
        fps: frames per second.
        mask: (B, T) bool valid frames, or None. A second difference counts when its three
            frames are valid.
        reduction: "frame" (B, T - 2) | "sequence" | "sum" | "mean" (module docstring).

    Returns:
        (B, T - 2), (B,) or scalar, m/s^2.
    """
    caller = "acceleration_error"
    _validate_pair(pred, gt, caller)
    fps = _validate_fps(fps, caller)
    if pred.shape[1] < 3:
        raise ValueError(f"{caller}: acceleration needs T >= 3 frames; got T = {pred.shape[1]}.")
    valid = _acceleration_valid(_validate_mask(mask, pred.shape[0], pred.shape[1], caller, pred.device))
    values = (_acceleration(pred, fps) - _acceleration(gt, fps)).norm(dim=-1).mean(dim=-1)
    return reduce_frames(values, valid, reduction, caller)
