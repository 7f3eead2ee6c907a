"""Observations synthesised from a body and motions, and the ground truth kept beside them.

The data structures are dataclasses of tensors, batch dimension first:

- :class:`PointCloudSequence`: dense or degraded scans, (B, T, N, 3) padded points.
- :class:`Landmarks`: the 16 MoCap-style markers of :data:`benchmark.core.skeleton.LANDMARK_NAMES`.
- :class:`NoisyJoints`: noisy local joint rotations plus noisy virtual-marker vertices (denoise table).
- :class:`GroundTruth`: the posed mesh and joints at the capture timestamps, and the motions,
  shapes and body that regenerate them at any other timestamp (:meth:`GroundTruth.at`).

Padding: sequences of different lengths share one (B, T) grid; ``frame_mask`` marks the real
frames, and the padded frames hold zeros (points, landmarks) or the pose at the motion's last
frame (ground truth, so every tensor stays finite). Within a frame only the first ``lengths``
points are real; the rest are zeros.

Units: metres, seconds, radians. Timestamps are float64 seconds.

The ``Motion`` objects consumed here follow :class:`benchmark.core.motion.Motion`: ``poses`` (T, 22, 3)
axis-angle local rotations, ``trans`` (T, 3) metres, ``timestamps`` (T,) seconds, ``shape`` (S,)
or None, ``resample(timestamps) -> Motion``. Only that interface is used (duck typing).

Randomness: every function takes a seed or a ``torch.Generator`` and draws in a documented
order, so the same seed gives the same observation. Random numbers are drawn on the generator's
device and then moved, so a CPU generator gives the same samples whatever device the body is on.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import roma
import torch

from benchmark.core.motion_posing import (
    DEFAULT_CHUNK_FRAMES,
    body_float,
    capture_timestamps,
    pose_body,
    resample_stack,
    stack_shapes,
)
from benchmark.core.skeleton import LANDMARK_NAMES, NUM_JOINTS, NUM_LANDMARKS
from benchmark.core.surface_sampling import (
    farthest_point_indices,
    sample_surface,
)

# Default number of virtual markers for the denoise table (MoSh / HuMoR use 43 marker vertices).
DEFAULT_NUM_MARKERS = 43


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
        """What defines this observation, independent of padding (see :func:`benchmark.data.degrade.fingerprint`)."""
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
    motions:    the B source motions (``benchmark.core.motion.Motion``).
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


# --------------------------------------------------------------------------- ground truth
# (sampling a mesh surface: benchmark.core.surface_sampling; posing motions: benchmark.core.motion_posing)
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
    dtype, device = body_float(body)
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
    shapes = stack_shapes(body, motions, shapes, dtype, device)
    poses, trans = resample_stack(motions, timestamps, frame_mask)
    poses = poses.to(device=device, dtype=dtype)
    trans = trans.to(device=device, dtype=dtype)
    vertices, joints = pose_body(body, roma.rotvec_to_rotmat(poses), trans, shapes, chunk_frames)
    gt = GroundTruth(
        vertices=vertices, joints=joints, timestamps=timestamps.to(device), frame_mask=frame_mask.to(device),
        motions=motions, shapes=shapes, body=body,
    )
    return gt, poses, trans


# --------------------------------------------------------------------------- observations
def seed_generators(seed: int | Sequence[int], batch: int, caller: str) -> list[torch.Generator]:
    """One CPU generator per sequence of a batch of ``batch``: ``seed`` an int gives one generator
    shared by them all (each draws after the one before it), a list of ``batch`` ints one
    generator each (a sequence's draws then do not depend on the rest of the batch)."""
    if isinstance(seed, (list, tuple)):
        if len(seed) != batch or not all(isinstance(s, int) and not isinstance(s, bool) for s in seed):
            raise ValueError(f"{caller}: `seed` must be an int or a list of {batch} ints (one per sequence); got {seed!r}")
        return [torch.Generator().manual_seed(int(s)) for s in seed]
    shared = torch.Generator().manual_seed(int(seed))
    return [shared] * batch


def make_scans(
    body,
    motions: Sequence,
    fps: float = 50.0,
    num_points: int = 10000,
    noise_std: float = 0.0,
    seed: int | Sequence[int] = 0,
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
    so the result does not depend on ``chunk_frames``; ``seed`` a list of one int per motion: each
    sequence draws from its own generator, so its points do not depend on the rest of the batch.
    Returns (PointCloudSequence with points (B, T, N, 3), GroundTruth at the same timestamps).
    """
    motions = tuple(motions)
    timestamps, frame_mask = capture_timestamps(motions, fps, duration)
    gt = ground_truth_at(body, motions, timestamps, shapes=shapes, frame_mask=frame_mask, chunk_frames=chunk_frames)
    generators = seed_generators(seed, len(motions), "make_scans")
    with torch.no_grad():
        points = torch.cat(
            [sample_surface(gt.vertices[b : b + 1], body.faces, num_points, generators[b], noise_std)
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



def virtual_marker_indices(body, count: int = DEFAULT_NUM_MARKERS, shape: torch.Tensor | None = None) -> torch.Tensor:
    """(count,) long: the denoise table's virtual markers, a farthest-point subset of the mesh
    vertices in the T-pose (zero rotations, zero translation) of ``shape`` (default: the body's
    default shape). Deterministic for a given body."""
    dtype, device = body_float(body)
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
    dtype, device = body_float(body)
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
