"""Observations synthesised from a body and motions, and the ground truth kept beside them.

The data structures are dataclasses of tensors, batch dimension first:

- :class:`PointCloudSequence`: dense or degraded scans, (B, T, N, 3) padded points.
- :class:`Landmarks`: the 16 MoCap-style markers of :data:`benchmark.skeleton.LANDMARK_NAMES`.
- :class:`NoisyJoints`: noisy local joint rotations plus noisy virtual-marker vertices (denoise table).
- :class:`GroundTruth`: the posed mesh and joints at the capture timestamps, and the motions,
  shapes and body that regenerate them at any other timestamp (:meth:`GroundTruth.at`).

Padding: sequences of different lengths share one (B, T) grid; ``frame_mask`` marks the real
frames, and the padded frames hold zeros (points, landmarks) or the pose at the motion's last
frame (ground truth, so every tensor stays finite). Within a frame only the first ``lengths``
points are real; the rest are zeros.

Units: metres, seconds, radians. Timestamps are float64 seconds.

The ``Motion`` objects consumed here follow :class:`benchmark.motion.Motion`: ``poses`` (T, 22, 3)
axis-angle local rotations, ``trans`` (T, 3) metres, ``timestamps`` (T,) seconds, ``shape`` (S,)
or None, ``resample(timestamps) -> Motion``. Only that interface is used (duck typing).

Randomness: every function takes a seed or a ``torch.Generator`` and draws in a documented
order, so the same seed gives the same observation. Random numbers are drawn on the generator's
device and then moved, so a CPU generator gives the same samples whatever device the body is on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import roma
import torch

from benchmark.skeleton import LANDMARK_NAMES, NUM_JOINTS, NUM_LANDMARKS

# Frames per body call when posing (one chunk: chunk x V x (3 x 4) floats of skinning transforms).
DEFAULT_CHUNK_FRAMES = 256
# Frames per chunk when gathering sampled triangles (bounds the (chunk, N, 3) temporaries).
_SAMPLE_CHUNK_FRAMES = 64
# Default number of virtual markers for the denoise table (MoSh / HuMoR use 43 marker vertices).
DEFAULT_NUM_MARKERS = 43
# Tolerance (s) when checking that requested timestamps lie inside a motion's time span.
_TIME_TOLERANCE = 1e-6


# --------------------------------------------------------------------------- data structures
def _check_shape(cls: str, name: str, tensor: torch.Tensor, shape: tuple) -> None:
    """shape: ints or None (any size) per dimension."""
    ok = tensor.dim() == len(shape) and all(s is None or s == d for s, d in zip(shape, tensor.shape))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{cls}.{name} must have shape {want}, got {tuple(tensor.shape)}")


def _default_mask(mask: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    if mask is None:
        return torch.ones(like.shape[:2], dtype=torch.bool, device=like.device)
    return mask.to(torch.bool)


def _valid_frames(frame_mask: torch.Tensor) -> torch.Tensor:
    """(K, 2) int64 (sequence, frame) indices of the real frames: padding-independent."""
    return frame_mask.nonzero().to(torch.int64)


@dataclass
class PointCloudSequence:
    """A batch of point-cloud sequences.

    points:     (B, T, N, 3) metres, padded with zeros beyond ``lengths`` and on padded frames.
    lengths:    (B, T) long, number of real points in each frame (0 on padded frames).
    timestamps: (B, T) float64 seconds.
    frame_mask: (B, T) bool, True on real frames (default: all True).
    """

    points: torch.Tensor
    lengths: torch.Tensor
    timestamps: torch.Tensor
    frame_mask: torch.Tensor | None = None

    def __post_init__(self):
        cls = type(self).__name__
        _check_shape(cls, "points", self.points, (None, None, None, 3))
        B, T, N = self.points.shape[:3]
        _check_shape(cls, "lengths", self.lengths, (B, T))
        _check_shape(cls, "timestamps", self.timestamps, (B, T))
        self.lengths = self.lengths.to(torch.long)
        self.timestamps = self.timestamps.to(torch.float64)
        self.frame_mask = _default_mask(self.frame_mask, self.points)
        _check_shape(cls, "frame_mask", self.frame_mask, (B, T))
        if self.lengths.numel() and (int(self.lengths.min()) < 0 or int(self.lengths.max()) > N):
            raise ValueError(
                f"{cls}.lengths must lie in [0, {N}] (the padded point count), "
                f"got values in [{int(self.lengths.min())}, {int(self.lengths.max())}]"
            )

    @property
    def batch_size(self) -> int:
        return self.points.shape[0]

    @property
    def num_frames(self) -> int:
        return self.points.shape[1]

    @property
    def max_points(self) -> int:
        return self.points.shape[2]

    def point_mask(self) -> torch.Tensor:
        """(B, T, N) bool: True on real points of real frames."""
        n = torch.arange(self.max_points, device=self.points.device)
        return (n < self.lengths[..., None]) & self.frame_mask[..., None]

    def frame_points(self, b: int, t: int) -> torch.Tensor:
        """(n, 3) the real points of sequence b, frame t (for inspection and tests, not hot paths)."""
        if not bool(self.frame_mask[b, t]):
            return self.points.new_zeros(0, 3)
        return self.points[b, t, : int(self.lengths[b, t])]

    def to(self, device=None, dtype: torch.dtype | None = None) -> "PointCloudSequence":
        """Move to a device; ``dtype`` applies to the points only (timestamps stay float64)."""
        return PointCloudSequence(
            points=self.points.to(device=device, dtype=dtype),
            lengths=self.lengths.to(device),
            timestamps=self.timestamps.to(device),
            frame_mask=self.frame_mask.to(device),
        )

    def canonical_arrays(self) -> dict[str, torch.Tensor]:
        """What defines this observation, independent of padding (see :func:`benchmark.degrade.fingerprint`)."""
        m = self.frame_mask
        return {
            "batch_size": torch.tensor([self.batch_size], dtype=torch.int64),
            "frames": _valid_frames(m),
            "timestamps": self.timestamps[m],
            "lengths": self.lengths[m],
            "points": self.points[self.point_mask()].to(torch.float32),
        }


@dataclass
class Landmarks:
    """16 MoCap-style markers per frame, in :data:`LANDMARK_NAMES` order.

    positions:  (B, T, 16, 3) metres (zeros on padded frames).
    timestamps: (B, T) float64 seconds.
    frame_mask: (B, T) bool (default: all True).
    """

    positions: torch.Tensor
    timestamps: torch.Tensor
    frame_mask: torch.Tensor | None = None
    names: tuple[str, ...] = LANDMARK_NAMES

    def __post_init__(self):
        cls = type(self).__name__
        _check_shape(cls, "positions", self.positions, (None, None, NUM_LANDMARKS, 3))
        B, T = self.positions.shape[:2]
        _check_shape(cls, "timestamps", self.timestamps, (B, T))
        self.timestamps = self.timestamps.to(torch.float64)
        self.frame_mask = _default_mask(self.frame_mask, self.positions)
        _check_shape(cls, "frame_mask", self.frame_mask, (B, T))

    def canonical_arrays(self) -> dict[str, torch.Tensor]:
        m = self.frame_mask
        return {
            "batch_size": torch.tensor([self.positions.shape[0]], dtype=torch.int64),
            "frames": _valid_frames(m),
            "timestamps": self.timestamps[m],
            "positions": self.positions[m].to(torch.float32),
        }


@dataclass
class NoisyJoints:
    """Noisy motion capture for the denoise table.

    rotations:      (B, T, 22, 3) noisy local joint rotations, axis-angle radians (root included).
    joints:         (B, T, 22, 3) joint positions of the noisy pose, metres.
    markers:        (B, T, M, 3) virtual-marker vertices of the noisy pose, metres.
    marker_indices: (M,) long, the mesh vertices the markers are.
    trans:          (B, T, 3) root translation (clean: the noise is on rotations only), metres.
    shapes:         (B, S) the body shapes the markers were posed with.
    timestamps:     (B, T) float64 seconds.
    frame_mask:     (B, T) bool (default: all True).
    sigma:          the noise standard deviation (rad).
    """

    rotations: torch.Tensor
    joints: torch.Tensor
    markers: torch.Tensor
    marker_indices: torch.Tensor
    trans: torch.Tensor
    shapes: torch.Tensor
    timestamps: torch.Tensor
    frame_mask: torch.Tensor | None = None
    sigma: float = 0.0

    def __post_init__(self):
        cls = type(self).__name__
        _check_shape(cls, "rotations", self.rotations, (None, None, NUM_JOINTS, 3))
        B, T = self.rotations.shape[:2]
        _check_shape(cls, "joints", self.joints, (B, T, NUM_JOINTS, 3))
        _check_shape(cls, "marker_indices", self.marker_indices, (None,))
        _check_shape(cls, "markers", self.markers, (B, T, self.marker_indices.shape[0], 3))
        _check_shape(cls, "trans", self.trans, (B, T, 3))
        _check_shape(cls, "shapes", self.shapes, (B, None))
        _check_shape(cls, "timestamps", self.timestamps, (B, T))
        self.timestamps = self.timestamps.to(torch.float64)
        self.frame_mask = _default_mask(self.frame_mask, self.rotations)
        _check_shape(cls, "frame_mask", self.frame_mask, (B, T))

    def rotmats(self) -> torch.Tensor:
        """(B, T, 22, 3, 3) the noisy local rotations as matrices."""
        return roma.rotvec_to_rotmat(self.rotations)

    def canonical_arrays(self) -> dict[str, torch.Tensor]:
        m = self.frame_mask
        return {
            "batch_size": torch.tensor([self.rotations.shape[0]], dtype=torch.int64),
            "frames": _valid_frames(m),
            "timestamps": self.timestamps[m],
            "rotations": self.rotations[m].to(torch.float32),
            "joints": self.joints[m].to(torch.float32),
            "marker_indices": self.marker_indices.to(torch.int64),
            "markers": self.markers[m].to(torch.float32),
            "trans": self.trans[m].to(torch.float32),
            "shapes": self.shapes.to(torch.float32),
        }


@dataclass
class GroundTruth:
    """The clean posed body at the observation timestamps, and what regenerates it elsewhere.

    vertices:   (B, T, V, 3) metres.
    joints:     (B, T, 22, 3) metres.
    timestamps: (B, T) float64 seconds.
    frame_mask: (B, T) bool; padded frames hold the pose at the motion's last frame.
    motions:    the B source motions (``benchmark.motion.Motion``).
    shapes:     (B, S) the body shapes used.
    body:       the body model that posed them.
    """

    vertices: torch.Tensor
    joints: torch.Tensor
    timestamps: torch.Tensor
    frame_mask: torch.Tensor
    motions: tuple
    shapes: torch.Tensor
    body: torch.nn.Module = field(repr=False)

    def at(self, timestamps: torch.Tensor, frame_mask: torch.Tensor | None = None,
           chunk_frames: int = DEFAULT_CHUNK_FRAMES) -> "GroundTruth":
        """Ground truth at other timestamps ((B, T') or (T',) seconds), same body and shapes."""
        return ground_truth_at(self.body, self.motions, timestamps, shapes=self.shapes,
                               frame_mask=frame_mask, chunk_frames=chunk_frames)


# --------------------------------------------------------------------------- surface sampling
def sample_surface(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    num_points: int,
    generator: torch.Generator | None,
    noise_std: float = 0.0,
) -> torch.Tensor:
    """Points sampled uniformly over the area of a triangle mesh, independently per frame.

    vertices: (..., V, 3) e.g. (B, T, V, 3) metres; faces: (F, 3) long; num_points: N.
    Each point picks a triangle with probability proportional to its area (in that frame's
    posed mesh), then uniform barycentric coordinates by the square-root trick:
    ``p = (1 - sqrt(r1)) a + sqrt(r1) (1 - r2) b + sqrt(r1) r2 c``, r1, r2 ~ U[0, 1).
    Optional isotropic Gaussian noise of std ``noise_std`` metres is added to each coordinate.

    Draw order (for reproducibility): triangle uniforms (..., N) float64, then barycentric
    uniforms (..., N, 2), then (only when noise_std > 0) the noise (..., N, 3); so the same seed
    gives the same noiseless points with or without noise. ``generator=None`` uses torch's
    global RNG (not reproducible across calls).
    Returns (..., N, 3) in the dtype and on the device of ``vertices``.
    """
    if vertices.dim() < 2 or vertices.shape[-1] != 3:
        raise ValueError(f"sample_surface: vertices must be (..., V, 3), got {tuple(vertices.shape)}")
    if faces.dim() != 2 or faces.shape[-1] != 3 or faces.shape[0] == 0:
        raise ValueError(f"sample_surface: faces must be a non-empty (F, 3) index tensor, got {tuple(faces.shape)}")
    if num_points < 0:
        raise ValueError(f"sample_surface: num_points must be >= 0, got {num_points}")
    if noise_std < 0:
        raise ValueError(f"sample_surface: noise_std is a standard deviation in metres, got {noise_std} < 0")
    lead = vertices.shape[:-2]
    V = vertices.shape[-2]
    faces = faces.to(device=vertices.device, dtype=torch.long)
    if int(faces.min()) < 0 or int(faces.max()) >= V:
        raise ValueError(f"sample_surface: faces index vertices outside [0, {V})")
    flat = vertices.reshape(-1, V, 3)
    K = flat.shape[0]

    gen_device = generator.device if generator is not None else torch.device("cpu")
    r_face = torch.rand(K, num_points, dtype=torch.float64, generator=generator, device=gen_device)
    r_bary = torch.rand(K, num_points, 2, dtype=vertices.dtype, generator=generator, device=gen_device)
    noise = None
    if noise_std > 0:
        noise = torch.randn(K, num_points, 3, dtype=vertices.dtype, generator=generator, device=gen_device)
    r_face = r_face.to(vertices.device)
    r_bary = r_bary.to(vertices.device)

    out = vertices.new_empty(K, num_points, 3)
    for start in range(0, K, _SAMPLE_CHUNK_FRAMES):
        v = flat[start : start + _SAMPLE_CHUNK_FRAMES]  # (k, V, 3)
        tri = v[:, faces]  # (k, F, 3, 3)
        a, b, c = tri.unbind(-2)
        area = torch.linalg.cross(b - a, c - a).norm(dim=-1).to(torch.float64)  # 2x area, (k, F)
        cdf = area.cumsum(-1)
        total = cdf[:, -1:]
        if not bool((total > 0).all()) or not bool(torch.isfinite(total).all()):
            bad = int(torch.nonzero(~(total[:, 0] > 0) | ~torch.isfinite(total[:, 0]))[0]) + start
            raise ValueError(
                f"sample_surface: frame {bad} (flattened over {tuple(lead)}) has zero or non-finite "
                "surface area; check the vertices (all zeros? NaN?)"
            )
        u = r_face[start : start + v.shape[0]] * total
        idx = torch.searchsorted(cdf, u, right=True).clamp_(max=faces.shape[0] - 1)  # (k, N)
        rows = torch.arange(v.shape[0], device=v.device)[:, None]
        corners = tri[rows, idx]  # (k, N, 3, 3)
        s = r_bary[start : start + v.shape[0], :, 0:1].sqrt()
        r2 = r_bary[start : start + v.shape[0], :, 1:2]
        out[start : start + v.shape[0]] = (
            (1 - s) * corners[..., 0, :] + s * (1 - r2) * corners[..., 1, :] + s * r2 * corners[..., 2, :]
        )
    if noise is not None:
        out = out + noise_std * noise.to(vertices.device)
    return out.reshape(*lead, num_points, 3)


# --------------------------------------------------------------------------- posing motions
def _body_float(body: torch.nn.Module) -> tuple[torch.dtype, torch.device]:
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


def _stack_shapes(body, motions: Sequence, shapes: torch.Tensor | None, dtype, device) -> torch.Tensor:
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


def _resample_stack(motions: Sequence, timestamps: torch.Tensor, frame_mask: torch.Tensor):
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


def ground_truth_at(
    body,
    motions: Sequence,
    timestamps: torch.Tensor,
    shapes: torch.Tensor | None = None,
    frame_mask: torch.Tensor | None = None,
    chunk_frames: int = DEFAULT_CHUNK_FRAMES,
) -> GroundTruth:
    """Pose ``body`` with ``motions`` resampled at ``timestamps``.

    timestamps: (B, T) or (T,) (shared) seconds; frame_mask: (B, T) bool (default: all True).
    Real frames must lie inside each motion's time span (error otherwise); padded frames are
    posed at the nearest end of the span. shapes: (B, S) or (S,); default: each motion's own
    ``shape`` (the body's default shape where it has none).
    """
    return _pose_motions(body, motions, timestamps, shapes, frame_mask, chunk_frames)[0]


def _pose_motions(body, motions, timestamps, shapes, frame_mask, chunk_frames):
    """ground_truth_at, also returning the resampled poses (B, T, 22, 3) and trans (B, T, 3)."""
    motions = tuple(motions)
    B = len(motions)
    if B == 0:
        raise ValueError("no motions given")
    dtype, device = _body_float(body)
    timestamps = torch.as_tensor(timestamps, dtype=torch.float64).cpu()
    if timestamps.dim() == 1:
        timestamps = timestamps.expand(B, -1)
    if timestamps.dim() != 2 or timestamps.shape[0] != B:
        raise ValueError(f"timestamps must be (batch, T) = ({B}, T) or (T,), got {tuple(timestamps.shape)}")
    if frame_mask is None:
        frame_mask = torch.ones(timestamps.shape, dtype=torch.bool)
    frame_mask = torch.as_tensor(frame_mask, dtype=torch.bool).cpu()
    if frame_mask.shape != timestamps.shape:
        raise ValueError(f"frame_mask must match timestamps {tuple(timestamps.shape)}, got {tuple(frame_mask.shape)}")
    shapes = _stack_shapes(body, motions, shapes, dtype, device)
    poses, trans = _resample_stack(motions, timestamps, frame_mask)
    poses = poses.to(device=device, dtype=dtype)
    trans = trans.to(device=device, dtype=dtype)
    vertices, joints = pose_body(body, roma.rotvec_to_rotmat(poses), trans, shapes, chunk_frames)
    gt = GroundTruth(
        vertices=vertices, joints=joints, timestamps=timestamps.to(device), frame_mask=frame_mask.to(device),
        motions=motions, shapes=shapes, body=body,
    )
    return gt, poses, trans


# --------------------------------------------------------------------------- observations
def make_scans(
    body,
    motions: Sequence,
    fps: float = 50.0,
    num_points: int = 10000,
    noise_std: float = 0.0,
    seed: int = 0,
    duration: float | None = None,
    shapes: torch.Tensor | None = None,
    chunk_frames: int = DEFAULT_CHUNK_FRAMES,
) -> tuple[PointCloudSequence, GroundTruth]:
    """Dense synthetic scans of ``body`` performing ``motions``, and their ground truth.

    The motions are resampled on the capture grid of :func:`capture_timestamps` (``fps``,
    ``duration``), posed (in chunks), and ``num_points`` points are sampled per frame uniformly
    over the posed surface's area (:func:`sample_surface`), independently per frame, with optional
    Gaussian noise of std ``noise_std`` metres. Padded frames get no points (length 0).
    Sampling draws from one ``torch.Generator`` seeded with ``seed`` (CPU), sequence by sequence,
    so the result does not depend on ``chunk_frames``.
    Returns (PointCloudSequence with points (B, T, N, 3), GroundTruth at the same timestamps).
    """
    motions = tuple(motions)
    timestamps, frame_mask = capture_timestamps(motions, fps, duration)
    gt = ground_truth_at(body, motions, timestamps, shapes=shapes, frame_mask=frame_mask, chunk_frames=chunk_frames)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        points = torch.cat(
            [sample_surface(gt.vertices[b : b + 1], body.faces, num_points, generator, noise_std)
             for b in range(len(motions))]
        )
    mask = gt.frame_mask
    points = points * mask[..., None, None]
    lengths = mask.to(torch.long) * num_points
    scans = PointCloudSequence(points=points, lengths=lengths, timestamps=gt.timestamps, frame_mask=mask)
    return scans, gt


def make_landmarks(
    source: torch.Tensor | GroundTruth,
    body,
    noise_std: float = 0.0,
    generator: torch.Generator | None = None,
    timestamps: torch.Tensor | None = None,
    frame_mask: torch.Tensor | None = None,
) -> Landmarks:
    """The 16 markers (``body.landmark_indices``, LANDMARK_NAMES order) of posed meshes.

    source: a GroundTruth (its timestamps and frame mask are used), or vertices (B, T, V, 3)
    together with ``timestamps`` (B, T). Optional Gaussian noise of std ``noise_std`` metres per
    coordinate, drawn from ``generator`` (required when noise_std > 0). Padded frames are zeros.
    """
    if isinstance(source, GroundTruth):
        vertices = source.vertices
        timestamps = source.timestamps if timestamps is None else timestamps
        frame_mask = source.frame_mask if frame_mask is None else frame_mask
    else:
        vertices = source
        if timestamps is None:
            raise ValueError(
                "make_landmarks: vertices carry no timestamps; pass timestamps=(B, T) seconds, "
                "or pass the GroundTruth from make_scans instead of its vertices"
            )
    if vertices.dim() != 4 or vertices.shape[-1] != 3:
        raise ValueError(f"make_landmarks: vertices must be (B, T, V, 3), got {tuple(vertices.shape)}")
    if noise_std < 0:
        raise ValueError(f"make_landmarks: noise_std is a standard deviation in metres, got {noise_std} < 0")
    if noise_std > 0 and generator is None:
        raise ValueError(
            "make_landmarks: noise_std > 0 needs a torch.Generator (generator=...) so the noise is reproducible"
        )
    idx = body.landmark_indices.to(vertices.device)
    positions = vertices.index_select(-2, idx)
    if noise_std > 0:
        noise = torch.randn(positions.shape, dtype=positions.dtype, generator=generator, device=generator.device)
        positions = positions + noise_std * noise.to(positions.device)
    mask = _default_mask(None if frame_mask is None else frame_mask.to(positions.device), positions)
    positions = positions * mask[..., None, None]
    return Landmarks(positions=positions, timestamps=torch.as_tensor(timestamps), frame_mask=mask)


def farthest_point_indices(points: torch.Tensor, count: int) -> torch.Tensor:
    """Greedy farthest-point subset of (P, 3) points: (count,) long indices.

    Starts at the point farthest from the centroid; each next point maximises its distance to
    the points already chosen (ties: the lowest index). Deterministic.
    """
    if points.dim() != 2 or points.shape[-1] != 3:
        raise ValueError(f"farthest_point_indices: points must be (P, 3), got {tuple(points.shape)}")
    P = points.shape[0]
    if not 1 <= count <= P:
        raise ValueError(f"farthest_point_indices: count must be in [1, {P}], got {count}")
    pts = points.to(torch.float64)
    chosen = torch.empty(count, dtype=torch.long, device=points.device)
    chosen[0] = torch.argmax((pts - pts.mean(0)).norm(dim=-1))
    dist = (pts - pts[chosen[0]]).norm(dim=-1)
    for i in range(1, count):
        chosen[i] = torch.argmax(dist)
        dist = torch.minimum(dist, (pts - pts[chosen[i]]).norm(dim=-1))
    return chosen


def virtual_marker_indices(body, count: int = DEFAULT_NUM_MARKERS, shape: torch.Tensor | None = None) -> torch.Tensor:
    """(count,) long: the denoise table's virtual markers, a farthest-point subset of the mesh
    vertices in the T-pose (zero rotations, zero translation) of ``shape`` (default: the body's
    default shape). Deterministic for a given body."""
    dtype, device = _body_float(body)
    shape = body.default_shape(1) if shape is None else torch.as_tensor(shape).reshape(1, -1)
    rot = torch.eye(3, dtype=dtype, device=device).expand(1, 1, NUM_JOINTS, 3, 3)
    with torch.no_grad():
        rest = body(rot, torch.zeros(1, 1, 3, dtype=dtype, device=device), shape.to(device=device, dtype=dtype))
    return farthest_point_indices(rest.vertices[0, 0], count)


def make_noisy_joints(
    motions: Sequence,
    sigma: float,
    seed: int = 0,
    *,
    body,
    marker_indices: torch.Tensor | None = None,
    fps: float | None = None,
    duration: float | None = None,
    shapes: torch.Tensor | None = None,
    chunk_frames: int = DEFAULT_CHUNK_FRAMES,
) -> tuple[NoisyJoints, GroundTruth]:
    """Noisy motion capture (denoise table): Gaussian noise on every joint's axis-angle rotation.

    Frames: each motion's own timestamps (padded to the longest), or, when ``fps`` is given, the
    capture grid of :func:`capture_timestamps` (``fps``, ``duration``).
    Noise: ``sigma`` (rad) times N(0, 1) added to each of the 22 x 3 axis-angle components of every
    frame (root orientation included; translation and shape stay clean), drawn as one
    (B, T, 22, 3) tensor from ``torch.Generator().manual_seed(seed)``.
    Markers: the vertices ``marker_indices`` (default :func:`virtual_marker_indices`, 43 vertices)
    of the body posed with the noisy rotations.
    Returns (NoisyJoints, GroundTruth of the clean motion at the same timestamps).
    """
    if sigma < 0:
        raise ValueError(f"make_noisy_joints: sigma is a standard deviation in radians, got {sigma} < 0")
    motions = tuple(motions)
    if fps is not None:
        timestamps, frame_mask = capture_timestamps(motions, fps, duration)
    else:
        if duration is not None:
            raise ValueError("make_noisy_joints: duration needs fps (the capture grid); pass fps=... or drop duration")
        if len(motions) == 0:
            raise ValueError("no motions given")
        rows = [torch.as_tensor(m.timestamps, dtype=torch.float64).reshape(-1) for m in motions]
        T = max(r.numel() for r in rows)
        timestamps = torch.stack([torch.cat([r, r[-1:].expand(T - r.numel())]) for r in rows])
        frame_mask = torch.arange(T)[None, :] < torch.tensor([r.numel() for r in rows])[:, None]
    gt, clean, trans = _pose_motions(body, motions, timestamps, shapes, frame_mask, chunk_frames)
    dtype, device = _body_float(body)
    if marker_indices is None:
        marker_indices = virtual_marker_indices(body)
    marker_indices = torch.as_tensor(marker_indices, dtype=torch.long, device=device)
    V = gt.vertices.shape[-2]
    if marker_indices.dim() != 1 or marker_indices.numel() == 0 or not bool(
        ((marker_indices >= 0) & (marker_indices < V)).all()
    ):
        raise ValueError(
            f"make_noisy_joints: marker_indices must be a non-empty (M,) tensor of vertex indices in [0, {V}), "
            f"got shape {tuple(marker_indices.shape)}"
        )
    generator = torch.Generator().manual_seed(seed)
    noise = torch.randn(clean.shape, dtype=dtype, generator=generator).to(device)
    noisy = clean + sigma * noise
    vertices, joints = pose_body(body, roma.rotvec_to_rotmat(noisy), trans, gt.shapes, chunk_frames)
    mask = gt.frame_mask
    keep = mask[..., None, None]
    obs = NoisyJoints(
        rotations=noisy * keep, joints=joints * keep, markers=vertices.index_select(-2, marker_indices) * keep,
        marker_indices=marker_indices, trans=trans * mask[..., None], shapes=gt.shapes,
        timestamps=gt.timestamps, frame_mask=mask, sigma=float(sigma),
    )
    return obs, gt
