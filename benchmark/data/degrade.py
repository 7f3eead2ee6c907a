"""Degradation of dense scans (table1's grid) and fingerprints of what a cell saw.

:func:`degrade` thins a :class:`~benchmark.data.observations.PointCloudSequence` in time (keep every
k-th capture frame) and in space (a fresh random subset of points in each kept frame).
:func:`fingerprint` is a sha256 digest of an observation's content, recorded with each result so
that "the input changed" can be told apart from "the model changed".
"""

from __future__ import annotations

import hashlib
import logging

import torch

from benchmark.data.observations import PointCloudSequence, seed_generators

log = logging.getLogger(__name__)

# Largest relative deviation of a capture frame interval from the median interval.
_UNIFORM_TOLERANCE = 1e-2
# Largest relative deviation of capture_fps / fps from an integer.
_RATIO_TOLERANCE = 1e-3


def capture_rate(scans: PointCloudSequence) -> float:
    """The capture rate (frames per second) of uniformly timed scans, from their timestamps.

    Uses the intervals between consecutive real frames of every sequence; they must all agree
    with their median within 1 % (error otherwise, as for fewer than two frames).
    """
    ts, m = scans.timestamps, scans.frame_mask
    dt = ts[:, 1:] - ts[:, :-1]
    both = m[:, 1:] & m[:, :-1]
    dt = dt[both]
    if dt.numel() == 0:
        raise ValueError(
            "degrade: cannot infer the capture rate from fewer than two consecutive frames; pass capture_fps=..."
        )
    period = float(dt.median())
    if not period > 0:
        raise ValueError(f"degrade: scan timestamps must increase frame to frame, median interval is {period} s")
    worst = float((dt - period).abs().max())
    if worst > _UNIFORM_TOLERANCE * period:
        raise ValueError(
            f"degrade: scan timestamps are not uniform (intervals {float(dt.min()):.6f} .. {float(dt.max()):.6f} s "
            f"around {period:.6f} s); temporal degradation keeps every k-th frame and needs a uniform capture "
            "rate: pass capture_fps=... to assert one"
        )
    return 1.0 / period


