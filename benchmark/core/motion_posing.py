"""Posing a body with motions: the capture timestamp grid, resampling motions onto it, stacking
their shape vectors, and posing the body in chunks without gradients.

Used by :mod:`benchmark.data.observations` (ground truth, scans, landmarks) and
:mod:`benchmark.data.unit_arrays`. Units: metres, seconds, radians; timestamps are float64 seconds.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

from benchmark.core.skeleton import NUM_JOINTS

# Frames per body call when posing (one chunk: chunk x V x (3 x 4) floats of skinning transforms).
DEFAULT_CHUNK_FRAMES = 256
# Tolerance (s) when checking that requested timestamps lie inside a motion's time span.
_TIME_TOLERANCE = 1e-6


def body_float(body: torch.nn.Module) -> tuple[torch.dtype, torch.device]:
    """The floating dtype and device of a body's buffers (float32 on CPU if it has none)."""
    for buf in body.buffers():
        if buf.is_floating_point():
            return buf.dtype, buf.device
    return torch.float32, body.faces.device


def _motion_span(motion, index: int) -> tuple[float, float]:
    ts = torch.as_tensor(motion.timestamps, dtype=torch.float64)
    if ts.dim() != 1 or ts.numel() == 0:
        raise ValueError(f"motion {index}: timestamps must be a non-empty (T,) tensor, got shape {tuple(ts.shape)}")
    return float(ts[0]), float(ts[-1])


