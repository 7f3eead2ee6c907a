"""The motion representation chi of Marsot et al. (3DV 2022, paper 001 §3.1, Supp. §1-2).

One motion = n = 100 timestamped anchor frames; per anchor (124 numbers, in this order):

- pose theta (120): the 20 joints of :data:`JOINTS` (SMPL-22 minus the feet 10 and 11, which the
  paper drops because AMASS keeps them constant), each as 6D (Zhou et al.) in the **"columns"**
  layout (first column then second column of the rotation matrix) minus the identity
  [1, 0, 0, 0, 1, 0] (the paper's identity vector is the concatenated-columns 6D of I); joint-major.
  The root (joint 0) is included: chi encodes the root orientation.
- translation gamma (3): root translation (m) min-max normalised to [-1, 1]^3 with the training
  set's per-axis min and max (stored with the weights).
- timestamp tau (1): seconds since the first anchor, min-max normalised to [0, 1] with the
  training set's range (min 0, max = the longest training motion; stored with the weights).

Alignment (Supp. §1: "zeroing the initial translation and [using] the identity rotation as
initial rotation of the root joint to be invariant in the ground plane"), read here as removing the
ground-plane pose only (y-up world): the initial root heading (yaw about +y of the root's +z axis)
is removed from the root rotation and the translation, and the initial translation is zeroed in
the ground plane (x, z); the height and the initial pitch/roll are kept, since the body's lean
and height are part of the motion. The inverse is ``world = R_y(yaw0) @ canonical + offset0``.
"""

from __future__ import annotations

from dataclasses import dataclass

import roma
import torch

from benchmark.core.frames import from_heading_frame, ground_origin, heading, to_heading_frame
from benchmark.core.frames import sixd_columns_to_matrix as gram_schmidt
from benchmark.core.interpolate import lerp_frames, slerp_frames
from benchmark.core.rotations import matrix_to_sixd
from benchmark.core.skeleton import NUM_JOINTS

ANCHORS = 100
FOOT_JOINTS = (10, 11)
JOINTS = tuple(j for j in range(NUM_JOINTS) if j not in FOOT_JOINTS)  # 20 joints, root included
NUM_MODEL_JOINTS = len(JOINTS)
POSE_DIM = 6 * NUM_MODEL_JOINTS  # 120
FEATURES = POSE_DIM + 3 + 1  # 124
POSE = slice(0, POSE_DIM)
TRANS = slice(POSE_DIM, POSE_DIM + 3)
TIME = POSE_DIM + 3
SIXD_LAYOUT = "columns"
IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


def anchor_times(t0: torch.Tensor, t1: torch.Tensor, n: int = ANCHORS) -> torch.Tensor:
    """(B,) start and end times -> (B, n) uniformly spaced instants, both ends included."""
    u = torch.linspace(0.0, 1.0, n, dtype=torch.float64, device=t0.device)
    t0 = t0.to(torch.float64)[:, None]
    return t0 + (t1.to(torch.float64)[:, None] - t0) * u


def resample_anchors(rotations: torch.Tensor, trans: torch.Tensor, timestamps: torch.Tensor,
                     n: int = ANCHORS) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Motions (B, T, 22, 3, 3), (B, T, 3) at timestamps (B, T) -> n anchors uniformly in time over
    [t_first, t_last] of each: rotations (B, n, 22, 3, 3) (SLERP), translation (B, n, 3) (LERP),
    tau (B, n) seconds since the first anchor (float64)."""
    if rotations.dim() != 5 or rotations.shape[2:] != (NUM_JOINTS, 3, 3):
        raise ValueError(f"rotations must be (B, T, 22, 3, 3), got {tuple(rotations.shape)}")
    B, T = rotations.shape[:2]
    if trans.shape != (B, T, 3) or timestamps.shape != (B, T):
        raise ValueError(f"trans must be {(B, T, 3)} and timestamps {(B, T)}, got {tuple(trans.shape)}, {tuple(timestamps.shape)}")
    if T < 2:
        raise ValueError("a motion needs at least 2 frames to be resampled to anchors")
    ts = timestamps.to(torch.float64)
    dst = anchor_times(ts[:, 0], ts[:, -1], n)
    rot = slerp_frames(rotations, ts, dst)
    tr = lerp_frames(trans, ts, dst)
    return rot, tr, dst - dst[:, :1]


def yaw_matrix(yaw: torch.Tensor) -> torch.Tensor:
    """(...) angles -> (..., 3, 3) rotations about +y, by roma's rotation-vector map (this prior's
    weights were trained with it; :func:`benchmark.core.frames.yaw_matrix`, the cos/sin form, differs
    in the last bits)."""
    zero = torch.zeros_like(yaw)
    return roma.rotvec_to_rotmat(torch.stack([zero, yaw, zero], dim=-1))


def canonical_frame(rotations: torch.Tensor, trans: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The initial heading yaw0 (B,) and ground-plane offset (B, 3) = (x0, 0, z0) of motions."""
    yaw0 = heading(rotations[:, 0, 0])
    offset = ground_origin(trans)
    return yaw0, offset