def temporal_stride(capture_fps: float, fps: float) -> int:
    """k = capture_fps / fps, which must be a positive integer (error naming both rates otherwise)."""
    if not fps > 0 or not capture_fps > 0:
        raise ValueError(f"degrade: frame rates must be > 0, got capture {capture_fps} fps and target {fps} fps")
    ratio = capture_fps / fps
    k = round(ratio)
    if k < 1 or abs(ratio - k) > _RATIO_TOLERANCE * ratio:
        hint = "a target rate capture_fps / k for an integer k"
        whole = round(capture_fps)
        if abs(capture_fps - whole) < 1e-9 and whole <= 10000:
            rates = [str(whole // d) for d in range(1, whole + 1) if whole % d == 0]
            hint += f" ({', '.join(rates)} fps for this capture)"
        raise ValueError(
            f"degrade: cannot keep every k-th frame to go from the {capture_fps:g} fps capture to {fps:g} fps: "
            f"{capture_fps:g} / {fps:g} = {ratio:.4g} is not an integer; choose {hint}"
        )
    return k


def degrade(
    scans: PointCloudSequence,
    points_per_frame: int | None,
    fps: float | None,
    seed: int | list[int] = 0,
    capture_fps: float | None = None,
) -> PointCloudSequence:
    """Thin scans in time and space.

    Temporal (``fps``; None keeps every frame): keep capture frames 0, k, 2k, ... with
    k = capture_fps / fps an integer; ``capture_fps`` defaults to the rate read off the
    timestamps (:func:`capture_rate`). 50 fps -> 5 fps keeps frames 0, 10, 20, ...
    Spatial (``points_per_frame``; None keeps every point): a fresh uniform random subset of
    ``points_per_frame`` distinct points in each kept frame, drawn from
    ``torch.Generator().manual_seed(seed)`` (one float64 key per padded point slot, shape
    (B, T', N), the smallest keys win); the kept points stay in their original order. ``seed`` a
    list of B ints: sequence b's keys ((T', N)) come from its own generator, so its subset does not
    depend on the rest of the batch. A frame with
    fewer points keeps all of them: its ``lengths`` entry stays below ``points_per_frame``, and
    the number of such frames is logged as a warning.
    Returns a new PointCloudSequence with points (B, T', min(N, points_per_frame), 3).
    """
    points, lengths, timestamps, mask = scans.points, scans.lengths, scans.timestamps, scans.frame_mask
    if fps is not None:
        rate = capture_rate(scans) if capture_fps is None else float(capture_fps)
        k = temporal_stride(rate, fps)
        points, lengths, timestamps, mask = points[:, ::k], lengths[:, ::k], timestamps[:, ::k], mask[:, ::k]
    lengths = lengths * mask

    if points_per_frame is None:
        return PointCloudSequence(points=points.clone(), lengths=lengths.clone(), timestamps=timestamps.clone(),
                                  frame_mask=mask.clone())
    if points_per_frame < 1:
        raise ValueError(f"degrade: points_per_frame must be >= 1 (or None to keep all), got {points_per_frame}")
    B, T, N = points.shape[:3]
    keep = min(points_per_frame, N)
    short = int(((lengths < points_per_frame) & mask).sum())
    if short:
        log.warning(
            "degrade: %d of %d frames have fewer than %d points and keep all of theirs (see lengths)",
            short, int(mask.sum()), points_per_frame,
        )
    slot = torch.arange(N, device=points.device)
    real = slot < lengths[..., None]  # (B, T, N)
    if isinstance(seed, (list, tuple)):
        keys = torch.stack([torch.rand(T, N, dtype=torch.float64, generator=g)
                            for g in seed_generators(seed, B, "degrade")]).to(points.device)
    else:
        keys = torch.rand(B, T, N, dtype=torch.float64, generator=torch.Generator().manual_seed(seed)).to(points.device)
    keys = keys.masked_fill(~real, 2.0)  # padding sorts after every real point
    idx = keys.topk(keep, dim=-1, largest=False).indices.sort(dim=-1).values  # (B, T, keep)
    subset = points.gather(2, idx[..., None].expand(B, T, keep, 3))
    new_lengths = lengths.clamp(max=keep)
    valid = torch.arange(keep, device=points.device) < new_lengths[..., None]
    subset = subset * valid[..., None]
    return PointCloudSequence(points=subset, lengths=new_lengths, timestamps=timestamps.clone(),
                              frame_mask=mask.clone())


def fingerprint(obs) -> str:
    """sha256 hex digest of an observation's content (PointCloudSequence, Landmarks, NoisyJoints).

    Hashes the class name and the observation's ``canonical_arrays()`` in order: per array its
    name, shape and dtype, then its little-endian bytes. Point coordinates enter as float32, only
    real points of real frames are hashed (padding never matters), and -0.0 is folded into 0.0.
    Identical inputs give identical digests across runs and machines; any changed point,
    timestamp or length changes it.
    """
    canonical = getattr(obs, "canonical_arrays", None)
    if canonical is None:
        raise TypeError(f"fingerprint: {type(obs).__name__} is not an observation (no canonical_arrays())")
    h = hashlib.sha256()
    h.update(type(obs).__name__.encode())
    for name, array in canonical().items():
        a = array.detach().cpu().contiguous()
        if a.is_floating_point():
            a = a + 0.0  # -0.0 -> 0.0
        data = a.numpy()
        data = data.astype(data.dtype.newbyteorder("<"), copy=False)
        h.update(f"|{name}:{tuple(data.shape)}:{data.dtype.str}|".encode())
        h.update(data.tobytes())
    return h.hexdigest()