def capture_timestamps(
    motions: Sequence, fps: float, duration: float | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The capture grid: frame i of motion b at ``t0_b + i / fps`` (t0_b: the motion's first timestamp).

    duration None: every capture instant inside the motion's closed span [t0, t_end].
    duration D: a half-open window [t0, t0 + D), i.e. round(D * fps) frames (a 4 s window at
    50 fps is 200 frames, 0 .. 3.98 s); every motion must be long enough.
    Returns (timestamps (B, T) float64, frame_mask (B, T) bool); T is the longest sequence.
    """
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if len(motions) == 0:
        raise ValueError("no motions given")
    starts, counts = [], []
    for b, m in enumerate(motions):
        t0, t1 = _motion_span(m, b)
        if duration is None:
            n = int(math.floor((t1 - t0) * fps + 1e-6)) + 1
        else:
            if not duration > 0:
                raise ValueError(f"duration must be > 0 seconds, got {duration}")
            n = int(round(duration * fps))
            last = t0 + (n - 1) / fps
            if last > t1 + _TIME_TOLERANCE:
                raise ValueError(
                    f"motion {b} spans {t1 - t0:.4f} s ({t0:.4f} .. {t1:.4f}), but a {duration} s window at "
                    f"{fps} fps needs frames up to {last:.4f} s: pass a shorter duration or a longer motion"
                )
        starts.append(t0)
        counts.append(max(n, 1))
    T = max(counts)
    i = torch.arange(T, dtype=torch.float64)
    timestamps = torch.tensor(starts, dtype=torch.float64)[:, None] + i / fps
    frame_mask = i[None, :] < torch.tensor(counts, dtype=torch.float64)[:, None]
    return timestamps, frame_mask


def stack_shapes(body, motions: Sequence, shapes: torch.Tensor | None, dtype, device) -> torch.Tensor:
    B = len(motions)
    if shapes is not None:
        shapes = torch.as_tensor(shapes)
        if shapes.dim() == 1:
            shapes = shapes.expand(B, -1)
        if shapes.shape != (B, body.shape_dim):
            raise ValueError(
                f"shapes must be (batch, {body.shape_dim}) = ({B}, {body.shape_dim}) for body "
                f"{body.name!r}, got {tuple(shapes.shape)}"
            )
        return shapes.to(device=device, dtype=dtype)
    own = [getattr(m, "shape", None) for m in motions]
    if all(s is None or torch.as_tensor(s).numel() == 0 for s in own):
        return body.default_shape(B).to(device=device, dtype=dtype)
    rows = []
    for b, s in enumerate(own):
        if s is None or torch.as_tensor(s).numel() == 0:
            rows.append(body.default_shape(1)[0].to(device=device, dtype=dtype))
            continue
        s = torch.as_tensor(s).reshape(-1)
        if s.numel() != body.shape_dim:
            raise ValueError(
                f"motion {b} carries a shape vector of size {s.numel()}, but body {body.name!r} takes "
                f"{body.shape_dim} parameters: pass shapes=(batch, {body.shape_dim}) for this body"
            )
        rows.append(s.to(device=device, dtype=dtype))
    return torch.stack(rows)


def resample_stack(motions: Sequence, timestamps: torch.Tensor, frame_mask: torch.Tensor):
    """Resample each motion at its row of timestamps (padded frames clamped into its span).

    Returns poses (B, T, 22, 3) axis-angle and trans (B, T, 3).
    """
    poses, trans = [], []
    for b, m in enumerate(motions):
        t0, t1 = _motion_span(m, b)
        ts = timestamps[b]
        valid = ts[frame_mask[b]]
        if valid.numel() and (float(valid.min()) < t0 - _TIME_TOLERANCE or float(valid.max()) > t1 + _TIME_TOLERANCE):
            raise ValueError(
                f"motion {b} spans {t0:.4f} .. {t1:.4f} s, but ground truth was asked for at "
                f"{float(valid.min()):.4f} .. {float(valid.max()):.4f} s: timestamps outside a motion "
                "cannot be posed (mark them invalid with frame_mask, or pass timestamps inside the span)"
            )
        ts_dtype = torch.as_tensor(m.timestamps).dtype
        r = m.resample(ts.clamp(t0, t1).to(ts_dtype))
        p = torch.as_tensor(r.poses)
        tr = torch.as_tensor(r.trans)
        if p.shape != (ts.shape[0], NUM_JOINTS, 3) or tr.shape != (ts.shape[0], 3):
            raise ValueError(
                f"motion {b}: resample gave poses {tuple(p.shape)} and trans {tuple(tr.shape)}, expected "
                f"({ts.shape[0]}, {NUM_JOINTS}, 3) axis-angle and ({ts.shape[0]}, 3)"
            )
        poses.append(p)
        trans.append(tr)
    return torch.stack(poses), torch.stack(trans)


def pose_body(
    body, rotations: torch.Tensor, trans: torch.Tensor, shapes: torch.Tensor,
    chunk_frames: int = DEFAULT_CHUNK_FRAMES,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pose a body in chunks, without gradients.

    rotations (B, T, 22, 3, 3), trans (B, T, 3), shapes (B, S).
    The rest state is prepared once per batch chunk and shared by its time chunks; at most
    ``chunk_frames`` frames go through the body at once.
    Returns vertices (B, T, V, 3) and joints (B, T, 22, 3).
    """
    if chunk_frames < 1:
        raise ValueError(f"chunk_frames must be >= 1, got {chunk_frames}")
    B, T = rotations.shape[:2]
    batch_chunk = max(1, chunk_frames // max(T, 1))
    time_chunk = min(T, chunk_frames) if T > 0 else 1
    verts, joints = [], []
    with torch.no_grad():
        for b0 in range(0, B, batch_chunk):
            b1 = min(B, b0 + batch_chunk)
            rest = body.prepare(shapes[b0:b1])
            v_row, j_row = [], []
            for t0 in range(0, T, time_chunk):
                t1 = min(T, t0 + time_chunk)
                out = body(rotations[b0:b1, t0:t1], trans[b0:b1, t0:t1], rest=rest)
                v_row.append(out.vertices)
                j_row.append(out.joints)
            verts.append(torch.cat(v_row, dim=1))
            joints.append(torch.cat(j_row, dim=1))
    return torch.cat(verts), torch.cat(joints)