def canonicalise(rotations: torch.Tensor, trans: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Remove the initial heading and ground-plane position (module docstring).

    rotations (B, n, 22, 3, 3), trans (B, n, 3) -> (rotations, trans, yaw0 (B,), offset (B, 3)) with
    world = R_y(yaw0) @ canonical + offset (root rotation: R_y(yaw0) @ canonical root).
    """
    yaw0, offset = canonical_frame(rotations, trans)
    rot, tr = to_heading_frame(rotations, trans, yaw_matrix(-yaw0).to(rotations.dtype), offset)
    return rot, tr, yaw0, offset


def uncanonicalise(rotations: torch.Tensor, trans: torch.Tensor, yaw0: torch.Tensor, offset: torch.Tensor):
    """Inverse of :func:`canonicalise`."""
    return from_heading_frame(rotations, trans, yaw_matrix(yaw0).to(rotations.dtype), offset)


@dataclass
class Normalisation:
    """Training-set statistics of chi's translation and timestamps (min-max scaling, Supp. §2)."""

    trans_min: tuple[float, float, float]
    trans_max: tuple[float, float, float]
    tau_max: float  # seconds (tau_min is 0: the first anchor)

    @classmethod
    def fit(cls, trans: torch.Tensor, tau: torch.Tensor, min_range: float = 1e-3) -> "Normalisation":
        """From canonical translations (N, n, 3) and timestamps (N, n) (seconds since the start).
        An axis spanning less than ``min_range`` m is widened symmetrically to it."""
        flat = trans.reshape(-1, 3).to(torch.float64)
        lo, hi = flat.min(0).values, flat.max(0).values
        mid, half = (lo + hi) / 2, ((hi - lo) / 2).clamp_min(min_range / 2)
        tau_max = float(tau.max())
        if not tau_max > 0:
            raise ValueError("Normalisation.fit: every training motion has zero duration")
        return cls(tuple(float(x) for x in mid - half), tuple(float(x) for x in mid + half), tau_max)

    def to_dict(self) -> dict:
        return {"trans_min": list(self.trans_min), "trans_max": list(self.trans_max), "tau_max": self.tau_max}

    @classmethod
    def from_dict(cls, d: dict) -> "Normalisation":
        try:
            return cls(tuple(float(x) for x in d["trans_min"]), tuple(float(x) for x in d["trans_max"]), float(d["tau_max"]))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"normalisation record needs 'trans_min', 'trans_max' (3 each) and 'tau_max', got {d!r}") from exc


def identity_6d(like: torch.Tensor) -> torch.Tensor:
    return like.new_tensor(IDENTITY_6D)


def motion_to_chi(rotations: torch.Tensor, trans: torch.Tensor, tau: torch.Tensor, trans_min: torch.Tensor,
                  trans_max: torch.Tensor, tau_max: torch.Tensor | float) -> torch.Tensor:
    """Canonical anchors -> chi (B, n, 124): rotations (B, n, 22, 3, 3), trans (B, n, 3) metres,
    tau (B, n) seconds since the first anchor. Float32."""
    pose = matrix_to_sixd(rotations[:, :, list(JOINTS)].float(), SIXD_LAYOUT) - identity_6d(trans.float())
    tmin, tmax = torch.as_tensor(trans_min).float(), torch.as_tensor(trans_max).float()
    gamma = 2 * (trans.float() - tmin) / (tmax - tmin) - 1
    t = tau.float() / torch.as_tensor(tau_max).float()
    return torch.cat([pose.flatten(-2), gamma, t[..., None]], dim=-1)


def expand_joints(model_rot: torch.Tensor) -> torch.Tensor:
    """(..., 20, 3, 3) rotations of :data:`JOINTS` -> (..., 22, 3, 3) with identity feet."""
    a = FOOT_JOINTS[0]  # the feet are contiguous (10, 11)
    # "x * 0" keeps the batch dimensions symbolic when traced (zeros_like / expand would freeze them)
    eye = model_rot[..., : len(FOOT_JOINTS), :, :] * 0 + torch.eye(3, dtype=model_rot.dtype, device=model_rot.device)
    return torch.cat([model_rot[..., :a, :, :], eye, model_rot[..., a:, :, :]], dim=-3)


def sixd_columns_to_matrix(x: torch.Tensor) -> torch.Tensor:
    """(..., 6) "columns" 6D -> (..., 3, 3) by Gram-Schmidt with norms clamped at 1e-12
    (:func:`benchmark.core.frames.sixd_columns_to_matrix`: elementwise ops, so a traced graph keeps
    every batch dimension dynamic; roma's flatten / unflatten freeze them)."""
    return gram_schmidt(x, eps=1e-12)


def chi_to_motion(chi: torch.Tensor, trans_min: torch.Tensor, trans_max: torch.Tensor,
                  tau_max: torch.Tensor | float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """chi (B, n, 124) -> rotations (B, n, 22, 3, 3) (Gram-Schmidt, identity feet), trans (B, n, 3)
    metres, tau (B, n) seconds. No data-dependent control flow (traceable)."""
    pose = chi[..., POSE].unflatten(-1, (NUM_MODEL_JOINTS, 6)) + identity_6d(chi)
    rot = expand_joints(sixd_columns_to_matrix(pose))
    tmin, tmax = torch.as_tensor(trans_min).to(chi), torch.as_tensor(trans_max).to(chi)
    trans = (chi[..., TRANS] + 1) / 2 * (tmax - tmin) + tmin
    tau = chi[..., TIME] * torch.as_tensor(tau_max).to(chi)
    return rot, trans, tau


__all__ = [
    "ANCHORS", "FOOT_JOINTS", "JOINTS", "NUM_MODEL_JOINTS", "POSE_DIM", "FEATURES", "POSE", "TRANS", "TIME",
    "SIXD_LAYOUT", "IDENTITY_6D", "anchor_times", "resample_anchors", "heading", "yaw_matrix", "canonical_frame",
    "canonicalise", "uncanonicalise", "Normalisation", "motion_to_chi", "chi_to_motion", "expand_joints",
    "sixd_columns_to_matrix",
]
